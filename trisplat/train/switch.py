"""The stage-2 switch: a trained triangle soup becomes ONE connected surface that keeps the soup's appearance.

MeshSplatting replaces the soup's faces by a restricted Delaunay triangulation of its vertices; on the thick,
layered soups a CPU budget trains, that keeps several faces per edge (docs/benchmarks_mesh.md: 44% non-manifold
edges). This switch instead renders the soup from every training camera, takes each pixel's surface depth (the face
where the accumulated blending weight passes 0.5, as the renderer reports it), fuses the depth maps into a truncated
signed distance field (`trisplat.mesh.fusion`: unobserved space solid, so objects close), extracts its zero surface
with marching cubes (welded, manifold, outward), drops small pieces, decimates to the face budget (quadric error,
fast-simplification) and gives every new vertex the colour (all SH bands) and opacity of the soup around it.
Training then fine-tunes this mesh (the trainer keeps its connectivity: no soup-style pruning or densification).
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Literal

import numba as nb
import numpy as np
import torch

from trisplat.mesh.cleanup import face_components
from trisplat.mesh.fusion import extract_surface, fuse_depths, grid_shape
from trisplat.scene.model import TriangleScene

BOX_PERCENTILE = 0.5  # the box of the soup's vertices between these percentiles (per axis) ...
BOX_MARGIN = 0.1  # ... grown by this fraction of its size on every side
INNER_RADIUS = 1.0  # normalised frame: the half-side of the inner box of a capture without a content box (the cameras
# lie within 1/1.1 of the centre); the soup beyond it is the far field (walls, distant furniture, sky) and stays a soup
PRE_DECIMATE = 3.0  # contracted fusion: the marching-cubes surface is decimated to this x the face budget first
REGION_BANDS = (0.0, 0.5, 1.0, 1.5, 2.0)  # contracted fusion: shells of the contracted cube (L-infinity norm) whose
# faces are decimated to their share of the training pixels (_ContractedSpace.reduce)
MIN_REGION_SHARE = 0.02  # ... at least this share of the budget each
GROUND_THICKNESS = 0.05  # contracted fusion: the closed floor's thickness below its plane (normalised units)
HIDDEN_FACES = 0.1  # the hidden faces kept to join pieces (trisplat.mesh.hidden_join) are decimated to this share
JOIN_VOXELS = 2.0  # contracted fusion: pieces of the surface closer than this (contracted voxels) are joined
MIN_DEPTH_VOXELS = 3.0  # unseen space is solid at least this many voxels behind what was observed (a thinner shell
# is breached by the noise of a coarse grid)


@dataclass(frozen=True)
class SurfaceConfig:
    """Settings of the switch. Lengths in voxels of the fusion grid unless said otherwise."""

    space: Literal["box", "contracted"] = "box"
    """where to fuse: 'box', a dense grid over a box of the normalised frame (the `bounds` given, or the soup's
    extent: an object); 'contracted', the whole scene out to outer_radius on a sparse grid over the contracted cube
    (`trisplat.mesh.contraction`: voxels grow with distance; a real capture's room, floor and walls)."""
    ground_reach: float = 0.0
    """space 'contracted': with a floor found under the cameras (trisplat.mesh.ground), the floor is closed and what
    no view observed between it and something solid up to this height above it (normalised units) is solid: things
    stand on the floor (0: no ground)."""
    outer_radius: float | None = None
    """space 'contracted': nothing farther than this from the origin (normalised units) is fused (None: fusion_radius
    of the soup, beyond nearly all of it)."""
    resolution: int = 512
    """space 'box': voxels along the longest side of the fused box (lowered to fit max_voxels); 'contracted': voxels
    across the inner cube [-1, 1]^3 (where the cameras are; the voxels beyond grow with the contraction)."""
    max_voxels: int = 48_000_000
    """grid size cap, dense voxels ('box') or allocated ones ('contracted'; the resolution is lowered until it
    fits) (memory: about 10 bytes per voxel; time: voxels x views projections)."""
    truncation_voxels: float = 3.0
    """TSDF truncation distance (voxels). The trainer passes trisplat.train.connect.surface_truncation (6 voxels for
    objects, 3 for real photos, or --surface-truncation); SLAM and the merge of partitioned blocks use this default."""
    retry_truncations: tuple[float, ...] = ()
    """truncations (fractions of the fused box's longest side) to fuse with in turn while the surface carves away
    more than `max_carved` of what the views saw (carved_fraction): a real capture's soup can put a surface at
    depths that differ between views by more than a few voxels (the bonsai's table: views from its two sides), and
    the views that see past it vote its space free. A larger truncation averages them; it also rounds fine detail
    off (fox: 0.3 dB less straight after the switch at 8 voxels, 1 dB at 20), so it is used only where needed."""
    max_carved: float = 0.1
    """see retry_truncations (measured: fox's surface at 3 voxels carves 3.4-3.5% of what its views saw, bonsai's
    6.3% with poses whose switch kept the table; the synthetic three-sphere soup of tests/train/test_switch.py 68%)."""
    carved_check_views: int = 16
    """views (evenly spaced over the training views) that carved_fraction renders the fused surface in."""
    face_ratio: float = 8.0
    """face budget of the surface: this many times the soup's face count (decimated down to it, never up)."""
    max_faces: int = 400_000
    """upper bound of the face budget (count)."""
    min_component_fraction: float = 0.02
    """pieces with fewer faces than this fraction of the largest piece are dropped (floaters)."""
    opacity: float = 0.9
    """vertex opacity the surface starts with (the trainer's opacity floor keeps rising from here)."""
    neighbours: int = 8
    """soup vertices whose attributes (SH, opacity) each surface vertex averages, weighted by opacity / distance."""
    max_depth_fraction: float = 0.01
    """space no view saw (behind every view's surface) is solid only this far behind the nearest surface, as a
    fraction of the fused box's longest side; deeper it is free (a hollow inside, whose inside-out wall is dropped).
    Without a bound, unseen space filled the box: lego's base plate, seen only from above, became a block down to
    the bottom of the box, and test views from low down lost 4-8 dB on it."""
    empty_is_free: bool = True
    """a pixel the soup leaves empty is free space all along its ray (background: an object capture). False for
    scenes seen from inside (a SLAM map of a room): an empty pixel is a hole in the map, unknown, and carving along
    it would cut through the walls behind. The trainer sets it from the photos: free only when they have alpha
    (a background to be free). Whether the cameras lie inside the soup's hull is not used: a real photo of an object
    from outside has no free pixel either (every pixel sees something), and floaters around an object would put
    its cameras inside. tests/mesh/test_room_walls.py: with True a room seen from inside loses its walls."""
    unseen_faces: Literal["keep", "drop_enclosed", "drop", "drop_but_bridges", "drop_but_joins"] = "keep"
    """faces no view saw (every vertex farther than the truncation from each view's surface depth): bounding unseen
    space leaves the far side of a shell behind what the views measured. 'drop_enclosed' drops those whose outward
    normal looks at the surface itself (a ray from the face along its normal hits the mesh): the inside wall of an
    object whose underside was never seen, which joins the outside through the unseen opening and so survives
    extract_surface's cavity test; an unseen underside that faces away into open space is kept, closing the object.
    'drop' drops every unseen face (a room scan: the back of its walls faces outwards, into nothing).
    'drop_but_bridges' drops them all but the hidden sides that join two pieces of the seen surface: a table top's
    underside, never seen, faces the floor and joins the top to its legs (hidden_bridges); then each piece still
    apart is joined to the main one by the hidden surface nearest to it, within its own size
    (trisplat.mesh.hidden_join: a cloth-draped table's unseen skirt down to the floor). 'drop_but_joins' keeps
    every group of unseen faces that joins two seen pieces, whatever it faces (the contracted fusion of a whole scene:
    the unseen foot of a stool between its seen sides and the floor)."""
    hidden_side_reach: float = 1.0
    """'drop_but_bridges': how far (scene units: metres in SLAM) an unseen face's normal ray looks for a seen face."""
    fill_holes_px: int = 2
    """empty pixels closer than this (pixels) to covered ones on two sides (a morphological closing) take the depth
    of the nearest covered pixel: a soup has gaps between its triangles, and one ray through a gap would carve the
    inside of the object away (free space wins where nothing else is observed)."""
    depth_memory_mb: float = 1024.0
    """the views' depth maps are needed again after the fusion (which faces some view sees, the photos' colours):
    this many MiB of them are kept in memory, the rest in a temporary folder (TMPDIR; 4 bytes per pixel per view),
    read back one at a time. The photos are loaded one at a time too: the switch's memory does not grow with the
    number of views (docs/benchmarks.md, "Switch memory")."""


@dataclass
class SwitchReport:
    """What the switch did (counts, seconds)."""

    soup_faces: int = 0
    soup_vertices: int = 0
    views: int = 0
    space: str = "box"
    grid: tuple[int, int, int] = (0, 0, 0)
    voxel: float = 0.0
    allocated_voxels: int = 0
    joins: int = 0
    ground: dict | None = None
    pixel_share: list | None = None
    truncation_voxels: float = 0.0
    carved_fraction: float | None = None
    marching_cubes_faces: int = 0
    pieces: int = 0
    pieces_dropped: int = 0
    faces: int = 0
    vertices: int = 0
    render_s: float = 0.0
    fuse_s: float = 0.0
    mesh_s: float = 0.0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        return (f"soup {self.soup_faces} faces -> surface {self.faces} faces / {self.vertices} vertices "
                f"(V/F {self.vertices / max(self.faces, 1):.2f}; fused {self.views} views on a "
                f"{'x'.join(map(str, self.grid))} grid"
                + (f" over the contracted scene ({self.allocated_voxels / 1e6:.1f}M voxels allocated)"
                   if self.space == "contracted" else "")
                + f", truncation {self.truncation_voxels:.1f} voxels; "
                f"{self.pieces_dropped} of {self.pieces} pieces dropped; "
                f"{self.render_s + self.fuse_s + self.mesh_s:.1f} s)")


@nb.njit(parallel=True, cache=True)
def _plane_depth_kernel(face_id, local, Kinv, normal, num, nlen, zmin, zmax, zmean, depth):
    H, W = face_id.shape
    for r in nb.prange(H):
        for c in range(W):
            if face_id[r, c] < 0:
                continue
            f = local[face_id[r, c]]
            x, y = c + 0.5, r + 0.5
            rx = Kinv[0, 0] * x + Kinv[0, 1] * y + Kinv[0, 2]
            ry = Kinv[1, 0] * x + Kinv[1, 1] * y + Kinv[1, 2]
            rz = Kinv[2, 0] * x + Kinv[2, 1] * y + Kinv[2, 2]
            den = normal[f, 0] * rx + normal[f, 1] * ry + normal[f, 2] * rz
            z = zmean[f]
            if abs(den) > 1e-6 * nlen[f] * math.sqrt(rx * rx + ry * ry + rz * rz):
                z = num[f] / den
                if not (np.isfinite(z) and z > 0):
                    z = zmean[f]
            depth[r, c] = min(max(z, zmin[f]), zmax[f])


def surface_depth(face_id: np.ndarray, positions: np.ndarray, faces: np.ndarray, world_to_camera: np.ndarray,
                  K: np.ndarray) -> np.ndarray:
    """View depth [H,W] where each pixel centre's ray meets the plane of its face `face_id` [H,W] (the face at
    which the accumulated blending weight passes 0.5, the "median depth" of 2DGS-style extraction); inf where
    face_id < 0 (nothing there: free space). Grazing planes fall back to the face's mean depth, and a plane met
    far outside its triangle is clamped to the triangle's depth range. Per-face planes in numpy, per-pixel rays in
    Numba: no per-pixel temporaries (a 12-megapixel view would otherwise hold gigabytes of them)."""
    H, W = face_id.shape
    depth = np.full((H, W), np.inf, dtype=np.float32)
    face_id = np.ascontiguousarray(face_id)
    used = np.flatnonzero(np.bincount(face_id[face_id >= 0]))  # the faces shown (bincount: no sort of all pixels)
    if len(used) == 0:
        return depth
    R, t = np.asarray(world_to_camera)[:3, :3], np.asarray(world_to_camera)[:3, 3]
    local = np.full(int(used[-1]) + 1, -1, np.int64)  # face id -> row of the per-face tables
    local[used] = np.arange(len(used))
    tri = np.asarray(positions, np.float64)[np.asarray(faces)[used]] @ R.T + t  # [n,3,3] camera frame
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    num = np.einsum("ij,ij->i", normal, tri[:, 0])
    _plane_depth_kernel(face_id, local, np.linalg.inv(np.asarray(K, np.float64)), normal, num,
                        np.linalg.norm(normal, axis=1), tri[:, :, 2].min(1), tri[:, :, 2].max(1), tri[:, :, 2].mean(1),
                        depth)
    return depth


def fill_holes(depth: np.ndarray, px: int) -> np.ndarray:
    """`depth` [H,W] with its small empty (inf) gaps filled: pixels inside the morphological closing (`px`
    iterations) of the covered area take the depth of the nearest covered pixel. Computed in the covered area's
    bounding box grown by px + 1 (the same result: the closing reaches no farther), so a small object in a large
    photo costs little."""
    from scipy import ndimage

    covered = np.isfinite(depth)
    if px <= 0 or covered.all() or not covered.any():
        return depth
    rows, cols = np.nonzero(covered.any(1))[0], np.nonzero(covered.any(0))[0]
    m = int(px) + 1
    r0, r1 = max(rows[0] - m, 0), min(rows[-1] + m + 1, depth.shape[0])
    c0, c1 = max(cols[0] - m, 0), min(cols[-1] + m + 1, depth.shape[1])
    win, cov = depth[r0:r1, c0:c1], covered[r0:r1, c0:c1]
    closed = ndimage.binary_closing(cov, iterations=int(px), border_value=0)
    gaps = closed & ~cov
    if not gaps.any():
        return depth
    # a gap pixel lies within px (L1) of a covered one: its nearest covered pixel is inside the gaps' box grown by m
    gr, gc = np.nonzero(gaps.any(1))[0], np.nonzero(gaps.any(0))[0]
    a0, a1 = max(gr[0] - m, 0), min(gr[-1] + m + 1, gaps.shape[0])
    b0, b1 = max(gc[0] - m, 0), min(gc[-1] + m + 1, gaps.shape[1])
    g = gaps[a0:a1, b0:b1]
    _, (ri, ci) = ndimage.distance_transform_edt(~cov[a0:a1, b0:b1], return_indices=True)
    out = depth.copy()
    out[r0 + a0:r0 + a1, c0 + b0:c0 + b1][g] = win[a0:a1, b0:b1][ri[g], ci[g]]
    return out


def fusion_box(positions: np.ndarray, bounds: np.ndarray | None) -> np.ndarray:
    """The box to fuse in: the soup's robust extent (BOX_PERCENTILE per axis, grown by BOX_MARGIN), cut to the
    capture's content box when it has one (a tighter box gives finer voxels for the same count)."""
    lo = np.percentile(positions, BOX_PERCENTILE, axis=0)
    hi = np.percentile(positions, 100 - BOX_PERCENTILE, axis=0)
    size = np.maximum(hi - lo, 1e-6)
    lo, hi = lo - BOX_MARGIN * size, hi + BOX_MARGIN * size
    if bounds is not None:
        b = np.asarray(bounds, dtype=np.float64)
        lo2, hi2 = np.maximum(lo, b[0]), np.minimum(hi, b[1])
        if (hi2 > lo2).all():
            lo, hi = lo2, hi2
    return np.stack([lo, hi])


def fitting_resolution(box: np.ndarray, resolution: int, max_voxels: int) -> int:
    """`resolution` (voxels along the box's longest side), lowered until the grid has at most max_voxels."""
    res = int(resolution)
    while res > 8 and int(np.prod(grid_shape(box, res)[0])) > max_voxels:
        res = int(res * 0.9)
    return res


def transfer_attributes(scene: TriangleScene, points: np.ndarray, neighbours: int = 8
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """SH [P,K,3] and realised opacity [P] for `points` [P,3]: the mean over the `neighbours` nearest soup vertices,
    weighted by their opacity over their distance (opaque, near soup vertices dominate: the visible layer)."""
    from scipy.spatial import cKDTree

    src = scene.positions.detach().cpu().numpy().astype(np.float64)
    k = int(min(max(neighbours, 1), len(src)))
    dist, idx = cKDTree(src).query(points, k=k)
    dist, idx = dist.reshape(len(points), k), idx.reshape(len(points), k)
    opac = scene.opacities().detach().cpu().numpy().astype(np.float64)
    w = opac[idx] / np.maximum(dist, 1e-9)
    w /= np.maximum(w.sum(1, keepdims=True), 1e-30)
    wt = torch.as_tensor(w, dtype=scene.sh.dtype)
    sh = (scene.sh.detach().cpu()[torch.as_tensor(idx)] * wt[:, :, None, None]).sum(1)
    return sh, torch.as_tensor((opac[idx] * w).sum(1), dtype=torch.float32)


def _visible(cam, depth: np.ndarray | None, points: np.ndarray, tolerance):
    """(indices into points, their pixel rows, columns) of the points [P,3] that `cam` sees: in front of it, inside
    its image, within `tolerance` scene units (one for all, or one per point [P]) of its surface depth [H,W] there
    (depth None: no occlusion test)."""
    R, t = cam.world_to_camera[:3, :3], cam.world_to_camera[:3, 3]
    pc = points @ R.T + t
    z = pc[:, 2]
    zs = np.where(z > 1e-9, z, 1.0)
    u = (cam.K[0, 0] * pc[:, 0] + cam.K[0, 1] * pc[:, 1]) / zs + cam.K[0, 2]
    v = cam.K[1, 1] * pc[:, 1] / zs + cam.K[1, 2]
    ok = (z > 1e-9) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
    col, row = u[ok].astype(np.int64), v[ok].astype(np.int64)
    if depth is None:
        return np.nonzero(ok)[0], row, col
    tol = tolerance[ok] if np.ndim(tolerance) else tolerance
    vis = np.abs(depth[row, col] - z[ok]) <= tol
    return np.nonzero(ok)[0][vis], row[vis], col[vis]


def carved_fraction(verts: np.ndarray, faces: np.ndarray, cameras: Sequence, depths: Sequence, box: np.ndarray | None,
                    tolerance, views: int = 16, radius: float = np.inf) -> float:
    """Share of the soup's pixels that see a point inside `box` [2,3] (None: anywhere) and within `radius` of the
    origin where the fused surface (verts [V,3], faces [F,3]) shows nothing, or something more than `tolerance`
    (scene units; a number, or a function of the points [N,3] giving one per point) farther away: what the views saw
    and the fusion carved away. `views` evenly spaced cameras of `cameras` are rendered (z-buffer), against their
    soup depth maps in `depths` (inf: nothing seen, nan: unknown, both not counted)."""
    from trisplat.data.rgbd import backproject
    from trisplat.render.hard import rasterize_hard

    pts = torch.as_tensor(verts, dtype=torch.float32)
    tri = torch.as_tensor(np.asarray(faces), dtype=torch.int32)
    grey = torch.zeros((len(verts), 3))
    b = None if box is None else np.asarray(box, dtype=np.float64)
    seen = carved = 0
    for n in np.unique(np.linspace(0, len(cameras) - 1, max(1, min(views, len(cameras)))).round().astype(int)):
        cam, d = cameras[n], np.asarray(depths[n])
        H, W = d.shape
        w2c = np.asarray(cam.world_to_camera, dtype=np.float64)
        # the soup's surface points of the pixels that saw something (inf: nothing, nan: unknown)
        world, rc = backproject(np.where(np.isfinite(d), d, 0.0), np.asarray(cam.K), np.linalg.inv(w2c), 1)
        inside = np.linalg.norm(world, axis=1) <= radius
        if b is not None:
            inside &= ((world >= b[0]) & (world <= b[1])).all(1)
        if not inside.any():
            continue
        ys, xs = rc[inside, 0], rc[inside, 1]
        out = rasterize_hard(pts, tri, grey, torch.as_tensor(w2c, dtype=torch.float32),
                             torch.as_tensor(np.asarray(cam.K), dtype=torch.float32), W, H)
        mesh = out.depth.reshape(H, W).numpy().astype(np.float64)
        mesh = np.where(out.face_id.reshape(H, W).numpy() >= 0, mesh, np.inf)
        seen += len(ys)
        tol = tolerance(world[inside]) if callable(tolerance) else tolerance
        carved += int((mesh[ys, xs] > d[ys, xs] + tol).sum())
    return carved / max(seen, 1)


def seen_counts(cameras: Sequence, depths: Sequence, points: np.ndarray, tolerance) -> np.ndarray:
    """Number of views that see each of `points` [P,3] (see _visible) [P]."""
    cnt = np.zeros(len(points))
    for n, cam in enumerate(cameras):
        cnt[_visible(cam, depths[n], points, tolerance)[0]] += 1
    return cnt


def image_colors(cameras: Sequence, images: Iterable, depths: Sequence | None, points: np.ndarray, tolerance
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Mean RGB [P,3] of `points` over the views that see them (the point projects into the image, in front of the
    camera, within `tolerance` scene units of that view's surface depth; depths None: wherever it projects into the
    image, nothing occluding), and the number of such views [P].
    images: one [H,W,3+] photo per camera, float in [0,1] or uint8, in camera order; any iterable (a generator that
    loads each photo when asked: only one is held at a time)."""
    acc = np.zeros((len(points), 3))
    cnt = np.zeros(len(points))
    photos = iter(images)
    for n, cam in enumerate(cameras):
        # (not zip: its reused result tuple would hold the previous photo while the next one loads)
        depth = None if depths is None else depths[n]
        img = np.asarray(next(photos))
        idx, row, col = _visible(cam, depth, points, tolerance)
        rgb = img[row, col, :3].astype(np.float64)
        acc[idx] += rgb / 255.0 if img.dtype == np.uint8 else rgb
        cnt[idx] += 1
        del img, depth
    out = acc / np.maximum(cnt, 1)[:, None]
    return out, cnt


class DepthStore(Sequence):
    """The switch's depth maps, one per view, kept for the passes after fusion (which faces some view sees, the
    photos' colours): the first `memory_bytes` worth in memory, the rest written to a temporary folder (TMPDIR)
    and read back one at a time, so a capture of hundreds of large photos does not hold them all. A context
    manager: the folder is removed on exit."""

    def __init__(self, memory_bytes: int):
        self.memory_bytes = int(memory_bytes)
        self._items: list[np.ndarray | str] = []
        self._held = 0
        self._dir = None

    def append(self, depth: np.ndarray) -> None:
        depth = np.ascontiguousarray(depth, dtype=np.float32)
        if self._held + depth.nbytes <= self.memory_bytes:
            self._items.append(depth)
            self._held += depth.nbytes
            return
        import tempfile

        if self._dir is None:
            self._dir = tempfile.TemporaryDirectory(prefix="trisplat-switch-")
        path = f"{self._dir.name}/depth_{len(self._items):06d}.npy"
        try:
            np.save(path, depth)
        except OSError as exc:
            raise RuntimeError(
                f"the switch could not write depth map {len(self._items)} to {path} ({exc}); it needs about "
                f"{depth.nbytes / 2**30:.2f} GiB per view there: set TMPDIR to a folder with room, or train with a "
                "larger --downscale") from exc
        self._items.append(path)

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, n):
        if isinstance(n, slice):
            return [self[k] for k in range(*n.indices(len(self)))]
        item = self._items[n]
        return np.load(item) if isinstance(item, str) else item

    @property
    def spilled(self) -> int:
        """How many of the maps live on disk."""
        return sum(isinstance(x, str) for x in self._items)

    def close(self) -> None:
        self._items.clear()
        if self._dir is not None:
            self._dir.cleanup()
            self._dir = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _normal_rays(verts: np.ndarray, faces: np.ndarray, idx: np.ndarray, lift: float):
    """(trimesh mesh, ray origins, directions) of the outward normal rays of faces `idx`, each from `lift` (scene
    units) above its face's centroid."""
    import trimesh

    mesh = trimesh.Trimesh(verts, faces, process=False)
    normal = mesh.face_normals[idx]
    return mesh, mesh.triangles_center[idx] + lift * normal, normal


def facing_seen(verts: np.ndarray, faces: np.ndarray, unseen: np.ndarray, reach: float) -> np.ndarray:
    """bool [F]: the unseen faces (`unseen`, bool [F]) whose outward normal ray, from just above the face's centroid,
    first meets a face that is not unseen within `reach` (scene units; trimesh's ray caster). Such a face is the
    hidden side of something standing in observed space (a table top's underside above the floor); an unseen face
    that faces nothing, or only more unseen surface, is the back of the scan."""
    out = np.zeros(len(faces), dtype=bool)
    idx = np.nonzero(unseen)[0]
    if len(idx) == 0:
        return out
    mesh, origin, normal = _normal_rays(verts, faces, idx, 1e-4 * max(float(np.ptp(verts, 0).max()), 1e-9))
    loc, ray, tri = mesh.ray.intersects_location(origin, normal, multiple_hits=False)
    ok = (~unseen[tri]) & (np.linalg.norm(loc - origin[ray], axis=1) <= reach)
    out[idx[ray[ok]]] = True
    return out


def hidden_bridges(verts: np.ndarray, faces: np.ndarray, unseen: np.ndarray, reach: float,
                   min_piece: float = 0.0) -> np.ndarray:
    """bool [F]: the unseen faces that are a hidden side joining pieces of the seen surface. The unseen faces that
    face a seen face within `reach` (facing_seen) are grouped into vertex-connected groups; a group is kept when its
    vertices touch two or more pieces of the seen faces with at least `min_piece` x the largest piece's faces (a
    table top's underside, touching the top's rim and the legs' tops; smaller pieces are floaters, dropped later).
    Hidden sides that join nothing are guesses the surface does not need, and stay dropped. reach inf: every unseen
    face is a candidate (no rays: the groups that join seen pieces are kept whatever they face)."""
    cand = unseen.copy() if math.isinf(reach) else facing_seen(verts, faces, unseen, reach)
    out = np.zeros(len(faces), dtype=bool)
    if not cand.any() or unseen.all():
        return out
    seen_faces = faces[~unseen]
    _, seen_label = face_components(seen_faces, len(verts))
    size = np.bincount(seen_label)
    seen_label = np.where(size[seen_label] >= min_piece * size.max(), seen_label, -1)
    vertex_piece = np.full(len(verts), -1, dtype=np.int64)
    vertex_piece[seen_faces.ravel()] = np.repeat(seen_label, 3)
    cf = faces[cand]
    n_groups, group = face_components(cf, len(verts))
    touched = vertex_piece[cf].ravel()
    pairs = np.unique(np.stack([np.repeat(group, 3), touched], 1)[touched >= 0], axis=0)
    joins = np.bincount(pairs[:, 0], minlength=n_groups) >= 2
    out[np.nonzero(cand)[0][joins[group]]] = True
    return out


def _fast_rays(rep) -> bool:
    """Whether trimesh casts rays with Embree (embreex, installed on x86-64). Without it, casting a ray from each of
    a room's ~1M unseen faces would take hours: 'drop_but_bridges' then drops them all, and says so in `rep`."""
    import trimesh

    if trimesh.ray.has_embree:
        return True
    note = "hidden sides not joined (no Embree ray caster: pip install embreex): every unseen face dropped"
    if note not in rep.notes:
        rep.notes.append(note)
    return False


def unseen_faces(verts: np.ndarray, faces: np.ndarray, cameras: Sequence, depths: Sequence, tolerance,
                 enclosed_only: bool, bridge_reach: float | None = None, min_piece: float = 0.0) -> np.ndarray:
    """bool [F]: faces none of whose vertices any view sees (seen_counts with `tolerance`); with enclosed_only, only
    those whose outward normal ray (from just above the face's centroid) hits the mesh (trimesh's ray caster); with
    bridge_reach, all but the hidden sides that join pieces of the seen surface (hidden_bridges)."""
    unseen = seen_counts(cameras, depths, verts, tolerance) == 0
    out = unseen[faces].all(1)
    if bridge_reach is not None:
        return out & ~hidden_bridges(verts, faces, out, bridge_reach, min_piece)
    if enclosed_only and out.any():
        idx = np.nonzero(out)[0]
        lift = 1e-3 * (tolerance[faces[idx]].min(1) if np.ndim(tolerance) else tolerance)
        mesh, origin, normal = _normal_rays(verts, faces, idx, lift[:, None] if np.ndim(lift) else lift)
        out[idx] = mesh.ray.intersects_any(origin, normal)
    return out


class _BoxSpace:
    """Fusion in a box of the normalised frame: a dense grid (`trisplat.mesh.fusion`); coordinates are the world's."""

    def __init__(self, box: np.ndarray, resolution: int, rep: SwitchReport):
        self.box, self.res = box, resolution
        rep.grid, rep.voxel = grid_shape(box, resolution)
        self.voxel = rep.voxel
        self.side = float((box[1] - box[0]).max())  # lengths given as fractions of the fused region are of this
        self.region = dict(box=box)  # carved_fraction's region

    def fuse(self, cameras, source, store, trunc_vox: float, max_depth: float, rep: SwitchReport):
        """verts [V,3] (this space's coordinates), faces [F,3] of the fused surface of the depth maps `source` (an
        iterable; `store`: the same maps again, when a second pass needs them); lengths in voxels."""
        grid = fuse_depths(cameras, source, self.box, self.res, trunc_vox, max_depth=max_depth * self.voxel)
        return extract_surface(grid)

    def to_world(self, v: np.ndarray) -> np.ndarray:
        return v

    def tolerance(self, points_world: np.ndarray, trunc_vox: float):
        return trunc_vox * self.voxel

    def reduce(self, verts, faces, target: int):
        """The marching-cubes surface, lighter before the passes over its faces (nothing here: a box's surface
        is about the size of its face budget)."""
        return verts, faces

    def decimate(self, verts, faces, target: int):
        """Quadric decimation to `target` faces (fast-simplification)."""
        import fast_simplification

        v, f = fast_simplification.simplify(verts, faces.astype(np.int32), target_count=int(target))
        return np.asarray(v, np.float64), np.asarray(f, np.int64)

    def join(self, verts, faces, rep: SwitchReport):
        """Pieces that nearly touch, joined (nothing here)."""
        return verts, faces


class _ContractedSpace:
    """Fusion of the whole scene within `radius` of the origin in the contracted cube: a sparse grid
    (`trisplat.mesh.contracted_fusion`); mesh coordinates are contracted ones (decimation there spends faces by
    angle, not by metre), lengths in contracted voxels, tolerances in the world grow with the contraction's
    stretch."""

    def __init__(self, resolution: int, radius: float, max_voxels: int, rep: SwitchReport, ground_reach: float = 0.0):
        from trisplat.mesh.contracted_fusion import ContractedGrid
        from trisplat.mesh.contraction import outer_extent

        self.radius, self.max_voxels, self.rep = float(radius), int(max_voxels), rep
        self.ground, self.ground_reach = None, float(ground_reach)
        self.pixel_share = None  # of the training pixels, per shell of REGION_BANDS
        self.extent = outer_extent(self.radius)
        self._set(ContractedGrid.for_resolution(resolution, self.extent))
        self.side = 2.0  # the inner cube's side: the scale of lengths given as fractions
        # what the carve check counts: the inner cube, where the object at the centre of a capture is (the far
        # soup's layers are averaged away by any fusion: bonsai's 33% carved overall, 1% in the inner cube)
        self.region = dict(box=inner_box(), radius=self.radius)

    def _set(self, grid) -> None:
        self.grid = grid
        self.voxel = grid.voxel
        self.rep.grid, self.rep.voxel = (grid.size,) * 3, grid.voxel

    def fuse(self, cameras, source, store, trunc_vox: float, max_depth: float, rep: SwitchReport):
        """As _BoxSpace.fuse: every map of `source` allocates, then the maps of `store` are fused."""
        from trisplat.mesh.contracted_fusion import ContractedGrid, ContractedTSDF

        if self.ground is None and self.ground_reach > 0:
            from trisplat.eval.walk import up_direction
            from trisplat.mesh.ground import estimate_ground

            self.ground = estimate_ground(cameras, store if source is store else _Tee(source, store), up_direction(
                cameras), GROUND_THICKNESS, self.ground_reach, radius=self.radius)
            source = store
            rep.ground = None if self.ground is None else self.ground.to_dict()
        while True:
            vol = ContractedTSDF(self.grid, trunc_vox, max_depth, self.radius, max_voxels=self.max_voxels,
                                 ground=self.ground)
            for n, d in enumerate(source):
                vol.allocate(cameras[n], d)
            try:
                vol.finish_allocation()
                break
            except MemoryError as exc:
                res = int(round(2.0 / self.voxel * 0.85))
                if res < 32:
                    raise
                rep.notes.append(f"{exc}; fused at {res} voxels across the inner cube instead")
                self._set(ContractedGrid.for_resolution(res, self.extent))
                source = store
        rep.allocated_voxels = vol.allocated_voxels
        if self.pixel_share is None:
            self.pixel_share = self.pixel_shares(cameras, store)
            rep.pixel_share = [round(float(x), 4) for x in self.pixel_share]
        _integrate_batches(vol, cameras, store)
        # no cavity rule: the scene is seen from inside, and the inside of a room is the free space its walls enclose
        # (their normals point into it, as a cavity's do); unseen cavity walls go with the unseen faces
        return vol.surface(drop_cavities=False)

    def to_world(self, v: np.ndarray) -> np.ndarray:
        from trisplat.mesh.contraction import uncontract

        return uncontract(v)

    def reduce(self, verts, faces, target: int):
        """A whole scene's marching-cubes surface holds millions of faces (bonsai: 6M at 314 voxels across the inner
        cube), most of them on the room, which covers a large part of the contracted cube, and few on the object at
        its centre, which covers a third of the photos (bonsai's tree and stool: 17k of 4.4M): decimated as one,
        the object kept a few thousand faces. So each shell of the contracted cube (REGION_BANDS) is decimated to
        its share of PRE_DECIMATE x the face budget, the share of the training pixels that see it (at least
        MIN_REGION_SHARE), its borders with the other shells locked (pyfqmr), and the shells are joined again
        along them. The marching-cubes surface is closed, so those are its only borders."""
        if len(faces) <= PRE_DECIMATE * target:
            return verts, faces
        from trisplat.mesh.cleanup import simplify_parts

        m = np.abs(verts[faces].mean(1)).max(1)
        region = np.searchsorted(REGION_BANDS, m, side="right") - 1
        share = np.maximum(self.pixel_share, MIN_REGION_SHARE)
        share /= share.sum()
        return simplify_parts(verts, faces, region, [int(share[r] * PRE_DECIMATE * target)
                                                      for r in range(len(REGION_BANDS) - 1)])

    def decimate(self, verts, faces, target: int):
        """Quadric decimation to `target` faces (fast-simplification), in contracted coordinates."""
        import fast_simplification

        v, f = fast_simplification.simplify(verts, faces.astype(np.int32), target_count=int(target))
        return np.asarray(v, np.float64), np.asarray(f, np.int64)

    def pixel_shares(self, cameras, depths, stride: int = 4) -> np.ndarray:
        """Share of the training pixels (every `stride`-th of each depth map) whose surface point lies in each shell
        of REGION_BANDS."""
        from trisplat.mesh.contraction import contract

        counts = np.zeros(len(REGION_BANDS) - 1)
        for cam, d in zip(cameras, depths):
            d = np.asarray(d)[::stride, ::stride]
            rows, cols = np.nonzero(np.isfinite(d) & (d > 0))
            if len(rows) == 0:
                continue
            ray = np.stack([cols * stride + 0.5, rows * stride + 0.5, np.ones(len(rows))], 1) @ np.linalg.inv(
                np.asarray(cam.K, np.float64)).T
            c2w = np.linalg.inv(np.asarray(cam.world_to_camera, np.float64))
            m = np.abs(contract((ray * d[rows, cols, None]) @ c2w[:3, :3].T + c2w[:3, 3])).max(1)
            counts += np.bincount(np.clip(np.searchsorted(REGION_BANDS, m, side="right") - 1, 0, len(counts) - 1),
                                  minlength=len(counts))
        return counts / max(counts.sum(), 1.0)

    def join(self, verts, faces, rep: SwitchReport):
        """Pieces that come within JOIN_VOXELS of each other, joined at their closest vertices (weld_near_pieces):
        the fused scene's objects stand on its floor, a voxel or so from it where the field's sampling splits
        them (bonsai's stool and the floor: 1.05 voxels at the closest)."""
        from trisplat.mesh.cleanup import weld_near_pieces

        verts, faces, joins = weld_near_pieces(verts, faces, JOIN_VOXELS * self.voxel)
        rep.joins += joins
        return verts, faces

    def tolerance(self, points_world: np.ndarray, trunc_vox: float):
        from trisplat.mesh.contraction import contract, stretch

        return trunc_vox * self.voxel * stretch(contract(points_world))


class _Tee:
    """The maps of `source` (a generator that also stores each map in `store`), all drawn first, then read from
    `store`: estimate_ground reads every map once, the allocation after it reads them again."""

    def __init__(self, source, store):
        for _ in source:
            pass
        self.store = store

    def __iter__(self):
        return iter(self.store[n] for n in range(len(self.store)))


def _integrate_batches(vol, cameras: Sequence, depths: Sequence, batch_bytes: int = 256 * 2**20) -> None:
    """Fuse every view of `depths` (a DepthStore) into `vol`, about `batch_bytes` of depth maps at a time."""
    Hm, Wm = max(c.height for c in cameras), max(c.width for c in cameras)
    per = int(max(1, min(len(cameras), batch_bytes // (4 * Hm * Wm))))
    stack = np.empty((per, Hm, Wm), np.float32)
    for n0 in range(0, len(cameras), per):
        batch = cameras[n0: n0 + per]
        for b, cam in enumerate(batch):
            stack[b] = np.nan
            stack[b, : cam.height, : cam.width] = depths[n0 + b]
        vol.integrate(batch, stack[: len(batch)])


def soup_to_surface(scene: TriangleScene, cameras: Sequence, render: Callable[[int], object],
                    bounds: np.ndarray | None = None, config: SurfaceConfig = SurfaceConfig(),
                    progress: Callable[[str], None] | None = None,
                    images: Callable[[int], np.ndarray] | None = None) -> tuple[TriangleScene, SwitchReport]:
    """One connected surface from a trained soup.

    cameras: the training cameras (trisplat.cameras.Camera); render(n) -> RenderOutput of the soup seen by
    cameras[n] (its face_id is used); bounds: float [2,3] content box (normalised frame) or None (with
    config.space 'box'; 'contracted' fuses the whole scene out to config.outer_radius and ignores it); images(n) ->
    the [H,W,3] photo of cameras[n]: when given, each vertex's base colour (SH DC) is the mean colour of the photos
    that see it (sharper than the soup's, whose layers blur), the higher bands come from the soup. Returns a
    TriangleScene with the surface's vertices and faces (int32, outward), SH transferred from the soup, the soup's
    opacity floor and vertex opacities of at least `config.opacity`, and a report. Raises ValueError when the
    renders show nothing to fuse.
    """
    rep = SwitchReport(soup_faces=scene.num_faces, soup_vertices=scene.num_vertices, views=len(cameras),
                       space=config.space)
    pos = scene.positions.detach().cpu().numpy().astype(np.float64)
    fc = scene.faces.detach().cpu().numpy().astype(np.int64)
    if config.space == "contracted":
        space = _ContractedSpace(config.resolution, config.outer_radius or fusion_radius(pos), config.max_voxels, rep,
                                 config.ground_reach)
    else:
        box = fusion_box(pos, bounds)
        space = _BoxSpace(box, fitting_resolution(box, config.resolution, config.max_voxels), rep)
    truncations = [config.truncation_voxels]
    truncations += [f * space.side / rep.voxel for f in config.retry_truncations
                    if f * space.side / rep.voxel > truncations[-1]]
    max_depth = max(config.max_depth_fraction * space.side / rep.voxel, MIN_DEPTH_VOXELS)  # voxels
    target = int(min(config.max_faces, max(config.face_ratio * scene.num_faces, 1_000)))  # the face budget
    # the depth maps outlive the fusion (seen faces, photo colours): in memory up to depth_memory_mb, then on disk
    with DepthStore(int(config.depth_memory_mb * 2**20)) as depths:
        covered = False

        def depth_maps():
            # one view at a time: render, surface depth, into the store (memory or disk) and on to the fusion
            nonlocal covered
            for n, cam in enumerate(cameras):
                t = time.perf_counter()
                out = render(n)
                d = fill_holes(surface_depth(out.face_id.cpu().numpy(), pos, fc, np.asarray(cam.world_to_camera),
                                             np.asarray(cam.K)), config.fill_holes_px)
                del out
                if not config.empty_is_free:
                    d[np.isinf(d)] = np.nan
                covered = covered or bool(np.isfinite(d).any())
                depths.append(d)
                rep.render_s += time.perf_counter() - t
                yield d

        join_note = None
        for attempt, trunc_vox in enumerate(truncations):
            t0 = time.perf_counter()
            render_s = rep.render_s
            # the first fusion renders the views; a retry fuses the same depth maps again (from the store)
            verts, faces = space.fuse(cameras, depth_maps() if attempt == 0 else depths, depths, trunc_vox,
                                      max_depth, rep)
            rep.fuse_s += time.perf_counter() - t0 - (rep.render_s - render_s)
            if not covered:
                raise ValueError("the soup covers no pixel of any training view: nothing to turn into a surface")
            if attempt == 0 and depths.spilled:
                rep.notes.append(f"{depths.spilled} of {len(depths)} depth maps kept on disk until the end of the "
                                 "switch")
            if progress:
                progress(f"fused {len(cameras)} depth maps, truncation {trunc_vox:.1f} voxels ({rep.render_s:.1f} s "
                         f"rendering, {rep.fuse_s:.1f} s fusing); extracting the surface")
            t0 = time.perf_counter()
            rep.marching_cubes_faces = len(faces)
            if len(faces) == 0:
                raise ValueError("depth fusion found no surface (every voxel is free): the soup's renders are empty")
            verts, faces = space.reduce(verts, faces, target)
            verts, faces = space.join(verts, faces, rep)
            if config.unseen_faces != "keep":
                world = space.to_world(verts)
                bridges = config.unseen_faces == "drop_but_bridges" and _fast_rays(rep)
                reach = math.inf if config.unseen_faces == "drop_but_joins" else \
                    config.hidden_side_reach if bridges else None
                drop = unseen_faces(world, faces, cameras, depths, space.tolerance(world, trunc_vox),
                                    enclosed_only=config.unseen_faces == "drop_enclosed", bridge_reach=reach,
                                    min_piece=config.min_component_fraction)
                if config.unseen_faces == "drop_but_bridges":
                    from trisplat.mesh.hidden_join import join_through_hidden

                    extra, joined = join_through_hidden(world, faces, drop, config.min_component_fraction,
                                                        ground=getattr(space, "ground", None))
                    drop &= ~extra
                faces = faces[~drop]
                join_note = None
                if config.unseen_faces == "drop_but_bridges" and joined:
                    # the hidden faces kept to join pieces, decimated apart (their borders with the seen surface
                    # locked) to HIDDEN_FACES of their number: the face budget goes to what the views see
                    from trisplat.mesh.cleanup import simplify_parts

                    n_hidden = int(extra.sum())
                    verts, faces = simplify_parts(verts, faces, extra[~drop].astype(np.int64),
                                                  [len(faces), max(int(HIDDEN_FACES * n_hidden), 1)])
                    join_note = (f"{len(joined)} pieces standing apart joined through the hidden surface nearest "
                                 f"to them ({n_hidden} hidden faces, decimated to {int(HIDDEN_FACES * n_hidden)}): "
                                 + "; ".join(f"{j['faces']} faces, {j['distance']:.3g} away"
                                             f"{' on the floor' if j['floor'] else ''}" for j in joined))
                del world
                if len(faces) == 0:
                    raise ValueError("no view sees any part of the fused surface: nothing is left to fine-tune")
            verts, faces, rep.pieces, rep.pieces_dropped = _drop_small_pieces(verts, faces,
                                                                             config.min_component_fraction)
            rep.truncation_voxels = trunc_vox
            if attempt + 1 == len(truncations):
                rep.mesh_s += time.perf_counter() - t0
                break
            rep.carved_fraction = carved_fraction(space.to_world(verts), faces, cameras, depths,
                                                  tolerance=lambda p, t=trunc_vox: space.tolerance(p, t),
                                                  views=config.carved_check_views, **space.region)
            rep.mesh_s += time.perf_counter() - t0
            if rep.carved_fraction <= config.max_carved:
                break
            rep.notes.append(f"truncation {trunc_vox:.1f} voxels carved away {100 * rep.carved_fraction:.1f}% of "
                             f"what the views saw {'in the box' if config.space == 'box' else ''}(more than "
                             f"{100 * config.max_carved:.0f}%): fused again with {truncations[attempt + 1]:.1f}")
            if progress:
                progress(rep.notes[-1])
        if join_note:  # (of the last attempt)
            rep.notes.append(join_note)
        if config.unseen_faces != "keep":
            rep.notes.append(f"{int(drop.sum())} of {len(drop)} faces no view saw dropped ({config.unseen_faces})")
        t0 = time.perf_counter()
        if len(faces) > target:
            # (in the fusion's coordinates: contracted ones spend the faces by angle seen from the centre)
            verts, faces = space.decimate(verts, faces, target)
            verts, faces = _manifold(verts, faces)
            verts, faces = space.join(verts, faces, rep)  # (decimation can pull a join apart)
        verts = space.to_world(np.asarray(verts, dtype=np.float64))
        sh, opac = transfer_attributes(scene, verts, config.neighbours)
        if images is not None:
            from trisplat.scene.sh import rgb_to_sh_dc

            rgb, seen = image_colors(cameras, (images(n) for n in range(len(cameras))), depths, verts,
                                     space.tolerance(verts, trunc_vox))
            seen_t = torch.as_tensor(seen > 0)
            sh[seen_t, 0] = rgb_to_sh_dc(torch.as_tensor(rgb[seen > 0], dtype=sh.dtype))
            rep.notes.append(f"{int((seen > 0).sum())} of {len(verts)} vertices coloured from the photos")
        floor = float(scene.opacity_floor)
        o = torch.clamp(torch.maximum(opac, torch.full_like(opac, config.opacity)), floor + 1e-4, 1 - 1e-4)
        logit = torch.logit((o - floor) / (1 - floor), eps=1e-6)
        out = TriangleScene(torch.as_tensor(verts, dtype=torch.float32), sh.to(torch.float32).contiguous(),
                            logit.to(torch.float32), torch.as_tensor(faces, dtype=torch.int32), floor)
        rep.faces, rep.vertices = out.num_faces, out.num_vertices
        rep.mesh_s += time.perf_counter() - t0
        return out, rep


def fusion_radius(positions: np.ndarray, percentile: float = 99.5, margin: float = 1.1) -> float:
    """World radius (normalised frame) out to which the contracted fusion reaches: `margin` times the `percentile`
    of the soup's vertex distances from the origin, at least 2 (what lies farther is the background sphere's)."""
    r = float(np.percentile(np.linalg.norm(np.asarray(positions, np.float64), axis=1), percentile))
    return max(2.0, margin * r)


def inner_box(radius: float = INNER_RADIUS) -> np.ndarray:
    """[2,3] the cube of half-side `radius` about the origin of the normalised frame: where the fused surface of a
    capture without a content box is built (Mip-NeRF 360's unit ball, as a box)."""
    return np.array([[-radius] * 3, [radius] * 3], dtype=np.float64)


def far_field_mask(scene: TriangleScene, box: np.ndarray) -> np.ndarray:
    """bool [F]: faces whose centroid lies outside `box` [2,3] (the far field of an unbounded capture)."""
    pos = scene.positions.detach().cpu().numpy().astype(np.float64)
    cen = pos[scene.faces.detach().cpu().numpy().astype(np.int64)].mean(1)
    b = np.asarray(box, dtype=np.float64)
    return ~((cen >= b[0]) & (cen <= b[1])).all(1)


def box_cut_pieces(scene: TriangleScene, box: np.ndarray, tolerance: float) -> np.ndarray:
    """bool [F]: the faces of every piece of a fused surface, but its largest, that reaches the fusion box's
    boundary (a vertex within `tolerance`, scene units, of one of its faces). Fused in the inner box of an unbounded
    capture, these are the near ends of walls and furniture that the box cuts off: the far field's content, not the
    scene's. A piece wholly inside the box is the scene's and is not flagged."""
    faces = scene.faces.detach().cpu().numpy().astype(np.int64)
    n, label = face_components(faces, scene.num_vertices)
    if n < 2:
        return np.zeros(len(faces), bool)
    pos = scene.positions.detach().cpu().numpy().astype(np.float64)
    b = np.asarray(box, dtype=np.float64)
    near = ((pos <= b[0] + tolerance) | (pos >= b[1] - tolerance)).any(1)  # [V] at the box's boundary
    touches = np.zeros(n, bool)
    touches[label[near[faces].any(1)]] = True
    touches[np.argmax(np.bincount(label, minlength=n))] = False
    return touches[label]


def cut_pieces_last(surface: TriangleScene, box: np.ndarray, tolerance: float) -> tuple[TriangleScene, int]:
    """`surface` with the pieces that box_cut_pieces flags moved to its last face rows (their vertices to the last
    vertex rows), and how many faces moved: the far-field layer's first rows."""
    cut = box_cut_pieces(surface, box, tolerance)
    if not cut.any():
        return surface, 0
    return append_scene(sub_scene(surface, ~cut), sub_scene(surface, cut)), int(cut.sum())


def sub_scene(scene: TriangleScene, face_mask: np.ndarray) -> TriangleScene:
    """The faces where face_mask [F] is True with the vertices they use (re-indexed), SH, opacity logits, floor."""
    faces = scene.faces.detach().cpu().numpy().astype(np.int64)[np.asarray(face_mask, bool)]
    used = np.unique(faces.reshape(-1))
    remap = np.full(scene.num_vertices, -1, np.int64)
    remap[used] = np.arange(len(used))
    idx = torch.as_tensor(used, dtype=torch.int64)
    return TriangleScene(scene.positions.detach()[idx].clone(), scene.sh.detach()[idx].clone(),
                         scene.opacity_logit.detach()[idx].clone(), torch.as_tensor(remap[faces], dtype=torch.int32),
                         scene.opacity_floor)


def append_scene(a: TriangleScene, b: TriangleScene) -> TriangleScene:
    """`a` then `b` in one table (b's vertex and face rows after a's; a's opacity floor, b's realised opacities
    kept: its logits are re-solved when the floors differ)."""
    logit_b = b.opacity_logit.detach()
    if abs(a.opacity_floor - b.opacity_floor) > 1e-12:
        o = b.opacities().detach().clamp(a.opacity_floor + 1e-6, 1 - 1e-6)
        logit_b = torch.logit((o - a.opacity_floor) / (1 - a.opacity_floor), eps=1e-6)
    return TriangleScene(torch.cat([a.positions.detach(), b.positions.detach().to(a.positions)]),
                         torch.cat([a.sh.detach(), b.sh.detach().to(a.sh)]),
                         torch.cat([a.opacity_logit.detach(), logit_b.to(a.opacity_logit)]),
                         torch.cat([a.faces, b.faces.to(a.faces) + a.num_vertices]), a.opacity_floor)


def _manifold(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decimation can fold two faces onto the same vertices or leave more than two faces on an edge: drop both faces
    of a fold, keep the best-shaped face traversing an over-full edge each way (marching cubes and decimation leave
    the faces consistently oriented, and so do the kept ones; keeping one of a fold, or the two best-shaped faces
    whatever their direction, left lego's surface impossible to orient consistently), then pieces below 1% of the
    largest, unused vertices."""
    from trisplat.mesh.cleanup import CleanupConfig, clean_mesh

    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    _, inverse, count = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    faces = faces[count[inverse.reshape(-1)] == 1]  # a fold (two faces on the same vertices): neither is a surface
    res = clean_mesh(verts, faces, CleanupConfig(weld=False, drop_duplicate_faces=False, repair_non_manifold_edges=True,
                                                 repair_keeps_orientation=True, orient=False))
    v, f, _, _ = _drop_small_pieces(res.vertices, res.faces, 0.01)
    return np.asarray(v, dtype=np.float64), f


def _drop_small_pieces(verts: np.ndarray, faces: np.ndarray, min_fraction: float):
    """Remove degenerate faces, pieces with fewer faces than min_fraction x the largest one's, unused vertices.
    Returns vertices, faces, the number of pieces and how many were dropped."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    good = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces = faces[good]
    n, label = face_components(faces, len(verts))
    if n == 0:
        return verts, faces, 0, 0
    sizes = np.bincount(label, minlength=n)
    keep_piece = sizes >= min_fraction * sizes.max()
    faces = faces[keep_piece[label]]
    used = np.zeros(len(verts), bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return np.asarray(verts)[used], remap[faces], int(n), int((~keep_piece).sum())
