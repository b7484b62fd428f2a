"""Depth fusion of a whole unbounded scene: a sparse TSDF over the contracted cube (`trisplat.mesh.contraction`).

A capture without alpha (a room, a table, a street) has content from the cameras out to the walls and beyond; one
dense grid fine enough for the table cannot hold the room. Here the scene is fused in contracted coordinates, where a
voxel's world size grows with its distance (the far wall costs about what the near table does), and only where the
views measured something: the cube is cut into blocks of BLOCK^3 voxels, and a block is allocated (voxel hashing,
with a dense block index) only along the rays of the depth maps near their surfaces. Everything else is free space
(+1), which is what the dense rule gives there too: in front of every surface, or farther than `max_depth` behind it.

The field follows `trisplat.mesh.fusion` voxel for voxel (read its docstring): each voxel averages the clipped
signed distances `(depth - voxel depth) / truncation` of the views that see it in front of or near their surface,
occluded views add a weak vote for solid, voxels inside some view but behind every surface are solid, and solid
farther than `max_depth` from any observed voxel (in the truncation band) becomes free along a ramp of one truncation.
Differences, all from the contraction: the truncation is `truncation_voxels` contracted voxels, in world units
`truncation_voxels * voxel * stretch` at each voxel (`contraction.stretch`: 1 in the inner cube, m^2 beyond it);
`max_depth` is measured in contracted voxels; its distance transform runs on a grid twice as coarse (the cut of
unseen space lands within a voxel or two of where the fine one puts it). Marching cubes runs on slabs of the cube,
welded where they meet; vertices are returned in contracted coordinates (decimate there: a quadric error is then
about the same number of pixels everywhere), `uncontract` maps them back.

Conventions: the grid covers `[-extent, extent]^3` of the contracted cube with `size` voxels per axis, voxel centres
at `-extent + (ijk + 0.5) * voxel`, indexed along x, y, z. Depth maps as in `trisplat.mesh.fusion` (view depth,
inf = nothing seen, nan = unknown).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from trisplat.mesh.contraction import OUTER, contract_point, uncontract_point
from trisplat.mesh.fusion import OCCLUSION_WEIGHT, _check_depth

BLOCK = 8  # voxels along a block's edge (blocks are allocated whole)
BV = BLOCK**3
EDT_COARSENING = 2  # the unseen-space cut's distance transform runs on voxels this many times larger
SLAB = 64  # voxels along x per marching-cubes slab
MAX_VOXELS = 160_000_000  # allocated voxels above this are refused (memory: 10 bytes per voxel)


@dataclass(frozen=True)
class ContractedGrid:
    """The voxel lattice over the contracted cube `[-extent, extent]^3`: `size` voxels per axis (a multiple of
    BLOCK), voxel edge `voxel` (contracted units = world units inside the inner cube)."""

    extent: float
    size: int

    @property
    def voxel(self) -> float:
        return 2.0 * self.extent / self.size

    @property
    def blocks(self) -> int:
        return self.size // BLOCK

    @staticmethod
    def for_resolution(inner_resolution: int, extent: float) -> ContractedGrid:
        """The lattice with `inner_resolution` voxels across the inner cube (side 2) that reaches at least `extent`
        (< 2), rounded up to whole blocks, and never reaching the outer cube (infinity)."""
        if not 1.0 <= extent < OUTER:
            raise ValueError(f"the contracted extent must lie in [1, {OUTER}), got {extent}")
        if int(inner_resolution) < 8:
            raise ValueError(f"contracted fusion needs at least 8 voxels across the inner cube, got {inner_resolution}")
        voxel = 2.0 / int(inner_resolution)
        size = BLOCK * math.ceil(2.0 * extent / voxel / BLOCK)
        while size * voxel / 2.0 >= OUTER - 0.5 * voxel:
            size -= BLOCK
        return ContractedGrid(size * voxel / 2.0, int(size))


@nb.njit(cache=True)
def _mark_rays(w2c_inv, Kinv, depth, origin, voxel, nblocks, front, back, radius, stride, mask):
    """Mark in `mask` [NB,NB,NB] the blocks that the samples along each finite-depth pixel's ray visit, from `front`
    contracted voxels in front of its surface point to `back` behind it (steps of half a block), inside the world
    ball of `radius`. Serial (called for one view at a time from a parallel loop over views is not worth its races)."""
    H, W = depth.shape
    step = 0.5 * BLOCK
    n_steps = int(math.ceil((front + back) / step)) + 1
    for r in range(0, H, stride):
        for c in range(0, W, stride):
            d = depth[r, c]
            if not np.isfinite(d) or d <= 0.0:
                continue
            x, y = c + 0.5, r + 0.5
            rx = Kinv[0, 0] * x + Kinv[0, 1] * y + Kinv[0, 2]
            ry = Kinv[1, 0] * x + Kinv[1, 1] * y + Kinv[1, 2]
            rz = Kinv[2, 0] * x + Kinv[2, 1] * y + Kinv[2, 2]
            # the surface point and its stretch: contracted voxels -> world depth along the ray
            px = w2c_inv[0, 0] * rx * d + w2c_inv[0, 1] * ry * d + w2c_inv[0, 2] * rz * d + w2c_inv[0, 3]
            py = w2c_inv[1, 0] * rx * d + w2c_inv[1, 1] * ry * d + w2c_inv[1, 2] * rz * d + w2c_inv[1, 3]
            pz = w2c_inv[2, 0] * rx * d + w2c_inv[2, 1] * ry * d + w2c_inv[2, 2] * rz * d + w2c_inv[2, 3]
            m = max(abs(px), max(abs(py), abs(pz)))
            st = m * m if m > 1.0 else 1.0
            per_vox = voxel * st  # world depth per contracted voxel near the surface point (rz: depth per unit ray)
            for k in range(n_steps):
                off = -front + k * step
                if off > back:
                    off = back
                dd = d + off * per_vox
                if dd <= 0.0:
                    continue
                wx = w2c_inv[0, 0] * rx * dd + w2c_inv[0, 1] * ry * dd + w2c_inv[0, 2] * rz * dd + w2c_inv[0, 3]
                wy = w2c_inv[1, 0] * rx * dd + w2c_inv[1, 1] * ry * dd + w2c_inv[1, 2] * rz * dd + w2c_inv[1, 3]
                wz = w2c_inv[2, 0] * rx * dd + w2c_inv[2, 1] * ry * dd + w2c_inv[2, 2] * rz * dd + w2c_inv[2, 3]
                if wx * wx + wy * wy + wz * wz > radius * radius:
                    continue
                cx, cy, cz = contract_point(wx, wy, wz)
                bi = int(math.floor((cx - origin) / voxel)) // BLOCK
                bj = int(math.floor((cy - origin) / voxel)) // BLOCK
                bk = int(math.floor((cz - origin) / voxel)) // BLOCK
                if 0 <= bi < nblocks and 0 <= bj < nblocks and 0 <= bk < nblocks:
                    mask[bi, bj, bk] = True


@nb.njit(cache=True, inline="always")
def _voxel_world(coords, b, q, origin, voxel):
    """World position and stretch of voxel q of block b (`uncontract_point` of its centre)."""
    i = coords[b, 0] * BLOCK + q // (BLOCK * BLOCK)
    j = coords[b, 1] * BLOCK + (q // BLOCK) % BLOCK
    k = coords[b, 2] * BLOCK + q % BLOCK
    return uncontract_point(origin + (i + 0.5) * voxel, origin + (j + 0.5) * voxel, origin + (k + 0.5) * voxel)


@nb.njit(parallel=True, cache=True)
def _block_spheres(coords, origin, voxel, centre, radius):
    """Per allocated block (coords [nb,3]): the bounding sphere (centre [nb,3], radius [nb]) of its voxel centres'
    world positions."""
    for b in nb.prange(coords.shape[0]):
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for q in range(BV):
            x0, x1, x2, _ = _voxel_world(coords, b, q, origin, voxel)
            lo[0], lo[1], lo[2] = min(lo[0], x0), min(lo[1], x1), min(lo[2], x2)
            hi[0], hi[1], hi[2] = max(hi[0], x0), max(hi[1], x1), max(hi[2], x2)
        r2 = 0.0
        for a in range(3):
            centre[b, a] = 0.5 * (lo[a] + hi[a])
            r2 += (0.5 * (hi[a] - lo[a])) ** 2
        radius[b] = math.sqrt(r2)


# fast math without the no-NaN / no-Inf assumptions (the depth maps hold both; see trisplat.mesh.fusion)
@nb.njit(parallel=True, cache=True, fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _fuse_blocks(coords, origin, voxel, centre, radius, w2c, K, planes, sizes, depths, trunc, near, occ_w, sdf_sum,
                 w_sum, in_view, band):
    """Add the votes of a batch of views (w2c [B,4,4], K [B,3,3], the frustum's four side planes through the camera
    centre planes [B,4,3] (inward normals, camera frame), sizes [B,2], depths [B,H,W]) to every allocated block's
    accumulators ([nb,BV]): `trisplat.mesh.fusion.fuse_reference`'s rule per voxel, with a truncation of
    `trunc * st` world units. A view whose frustum misses a block's bounding sphere is skipped for the block."""
    n_views = w2c.shape[0]
    for b in nb.prange(coords.shape[0]):
        world = np.empty((BV, 4))  # the block's voxel centres in the world, and their stretch
        for q in range(BV):
            world[q, 0], world[q, 1], world[q, 2], world[q, 3] = _voxel_world(coords, b, q, origin, voxel)
        for v in range(n_views):
            M = w2c[v]
            ccx = M[0, 0] * centre[b, 0] + M[0, 1] * centre[b, 1] + M[0, 2] * centre[b, 2] + M[0, 3]
            ccy = M[1, 0] * centre[b, 0] + M[1, 1] * centre[b, 1] + M[1, 2] * centre[b, 2] + M[1, 3]
            ccz = M[2, 0] * centre[b, 0] + M[2, 1] * centre[b, 1] + M[2, 2] * centre[b, 2] + M[2, 3]
            if ccz + radius[b] <= near:
                continue
            outside = False
            for p in range(4):
                if planes[v, p, 0] * ccx + planes[v, p, 1] * ccy + planes[v, p, 2] * ccz < -radius[b]:
                    outside = True
                    break
            if outside:
                continue
            Kv = K[v]
            Wv, Hv = sizes[v, 0], sizes[v, 1]
            for q in range(BV):
                x, y, z = world[q, 0], world[q, 1], world[q, 2]
                cz = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + M[2, 3]
                if cz <= near:
                    continue
                cx = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + M[0, 3]
                cy = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + M[1, 3]
                u = (Kv[0, 0] * cx + Kv[0, 1] * cy) / cz + Kv[0, 2]
                w = Kv[1, 1] * cy / cz + Kv[1, 2]
                if u < 0.0 or w < 0.0:
                    continue
                col = int(u)
                row = int(w)
                if col >= Wv or row >= Hv:
                    continue
                d = depths[v, row, col]
                if np.isnan(d):
                    continue  # unknown: this view says nothing about the voxel
                in_view[b, q] = True
                if np.isinf(d):
                    s = 1.0
                else:
                    s = (d - cz) / (trunc * world[q, 3])
                    if s < -1.0:
                        sdf_sum[b, q] -= occ_w  # occluded: a weak vote for solid
                        continue
                    if s < 1.0:
                        band[b, q] = True
                    else:
                        s = 1.0
                sdf_sum[b, q] += s
                w_sum[b, q] += 1.0


@nb.njit(parallel=True, cache=True)
def _field(sdf_sum, w_sum, in_view):
    """The field in place of sdf_sum: the mean vote where observed, -1 (solid) inside some view but never observed,
    +1 (free) in no view; clipped to [-1, 1]."""
    for b in nb.prange(sdf_sum.shape[0]):
        for q in range(BV):
            if w_sum[b, q] > 0.0:
                sdf_sum[b, q] = min(max(sdf_sum[b, q] / w_sum[b, q], -1.0), 1.0)
            else:
                sdf_sum[b, q] = -1.0 if in_view[b, q] else 1.0


@nb.njit(cache=True)
def _coarse_band(coords, band, coarse, f):
    """coarse [n,n,n] bool: a coarse voxel (f^3 voxels) holds a band voxel."""
    for b in range(coords.shape[0]):
        for q in range(BV):
            if band[b, q]:
                i = (coords[b, 0] * BLOCK + q // (BLOCK * BLOCK)) // f
                j = (coords[b, 1] * BLOCK + (q // BLOCK) % BLOCK) // f
                k = (coords[b, 2] * BLOCK + q % BLOCK) // f
                coarse[i, j, k] = True


@nb.njit(parallel=True, cache=True)
def _cut_unseen(coords, sdf, dist, f, max_depth, trunc):
    """Solid farther than max_depth (voxels) from the band becomes free along a ramp of `trunc` voxels: sdf =
    max(sdf, clip((distance - max_depth) / trunc, -1, 1)) where sdf < 0 (dist: the coarse distance transform, in
    coarse voxels)."""
    for b in nb.prange(coords.shape[0]):
        for q in range(BV):
            if sdf[b, q] < 0.0:
                i = (coords[b, 0] * BLOCK + q // (BLOCK * BLOCK)) // f
                j = (coords[b, 1] * BLOCK + (q // BLOCK) % BLOCK) // f
                k = (coords[b, 2] * BLOCK + q % BLOCK) // f
                ramp = min(max((dist[i, j, k] * f - max_depth) / trunc, -1.0), 1.0)
                if ramp > sdf[b, q]:
                    sdf[b, q] = ramp


@nb.njit(cache=True)
def _fill_slab(index, sdf, x0, y0, z0, out):
    """out [X,Y,Z]: the padded field (padded index p = voxel index + 1; +1 outside the grid and in unallocated
    blocks) on padded indices [x0, x0+X) x [y0, y0+Y) x [z0, z0+Z)."""
    X, Y, Z = out.shape
    NB = index.shape[0]
    out[:] = 1.0
    for bi in range(max((x0 - 1) // BLOCK, 0), min((x0 + X - 2) // BLOCK + 1, NB)):
        for bj in range(max((y0 - 1) // BLOCK, 0), min((y0 + Y - 2) // BLOCK + 1, NB)):
            for bk in range(max((z0 - 1) // BLOCK, 0), min((z0 + Z - 2) // BLOCK + 1, NB)):
                b = index[bi, bj, bk]
                if b < 0:
                    continue
                for q in range(BV):
                    i = bi * BLOCK + q // (BLOCK * BLOCK) + 1 - x0
                    j = bj * BLOCK + (q // BLOCK) % BLOCK + 1 - y0
                    k = bk * BLOCK + q % BLOCK + 1 - z0
                    if 0 <= i < X and 0 <= j < Y and 0 <= k < Z:
                        out[i, j, k] = sdf[b, q]


@nb.njit(cache=True, inline="always")
def _in_hull(u, v, hull):
    """Is (u, v) inside the counter-clockwise convex polygon hull [K,2]?"""
    K = hull.shape[0]
    for i in range(K):
        j = (i + 1) % K
        if (hull[j, 0] - hull[i, 0]) * (v - hull[i, 1]) - (hull[j, 1] - hull[i, 1]) * (u - hull[i, 0]) < 0.0:
            return False
    return True


@nb.njit(cache=True)
def _mark_ground(mask, origin, voxel, gvec, height, thickness, reach, hull, trunc):
    """Add to `mask` [NB,NB,NB] the blocks the ground needs: those within a truncation of the floor slab (the
    `thickness` below the floor plane) and, under every marked block within `reach` above the floor, the blocks
    down to the slab (where things standing on the floor may be filled). gvec: up, a, b [3,3]. Serial."""
    NB = mask.shape[0]
    marked = np.argwhere(mask)
    half = 0.5 * BLOCK * voxel
    for bi in range(NB):
        for bj in range(NB):
            for bk in range(NB):
                if mask[bi, bj, bk]:
                    continue
                y0 = origin + (bi * BLOCK + 0.5 * BLOCK) * voxel
                y1 = origin + (bj * BLOCK + 0.5 * BLOCK) * voxel
                y2 = origin + (bk * BLOCK + 0.5 * BLOCK) * voxel
                x0, x1, x2, st = uncontract_point(y0, y1, y2)
                m = max(abs(y0), max(abs(y1), abs(y2)))
                # world size of the block: its contracted half-diagonal times the stretch (radial) bound
                rad = math.sqrt(3.0) * half * (st if m > 1.0 else 1.0) + trunc * st
                h = x0 * gvec[0, 0] + x1 * gvec[0, 1] + x2 * gvec[0, 2]
                if h < height - thickness - rad or h > height + rad:
                    continue
                u = x0 * gvec[1, 0] + x1 * gvec[1, 1] + x2 * gvec[1, 2]
                v = x0 * gvec[2, 0] + x1 * gvec[2, 1] + x2 * gvec[2, 2]
                if _in_hull(u, v, hull):
                    mask[bi, bj, bk] = True
    for n in range(marked.shape[0]):
        y0 = origin + (marked[n, 0] * BLOCK + 0.5 * BLOCK) * voxel
        y1 = origin + (marked[n, 1] * BLOCK + 0.5 * BLOCK) * voxel
        y2 = origin + (marked[n, 2] * BLOCK + 0.5 * BLOCK) * voxel
        x0, x1, x2, st = uncontract_point(y0, y1, y2)
        h = x0 * gvec[0, 0] + x1 * gvec[0, 1] + x2 * gvec[0, 2]
        if h <= height or h > height + reach:
            continue
        u = x0 * gvec[1, 0] + x1 * gvec[1, 1] + x2 * gvec[1, 2]
        v = x0 * gvec[2, 0] + x1 * gvec[2, 1] + x2 * gvec[2, 2]
        if not _in_hull(u, v, hull):
            continue
        step = 0.5 * BLOCK * voxel  # world steps no longer than half a block where the stretch is 1
        t = 0.0
        while h - t > height - thickness:
            wx, wy, wz = x0 - t * gvec[0, 0], x1 - t * gvec[0, 1], x2 - t * gvec[0, 2]
            c0, c1, c2 = contract_point(wx, wy, wz)
            bi = int(math.floor((c0 - origin) / voxel)) // BLOCK
            bj = int(math.floor((c1 - origin) / voxel)) // BLOCK
            bk = int(math.floor((c2 - origin) / voxel)) // BLOCK
            if 0 <= bi < NB and 0 <= bj < NB and 0 <= bk < NB:
                mask[bi, bj, bk] = True
            t += step


@nb.njit(parallel=True, cache=True)
def _ground_field(coords, index, origin, voxel, sdf, weight, gvec, height, thickness, reach, hull, trunc):
    """The ground in the field (ContractedTSDF.apply_ground): the floor slab made solid within the floor's reach
    (sdf = min(sdf, slab)), then every voxel no view observed (weight 0) between the floor and something solid
    within `reach` straight above it, with only unobserved voxels between, made solid. Returns the new field."""
    out = sdf.copy()
    NB = index.shape[0]
    for b in nb.prange(coords.shape[0]):
        for q in range(BV):
            x0, x1, x2, st = _voxel_world(coords, b, q, origin, voxel)
            h = x0 * gvec[0, 0] + x1 * gvec[0, 1] + x2 * gvec[0, 2]
            tw = trunc * st
            if h > height + reach or h < height - thickness - tw:
                continue
            u = x0 * gvec[1, 0] + x1 * gvec[1, 1] + x2 * gvec[1, 2]
            v = x0 * gvec[2, 0] + x1 * gvec[2, 1] + x2 * gvec[2, 2]
            if not _in_hull(u, v, hull):
                continue
            # the floor: a slab from the plane down `thickness`, in truncation units (negative inside)
            slab = max(h - height, height - thickness - h) / tw
            if slab < out[b, q]:
                out[b, q] = max(slab, -1.0)
            if weight[b, q] > 0.0 or sdf[b, q] < 0.0 or h <= height:
                continue
            # standing on the floor: march up through unobserved voxels to something solid
            step = voxel * st
            t = step
            while h + t <= height + reach:
                c0, c1, c2 = contract_point(x0 + t * gvec[0, 0], x1 + t * gvec[0, 1], x2 + t * gvec[0, 2])
                i = int(math.floor((c0 - origin) / voxel))
                j = int(math.floor((c1 - origin) / voxel))
                k = int(math.floor((c2 - origin) / voxel))
                if not (0 <= i < NB * BLOCK and 0 <= j < NB * BLOCK and 0 <= k < NB * BLOCK):
                    break
                blk = index[i // BLOCK, j // BLOCK, k // BLOCK]
                if blk < 0:
                    break  # nothing measured there: free
                qq = (i % BLOCK) * BLOCK * BLOCK + (j % BLOCK) * BLOCK + (k % BLOCK)
                if sdf[blk, qq] < 0.0:
                    out[b, q] = -1.0
                    break
                if weight[blk, qq] > 0.0:
                    break  # observed: free space a view saw through
                t += step
    return out


def frustum_planes(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """[4,3] inward normals (camera frame, through the camera centre) of the planes u = 0, u = width, v = 0,
    v = height of a pinhole camera K [3,3]; unit length."""
    fx, s, cx = float(K[0, 0]), float(K[0, 1]), float(K[0, 2])
    fy, cy = float(K[1, 1]), float(K[1, 2])
    n = np.array([[fx, s, cx], [-fx, -s, width - cx], [0.0, fy, cy], [0.0, -fy, height - cy]], dtype=np.float64)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


class ContractedTSDF:
    """The sparse fusion's state. Use: `allocate` every view's depth map (blocks near what it measured), then
    `integrate` them (any batches, any order), then `surface()`. `allocate` after `integrate` is refused (the new
    blocks would miss the votes of the views already fused).

    truncation_voxels, max_depth_voxels: contracted voxels (see the module docstring); radius: world distance from
    the origin beyond which nothing is allocated (the background sphere's side of the scene); ground: a
    `trisplat.mesh.ground.Ground` (the floor closed, things standing on it) or None."""

    def __init__(self, grid: ContractedGrid, truncation_voxels: float = 3.0, max_depth_voxels: float = np.inf,
                 radius: float = np.inf, near: float = 1e-3, occlusion_weight: float = OCCLUSION_WEIGHT,
                 max_voxels: int = MAX_VOXELS, ground=None):
        self.grid = grid
        self.ground = ground  # trisplat.mesh.ground.Ground or None
        self.truncation_voxels = float(truncation_voxels)
        self.max_depth_voxels = float(max_depth_voxels)
        self.radius = float(radius)
        self.near, self.occlusion_weight, self.max_voxels = float(near), float(occlusion_weight), int(max_voxels)
        self.mask = np.zeros((grid.blocks,) * 3, np.bool_)
        self.coords: np.ndarray | None = None
        self.views = 0  # views fused
        self.allocated_views = 0

    # -------------------------------------------------------------------------------------------------- allocation
    def allocate(self, cam, depth: np.ndarray, stride: int = 1) -> None:
        """Mark the blocks along `depth`'s rays (one view; camera with world_to_camera, K, width, height) from one
        truncation in front of its surface to max_depth plus two truncations behind it (every `stride`-th pixel)."""
        if self.coords is not None:
            raise RuntimeError("ContractedTSDF.allocate after integrate: allocate every view first")
        _check_depth(self.allocated_views, cam, depth)
        self.allocated_views += 1
        g = self.grid
        behind = (self.max_depth_voxels if np.isfinite(self.max_depth_voxels) else 4 * BLOCK) \
            + 2.0 * self.truncation_voxels + 1.0
        _mark_rays(np.linalg.inv(np.asarray(cam.world_to_camera, np.float64)), np.linalg.inv(np.asarray(cam.K,
                   np.float64)), np.ascontiguousarray(depth, np.float32), -g.extent, g.voxel, g.blocks,
                   2.0 * self.truncation_voxels + 1.0, behind, self.radius if np.isfinite(self.radius) else 1e30,
                   int(stride), self.mask)

    @property
    def allocated_voxels(self) -> int:
        return int(self.mask.sum()) * BV

    def finish_allocation(self) -> None:
        """Close the allocation (MemoryError when more than max_voxels voxels would be allocated)."""
        from scipy import ndimage

        # one block of slack around every marked one: the rays' samples are half a block apart, and the field's
        # ramps reach sideways of the rays
        self.mask = ndimage.binary_dilation(self.mask, np.ones((3, 3, 3), bool))
        if self.ground is not None:
            g = self.ground
            _mark_ground(self.mask, -self.grid.extent, self.grid.voxel, self._ground_vectors(), g.height, g.thickness,
                         g.reach, np.ascontiguousarray(g.hull, np.float64), self.truncation_voxels * self.grid.voxel)
        if self.allocated_voxels > self.max_voxels:
            raise MemoryError(f"contracted fusion would allocate {self.allocated_voxels:,} voxels (more than "
                              f"{self.max_voxels:,}): lower the resolution")
        self.coords = np.argwhere(self.mask).astype(np.int32)
        n = len(self.coords)
        self.index = np.full(self.mask.shape, -1, np.int32)
        self.index[tuple(self.coords.T)] = np.arange(n, dtype=np.int32)
        self.sdf = np.zeros((n, BV), np.float32)
        self.weight = np.zeros((n, BV), np.float32)
        self.in_view = np.zeros((n, BV), np.bool_)
        self.band = np.zeros((n, BV), np.bool_)
        self._centre = np.empty((n, 3), np.float64)
        self._radius = np.empty(n, np.float64)
        self._fused = False  # the field computed (no more views)
        _block_spheres(self.coords, -self.grid.extent, self.grid.voxel, self._centre, self._radius)

    # ----------------------------------------------------------------------------------------------------- fusion
    def integrate(self, cameras, depths) -> None:
        """Add the votes of `cameras` with their depth maps (a float32 [B,H,W] stack whose views may be larger than
        their cameras, or one [H,W] map each)."""
        if self.coords is None:
            self.finish_allocation()
        if self._fused:
            raise RuntimeError("ContractedTSDF.integrate after field(): integrate every view first")
        cameras = list(cameras)
        if len(cameras) == 0:
            return
        if isinstance(depths, np.ndarray) and depths.ndim == 3 and depths.dtype == np.float32:
            stack = depths
        else:
            stack = np.full((len(cameras), max(c.height for c in cameras), max(c.width for c in cameras)), np.nan,
                            np.float32)
            for n, (cam, d) in enumerate(zip(cameras, depths)):
                _check_depth(self.views + n, cam, d)
                stack[n, : cam.height, : cam.width] = d
        w2c = np.stack([np.asarray(c.world_to_camera, np.float64) for c in cameras])
        K = np.stack([np.asarray(c.K, np.float64) for c in cameras])
        planes = np.stack([frustum_planes(c.K, c.width, c.height) for c in cameras])
        sizes = np.array([(int(c.width), int(c.height)) for c in cameras], np.int64)
        _fuse_blocks(self.coords, -self.grid.extent, self.grid.voxel, self._centre, self._radius, w2c, K, planes,
                     sizes, stack,
                     self.truncation_voxels * self.grid.voxel, self.near, self.occlusion_weight, self.sdf,
                     self.weight, self.in_view, self.band)
        self.views += len(cameras)

    def field(self) -> np.ndarray:
        """float32 [nb,BV]: the field of every allocated voxel (computed once, in place of the vote sums: no view
        can be integrated after it)."""
        if self.coords is None:
            self.finish_allocation()
        if self._fused:
            return self.sdf
        self._fused = True
        _field(self.sdf, self.weight, self.in_view)
        if np.isfinite(self.max_depth_voxels) and self.band.any():
            import edt
            import numba

            f = EDT_COARSENING
            n = -(-self.grid.size // f)
            coarse = np.zeros((n, n, n), np.bool_)
            _coarse_band(self.coords, self.band, coarse, f)
            dist = edt.edt(~coarse, black_border=False, parallel=numba.get_num_threads())
            del coarse
            _cut_unseen(self.coords, self.sdf, dist, f, self.max_depth_voxels, self.truncation_voxels)
        if self.ground is not None:
            g = self.ground
            self.sdf = _ground_field(self.coords, self.index, -self.grid.extent, self.grid.voxel, self.sdf,
                                     self.weight, self._ground_vectors(), g.height, g.thickness, g.reach,
                                     np.ascontiguousarray(g.hull, np.float64), self.truncation_voxels * self.grid.voxel)
        return self.sdf

    def _ground_vectors(self) -> np.ndarray:
        g = self.ground
        return np.ascontiguousarray(np.stack([g.up, g.a, g.b]), np.float64)

    # ----------------------------------------------------------------------------------------------- the surface
    def surface(self, drop_cavities: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The zero level set of the field: vertices float64 [V,3] in CONTRACTED coordinates and faces int64 [F,3],
        welded, counter-clockwise seen from the free side (outward). Marching cubes (scikit-image) on slabs of
        SLAB voxels, cropped to the allocated blocks, welded where they meet. drop_cavities: as
        `trisplat.mesh.fusion.extract_surface`."""
        from skimage.measure import marching_cubes

        from trisplat.mesh.fusion import inside_out_pieces

        sdf = self.field()
        g = self.grid
        P = g.size + 2  # padded index range
        verts, faces, boundary = [], [], []
        offset = 0
        occupied = self.mask.any(axis=(1, 2)), self.mask.any(axis=(0, 2)), self.mask.any(axis=(0, 1))
        if not self.mask.any():
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        # padded index box of the allocated blocks, one free plane around
        lo = [int(np.argmax(o)) * BLOCK for o in occupied]
        hi = [(len(o) - int(np.argmax(o[::-1]))) * BLOCK + 2 for o in occupied]
        x = lo[0]
        while x < hi[0] - 1:
            x1 = min(x + SLAB, hi[0] - 1, P - 1)
            sub = self.mask[max((x - 1) // BLOCK, 0): (x1 - 1) // BLOCK + 1]
            if sub.any():
                ys, zs = sub.any(axis=(0, 2)), sub.any(axis=(0, 1))
                y0 = int(np.argmax(ys)) * BLOCK
                y1 = (len(ys) - int(np.argmax(ys[::-1]))) * BLOCK + 2
                z0 = int(np.argmax(zs)) * BLOCK
                z1 = (len(zs) - int(np.argmax(zs[::-1]))) * BLOCK + 2
                vol = np.empty((x1 - x + 1, y1 - y0, z1 - z0), np.float32)
                _fill_slab(self.index, sdf, x, y0, z0, vol)
                if vol.min() < 0.0 < vol.max():
                    v, f, _, _ = marching_cubes(vol, level=0.0, allow_degenerate=False)
                    v = v.astype(np.float64) + np.array([x, y0, z0], np.float64)
                    verts.append(v)
                    faces.append(f.astype(np.int64) + offset)
                    boundary.append((np.abs(v[:, 0] - x) < 1e-9) | (np.abs(v[:, 0] - x1) < 1e-9))
                    offset += len(v)
            x = x1
        if not verts:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        v, f, on_plane = np.concatenate(verts), np.concatenate(faces), np.concatenate(boundary)
        v, f = _weld(v, f, on_plane)
        v = -g.extent + (v - 1.0 + 0.5) * g.voxel  # padded index -> voxel centre -> contracted coordinates
        # with gradient_direction='descent' scikit-image winds triangles counter-clockwise seen from the larger
        # field (free space): outward (as trisplat.mesh.fusion.extract_surface)
        if drop_cavities and len(f):
            f = f[~inside_out_pieces(v, f)]
            used = np.zeros(len(v), bool)
            used[f.reshape(-1)] = True
            v, f = v[used], (np.cumsum(used) - 1)[f]
        return v, f


def _weld(v: np.ndarray, f: np.ndarray, on_plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge the vertices that two slabs both made on the plane they share (same position to 1/4096 voxel), drop
    the faces that collapse."""
    idx = np.nonzero(on_plane)[0]
    remap = np.arange(len(v))
    if len(idx):
        key = np.round(v[idx] * 4096.0).astype(np.int64)
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        remap[idx] = idx[first][inverse.reshape(-1)]
    f = remap[f]
    good = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[good]
    used = np.zeros(len(v), bool)
    used[f.reshape(-1)] = True
    return v[used], (np.cumsum(used) - 1)[f]


def fuse_contracted(cameras, depths, grid: ContractedGrid, truncation_voxels: float = 3.0,
                    max_depth_voxels: float = np.inf, radius: float = np.inf, near: float = 1e-3,
                    occlusion_weight: float = OCCLUSION_WEIGHT, batch_bytes: int = 256 * 2**20,
                    max_voxels: int = MAX_VOXELS, ground=None) -> ContractedTSDF:
    """A ContractedTSDF with every view allocated and fused. depths: a sequence of [H,W] maps (read twice: once to
    allocate, once to fuse; a DepthStore keeps them out of memory)."""
    cameras = list(cameras)
    if len(cameras) != len(depths):
        raise ValueError(f"{len(cameras)} cameras but {len(depths)} depth maps")
    if not cameras:
        raise ValueError("depth fusion needs at least one view")
    vol = ContractedTSDF(grid, truncation_voxels, max_depth_voxels, radius, near, occlusion_weight, max_voxels, ground)
    for n, cam in enumerate(cameras):
        vol.allocate(cam, depths[n])
    Hm, Wm = max(c.height for c in cameras), max(c.width for c in cameras)
    per_batch = int(max(1, min(len(cameras), batch_bytes // (4 * Hm * Wm))))
    stack = np.empty((per_batch, Hm, Wm), np.float32)
    for n0 in range(0, len(cameras), per_batch):
        batch = cameras[n0: n0 + per_batch]
        for b, cam in enumerate(batch):
            d = depths[n0 + b]
            _check_depth(n0 + b, cam, d)
            stack[b] = np.nan
            stack[b, : cam.height, : cam.width] = d
        vol.integrate(batch, stack[: len(batch)])
    return vol
