"""Visual hull from silhouettes: carve a voxel grid with the alpha masks of the training views, then sample points
on its surface (with outward normals and image colours) to seed triangles where the object is.

Used by the `hull` initialisation for captures whose images carry alpha (synthetic Blender scenes, masked object
captures) and no sparse points: random points in the whole box put most of the first triangles in empty space,
where they cost render time and leave floaters until pruning removes them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

MASK_THRESHOLD = 0.5  # alpha at or above this is the object
MIN_KEPT_VOXELS = 64  # fewer surviving voxels than this: the masks and poses disagree, carving failed


@dataclass(frozen=True)
class VisualHull:
    """occupied: bool [R,R,R] voxels inside every silhouette, indexed [i,j,k] along x,y,z of the normalised frame.
    origin: float [3] corner of voxel (0,0,0); voxel: edge length; views: silhouettes used."""

    occupied: np.ndarray
    origin: np.ndarray
    voxel: float
    views: int

    def centers(self, ijk: np.ndarray) -> np.ndarray:
        return self.origin + (np.asarray(ijk, dtype=np.float64) + 0.5) * self.voxel


def _project(cam, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v) and view depth z of world points (OpenCV camera, pixel centres at +0.5)."""
    R, t = cam.world_to_camera[:3, :3], cam.world_to_camera[:3, 3]
    pc = pts @ R.T + t
    z = pc[:, 2]
    zs = np.where(z > 1e-9, z, 1.0)
    K = cam.K
    u = K[0, 0] * pc[:, 0] / zs + K[0, 1] * pc[:, 1] / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    return u, v, z


def _pixels(cam, pts: np.ndarray, near: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel row and column of each point, whether it lands in the image in front of the camera (z > near), and z."""
    u, v, z = _project(cam, pts)
    col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    inside = (z > near) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
    return row, col, inside, z


def carve(cameras, masks, bounds, resolution: int = 128, near: float = 1e-3) -> VisualHull:
    """Voxels of `bounds` (float [2,3]) that project inside every silhouette.

    cameras: Camera objects; masks: float or bool [H,W] per camera (alpha in [0,1] or a boolean mask), or None for
    a view without one (skipped). A voxel is carved by a view only where it projects inside that image, in front of
    the camera, onto background; the silhouette is dilated by the voxel's projected radius so thin parts survive.
    """
    lo, hi = np.asarray(bounds, dtype=np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
        raise ValueError(f"visual hull needs a finite box with max > min, got {lo} .. {hi}")
    voxel = float((hi - lo).max()) / resolution
    dims = tuple(np.maximum(np.ceil((hi - lo) / voxel).astype(int), 1))
    ijk = np.argwhere(np.ones(dims, dtype=bool))
    centers = lo + (ijk + 0.5) * voxel
    views = 0
    for cam, mask in zip(cameras, masks):
        if mask is None:
            continue
        m = np.asarray(mask)
        m = m if m.dtype == bool else m >= MASK_THRESHOLD
        if m.shape != (cam.height, cam.width):
            raise ValueError(f"mask of {cam.name} is {m.shape[1]}x{m.shape[0]}, camera is {cam.width}x{cam.height}")
        row, col, inside, z = _pixels(cam, centers, near)
        front = z > near
        if not front.any():
            continue
        radius_px = int(np.ceil(0.87 * voxel * max(cam.K[0, 0], cam.K[1, 1]) / max(float(z[front].min()), near)))
        if radius_px > 0:
            m = ndimage.binary_dilation(m, iterations=min(radius_px, 16))
        keep = np.ones(len(centers), dtype=bool)
        keep[inside] = m[row[inside], col[inside]]
        ijk, centers = ijk[keep], centers[keep]
        views += 1
    occupied = np.zeros(dims, dtype=bool)
    occupied[tuple(ijk.T)] = True
    return VisualHull(occupied, lo, voxel, views)


def surface_samples(hull: VisualHull, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n points on the hull's surface voxels (uniform jitter inside each voxel) and their outward unit normals
    (gradient of the smoothed occupancy). Voxels are drawn without replacement while there are enough of them."""
    occ = hull.occupied
    surface = occ & ~ndimage.binary_erosion(occ, border_value=0)
    idx = np.argwhere(surface)
    if len(idx) == 0:
        raise ValueError("the visual hull is empty: no voxel projects inside every silhouette")
    pick = rng.choice(len(idx), size=n, replace=n > len(idx))
    cell = idx[pick]
    pts = hull.centers(cell) + (rng.random((n, 3)) - 0.5) * hull.voxel
    smooth = ndimage.gaussian_filter(occ.astype(np.float32), sigma=1.5)
    grads = np.stack(np.gradient(smooth), axis=-1)[tuple(cell.T)]  # [n,3], points into the object
    normals = -grads
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    fallback = norm[:, 0] < 1e-8
    normals = np.where(fallback[:, None], rng.normal(size=(n, 3)), normals)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return pts, normals


def mean_colors(cameras, images, masks, pts: np.ndarray) -> np.ndarray:
    """Mean image colour of each point over the views where it projects onto the object (occlusion is ignored:
    a rough start that the optimisation corrects). Points no view sees on the object get mid-grey."""
    acc = np.zeros((len(pts), 3))
    cnt = np.zeros(len(pts))
    for cam, img, mask in zip(cameras, images, masks):
        if mask is None:
            continue
        row, col, ok, _ = _pixels(cam, pts, 0.0)
        ok[ok] = np.asarray(mask)[row[ok], col[ok]] >= MASK_THRESHOLD
        acc[ok] += np.asarray(img)[row[ok], col[ok], :3]
        cnt[ok] += 1
    out = np.full((len(pts), 3), 0.5)
    seen = cnt > 0
    out[seen] = acc[seen] / cnt[seen, None]
    return out
