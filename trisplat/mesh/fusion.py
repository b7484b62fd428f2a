"""Depth fusion: a truncated signed distance field (TSDF) from per-view depth maps, and its zero surface.

Used by the stage-2 switch (`trisplat.train.switch`): the trained soup is rendered from every training camera,
each pixel's surface depth is fused here, and marching cubes turns the field into ONE welded, consistently oriented
surface, whatever the soup looked like (layered, overlapping, thin): the field averages the layers away.

Conventions (docs/conventions.md): a grid `[X,Y,Z]` over a box in the normalised frame, indexed along x, y, z,
cubic voxels, voxel centres at `origin + (ijk + 0.5) * voxel`. A depth map is view depth (camera z, scene units)
per pixel: `inf` where the pixel sees nothing (its ray is free up to infinity: background), `nan` where unknown
(skipped: the view says nothing about the voxels behind that pixel). Field values are signed distances in units
of the truncation distance, clipped to [-1, 1]: positive in front of the observed surface (free), negative behind
it. A voxel that lies inside some view but behind every view's surface (occluded) is solid (-1), as in space
carving, so closed objects give closed surfaces, but only within `max_depth` of an observed surface (a voxel some
view's depth puts within the truncation band): farther from every observed surface it is free again. Unseen space
has no thickness to go by, and without that bound it
filled everything the cameras could not look behind (lego's base plate, seen only from above, became a block down to
the bottom of the box, which low test views showed: -4 to -8 dB there); with it, the inside of a closed object is a
cavity whose surface `extract_surface` drops (it is inside-out). A voxel
inside no view is free (+1): nothing was seen there. Views are integrated a batch at a time (`TSDFVolume`): memory is
the grid's, not the views'. Occluded views also cast a weak vote for solid
(OCCLUSION_WEIGHT): without it, one ray with a wrong depth (a gap between soup triangles, a grazing face) would
carve the inside of an object that every other view sees from outside.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

OCCLUSION_WEIGHT = 0.1  # an occluded view's vote for solid, against 1 for a view that sees the voxel (see fuse_depths)
MAX_VOXELS = 64_000_000  # a grid larger than this is refused (memory: 10 bytes per voxel, plus marching cubes)


@dataclass(frozen=True)
class FusionGrid:
    """sdf: float32 [X,Y,Z] in truncation units (+1 free, -1 solid/unknown); weight: float32 [X,Y,Z] number of
    views that observed each voxel within the truncation band or in free space; origin [3]; voxel edge length;
    truncation: the truncation distance (scene units)."""

    sdf: np.ndarray
    weight: np.ndarray
    origin: np.ndarray
    voxel: float
    truncation: float


def fuse_reference(dims, origin, voxel, w2c, K, sizes, depths, trunc, near, occ_w, sdf_sum, w_sum, in_view, band):
    """The votes of a batch of views added to the accumulators, voxel by voxel and view by view: the readable rule
    (pure Python, for tests on small grids) that `_fuse_kernel` computes."""
    for i in range(dims[0]):
        for j in range(dims[1]):
            for k in range(dims[2]):
                p = origin + (np.array([i, j, k]) + 0.5) * voxel
                s_acc, w_acc, n_in, n_band = 0.0, 0.0, 0, 0
                for v in range(len(w2c)):
                    c = w2c[v][:3, :3] @ p + w2c[v][:3, 3]
                    if c[2] <= near:
                        continue  # behind the camera
                    u = (K[v][0, 0] * c[0] + K[v][0, 1] * c[1]) / c[2] + K[v][0, 2]
                    w = K[v][1, 1] * c[1] / c[2] + K[v][1, 2]
                    if u < 0 or w < 0 or int(u) >= sizes[v][0] or int(w) >= sizes[v][1]:
                        continue  # outside the image
                    d = depths[v][int(w), int(u)]
                    if np.isnan(d):
                        continue  # unknown: this view says nothing about the voxel
                    n_in += 1
                    sd = 1.0 if np.isinf(d) else min((d - c[2]) / trunc, 1.0)
                    if sd < -1.0:
                        s_acc -= occ_w  # behind the surface this view saw: occluded, a weak vote for solid
                        continue
                    n_band += int(sd < 1.0)  # within the truncation band of a measured surface
                    s_acc += sd
                    w_acc += 1.0
                if n_in:
                    sdf_sum[i, j, k] += s_acc
                    w_sum[i, j, k] += w_acc
                    in_view[i, j, k] = True
                    band[i, j, k] |= n_band > 0


@nb.njit(inline="always")
def _keep_positive(a, b, lo, hi):
    """[lo, hi] cut to the k where a + b k > 0 (an empty range has lo > hi)."""
    if b > 0.0:
        lo = max(lo, -a / b)
    elif b < 0.0:
        hi = min(hi, -a / b)
    elif a < 0.0:
        lo = hi + 1.0
    return lo, hi


# fast math without the no-NaN / no-Inf assumptions: depth maps hold both (unknown, nothing seen), and with them
# the compiler may drop the isnan / isinf tests
@nb.njit(parallel=True, cache=True, fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _fuse_kernel(dims, origin, voxel, w2c, K, sizes, depths, trunc, near, occ_w, sdf_sum, w_sum, in_view, band):
    """Add the votes of a batch of views (w2c [B,4,4], K [B,3,3], sizes [B,2], depths [B,H,W]) to the accumulators
    sdf_sum, w_sum (float32 [X,Y,Z]), in_view, band (bool [X,Y,Z]): `fuse_reference`'s rule. Each column of voxels
    along z meets a view's frustum in one run of k (the camera coordinates are linear in k, so "in front of the
    camera and inside the image" is a set of linear inequalities in k): only that run, widened by one voxel each
    side, is visited, with the same per-voxel tests, so most voxel-view pairs of a room or a large box are never
    touched."""
    X, Y, Z = dims[0], dims[1], dims[2]
    n_views = w2c.shape[0]
    for i in nb.prange(X):
        x = origin[0] + (i + 0.5) * voxel
        s_col = np.zeros(Z)
        w_col = np.zeros(Z)
        in_col = np.zeros(Z, np.int32)
        band_col = np.zeros(Z, np.int32)
        for j in range(Y):
            y = origin[1] + (j + 0.5) * voxel
            s_col[:] = 0.0
            w_col[:] = 0.0
            in_col[:] = 0
            band_col[:] = 0
            z0 = origin[2] + 0.5 * voxel
            for v in range(n_views):
                M = w2c[v]
                Kv = K[v]
                # camera coordinates of voxel k: c0 + dc k; pixel u = nu / cz, w = nw / cz
                cx0 = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z0 + M[0, 3]
                cy0 = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z0 + M[1, 3]
                cz0 = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z0 + M[2, 3]
                dcx, dcy, dcz = M[0, 2] * voxel, M[1, 2] * voxel, M[2, 2] * voxel
                nu0 = Kv[0, 0] * cx0 + Kv[0, 1] * cy0 + Kv[0, 2] * cz0
                dnu = Kv[0, 0] * dcx + Kv[0, 1] * dcy + Kv[0, 2] * dcz
                nw0 = Kv[1, 1] * cy0 + Kv[1, 2] * cz0
                dnw = Kv[1, 1] * dcy + Kv[1, 2] * dcz
                lo, hi = 0.0, Z - 1.0
                lo, hi = _keep_positive(cz0 - near, dcz, lo, hi)  # in front of the camera
                lo, hi = _keep_positive(nu0, dnu, lo, hi)  # u > 0
                lo, hi = _keep_positive(sizes[v, 0] * cz0 - nu0, sizes[v, 0] * dcz - dnu, lo, hi)  # u < width
                lo, hi = _keep_positive(nw0, dnw, lo, hi)
                lo, hi = _keep_positive(sizes[v, 1] * cz0 - nw0, sizes[v, 1] * dcz - dnw, lo, hi)
                if not lo <= hi:
                    continue
                k0 = max(0, int(np.floor(lo)) - 1)
                k1 = min(Z - 1, int(np.ceil(hi)) + 1)
                for k in range(k0, k1 + 1):
                    z = origin[2] + (k + 0.5) * voxel
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
                    if col >= sizes[v, 0] or row >= sizes[v, 1]:
                        continue
                    d = depths[v, row, col]
                    if np.isnan(d):
                        continue  # unknown: this view says nothing about the voxel
                    in_col[k] += 1
                    if np.isinf(d):
                        s = 1.0
                    else:
                        s = (d - cz) / trunc
                        if s < -1.0:
                            # behind the surface this view saw: occluded, a weak vote for solid
                            s_col[k] -= occ_w
                            continue
                        if s < 1.0:
                            band_col[k] += 1  # within the truncation band of a measured surface
                        else:
                            s = 1.0
                    s_col[k] += s
                    w_col[k] += 1.0
            for k in range(Z):
                if in_col[k] > 0:
                    sdf_sum[i, j, k] += s_col[k]
                    w_sum[i, j, k] += w_col[k]
                    in_view[i, j, k] = True
                    if band_col[k] > 0:
                        band[i, j, k] = True


def grid_shape(bounds: np.ndarray, resolution: int) -> tuple[tuple[int, int, int], float]:
    """Voxel counts along x, y, z and the voxel edge for `resolution` voxels along the box's longest side."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
        raise ValueError(f"depth fusion needs a finite box with max > min, got {lo} .. {hi}")
    if int(resolution) < 8:
        raise ValueError(f"depth fusion needs a resolution of at least 8 voxels, got {resolution}")
    voxel = float((hi - lo).max()) / int(resolution)
    dims = tuple(int(d) for d in np.maximum(np.ceil((hi - lo) / voxel), 1).astype(int))
    return dims, voxel


class TSDFVolume:
    """The fusion's accumulators over a box, fed a few views at a time (`integrate`), so that no more than a batch
    of depth maps is ever held: the field of `fuse_depths`, streamed. Memory: 10 bytes per voxel (vote sum and
    weight float32, two flags), plus the batch being integrated."""

    def __init__(self, bounds, resolution: int = 256, truncation_voxels: float = 3.0, near: float = 1e-3,
                 occlusion_weight: float = OCCLUSION_WEIGHT):
        self.dims, self.voxel = grid_shape(bounds, resolution)
        if int(np.prod(self.dims)) > MAX_VOXELS:
            raise ValueError(f"depth fusion grid {self.dims} has more than {MAX_VOXELS} voxels: lower the resolution")
        self.origin = np.asarray(bounds, dtype=np.float64)[0].copy()
        self.truncation = float(truncation_voxels) * self.voxel
        self.near, self.occlusion_weight = float(near), float(occlusion_weight)
        self.sdf_sum = np.zeros(self.dims, np.float32)
        self.w_sum = np.zeros(self.dims, np.float32)
        self.in_view = np.zeros(self.dims, np.bool_)
        self.band = np.zeros(self.dims, np.bool_)
        self.views = 0

    def integrate(self, cameras, depths) -> None:
        """Add the votes of `cameras` (world_to_camera, K, width, height) with their view-depth maps `depths`
        (float [H,W] each, or one float32 [B,H,W] stack whose views may be larger than their cameras: the top-left
        height x width of each is used)."""
        if len(cameras) != len(depths):
            raise ValueError(f"{len(cameras)} cameras but {len(depths)} depth maps")
        if len(cameras) == 0:
            return
        if isinstance(depths, np.ndarray) and depths.ndim == 3 and depths.dtype == np.float32:
            stack = depths
            if any(c.height > stack.shape[1] or c.width > stack.shape[2] for c in cameras):
                raise ValueError(f"a depth stack of {stack.shape[2]}x{stack.shape[1]} is smaller than its cameras")
        else:
            stack = np.full((len(cameras), max(int(c.height) for c in cameras), max(int(c.width) for c in cameras)),
                            np.nan, dtype=np.float32)
            for n, (cam, d) in enumerate(zip(cameras, depths)):
                _check_depth(self.views + n, cam, d)
                stack[n, : cam.height, : cam.width] = d
        sizes = np.array([(int(c.width), int(c.height)) for c in cameras], np.int64)
        w2c = np.stack([np.asarray(c.world_to_camera, dtype=np.float64) for c in cameras])
        K = np.stack([np.asarray(c.K, dtype=np.float64) for c in cameras])
        _fuse_kernel(np.asarray(self.dims, np.int64), self.origin, self.voxel, w2c, K, sizes, stack,
                     self.truncation, self.near, self.occlusion_weight, self.sdf_sum, self.w_sum, self.in_view,
                     self.band)
        self.views += len(cameras)

    def grid(self, max_depth: float = float("inf")) -> FusionGrid:
        """The field so far (see fuse_depths for the rule and `max_depth`)."""
        observed = self.w_sum > 0
        # observed: the mean; inside some view but always behind its surface: occluded, solid; in no view: free
        sdf = np.divide(self.sdf_sum, self.w_sum, out=np.zeros(self.dims, np.float32), where=observed)
        np.clip(sdf, -1.0, 1.0, out=sdf)
        np.copyto(sdf, np.where(self.in_view, np.float32(-1.0), np.float32(1.0)), where=~observed)
        del observed
        if np.isfinite(max_depth) and self.band.any():
            import edt
            import numba

            # a ramp over one truncation distance, not a step: the cut is an offset surface of what was observed,
            # smooth, instead of a staircase of voxels (edt: scipy.ndimage.distance_transform_edt's distances,
            # float32, on several threads)
            dist = edt.edt(~self.band, anisotropy=(self.voxel,) * 3, black_border=False,
                           parallel=numba.get_num_threads())
            dist -= np.float32(max_depth)
            dist /= np.float32(self.truncation)
            np.clip(dist, -1.0, 1.0, out=dist)
            np.maximum(sdf, dist, out=sdf, where=sdf < 0)
        return FusionGrid(sdf, self.w_sum.copy(), self.origin.copy(), self.voxel, self.truncation)


def _check_depth(n: int, cam, d) -> None:
    shape = np.shape(d)
    if shape != (cam.height, cam.width):
        got = f"{shape[1]}x{shape[0]}" if len(shape) == 2 else f"of shape {shape}"
        raise ValueError(f"depth map {n} is {got}, its camera is {cam.width}x{cam.height}")


FUSE_BATCH_BYTES = 256 * 2**20  # depth maps integrated together (one pass over the grid per batch)


def fuse_depths(cameras, depths, bounds, resolution: int = 256, truncation_voxels: float = 3.0,
                near: float = 1e-3, occlusion_weight: float = OCCLUSION_WEIGHT,
                max_depth: float = float("inf"), batch_bytes: int = FUSE_BATCH_BYTES) -> FusionGrid:
    """TSDF of the depth maps inside `bounds` (float [2,3], normalised frame).

    cameras: objects with world_to_camera [4,4], K [3,3], width, height (trisplat.cameras.Camera); depths: one
    float [H,W] view-depth map per camera (inf = nothing seen, nan = unknown), a sequence or any iterable (a
    generator that renders each view when asked): the maps are consumed a batch of about `batch_bytes` at a time
    and not kept, so memory does not grow with the number of views. Each voxel averages, over the views
    that see it in front of or within `truncation_voxels` voxels behind their surface, the clipped signed distance
    (depth - voxel depth) / truncation; views where it lies farther behind the surface add -`occlusion_weight` to
    the sum (not to the weight), views where it lies outside the image or behind the camera say nothing. Voxels
    inside some view (on a pixel that is not nan) but behind every view's surface are solid (-1); voxels in no view
    at all are free (+1: nothing was seen there). Then every solid voxel farther than `max_depth` (scene units,
    Euclidean) from the nearest observed voxel (one within the truncation band of some view's depth) becomes
    free: the field near what the cameras measured is unchanged, and unseen space is a shell of that thickness
    behind it, not a block.
    """
    cameras = list(cameras)
    if hasattr(depths, "__len__") and len(cameras) != len(depths):
        raise ValueError(f"{len(cameras)} cameras but {len(depths)} depth maps")
    if len(cameras) == 0:
        raise ValueError("depth fusion needs at least one view")
    vol = TSDFVolume(bounds, resolution, truncation_voxels, near, occlusion_weight)
    Hm = max(int(c.height) for c in cameras)
    Wm = max(int(c.width) for c in cameras)
    per_batch = int(max(1, min(len(cameras), batch_bytes // (4 * Hm * Wm))))
    stack = np.empty((per_batch, Hm, Wm), np.float32)
    n = 0
    it = iter(depths)
    while n < len(cameras):
        b = 0
        while b < per_batch and n + b < len(cameras):
            try:
                d = next(it)
            except StopIteration:
                raise ValueError(f"{len(cameras)} cameras but {n + b} depth maps") from None
            cam = cameras[n + b]
            _check_depth(n + b, cam, d)
            stack[b] = np.nan
            stack[b, : cam.height, : cam.width] = d
            del d
            b += 1
        vol.integrate(cameras[n: n + b], stack[:b])
        n += b
    if next(it, None) is not None:
        raise ValueError(f"{len(cameras)} cameras but more depth maps")
    return vol.grid(max_depth)


def extract_surface(grid: FusionGrid, drop_cavities: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of the field (marching cubes, scikit-image) as vertices float64 [V,3] (normalised frame) and
    faces int64 [F,3], welded, counter-clockwise seen from the free side (outward). The grid is padded with free
    space, so a solid region touching the box is closed along the box's faces. Empty when nothing is solid.
    drop_cavities: remove the pieces that enclose free space inside solid (negative signed volume: their normals
    point inwards), i.e. the walls of hollow insides, which no camera outside can see."""
    from skimage.measure import marching_cubes

    vol = np.pad(grid.sdf, 1, constant_values=1.0)
    if not (vol < 0).any():
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    verts, faces, _, _ = marching_cubes(vol, level=0.0, allow_degenerate=False)
    verts = grid.origin + (verts - 1.0 + 0.5) * grid.voxel  # padding, then voxel centres
    # with gradient_direction='descent' scikit-image winds each triangle counter-clockwise seen from the side where
    # the field is larger (free space): outward, as docs/conventions.md wants (tests/mesh/test_fusion.py checks it)
    verts, faces = verts.astype(np.float64), np.ascontiguousarray(faces, dtype=np.int64)
    if drop_cavities and len(faces):
        faces = faces[~inside_out_pieces(verts, faces)]
        used = np.zeros(len(verts), bool)
        used[faces.reshape(-1)] = True
        verts, faces = verts[used], (np.cumsum(used) - 1)[faces]
    return verts, faces


def inside_out_pieces(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """bool [F]: faces of the closed pieces whose signed volume is negative (normals pointing into the region they
    enclose: the wall of a cavity, seen from the solid around it)."""
    from trisplat.mesh.cleanup import face_components

    n, label = face_components(faces, len(verts))
    t = verts[faces]
    vol = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])) / 6.0
    return (np.bincount(label, weights=vol, minlength=n) < 0)[label]
