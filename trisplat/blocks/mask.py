"""Which pixels of a block's views show content beyond the block's box, so the block is never asked to explain them.

A block trains on whole photos, but its surface is confined to its box (the expanded cell, as the content box of a
masked capture). A view of a street also shows what lies beyond the box: the neighbouring blocks' objects, the ground
up to the horizon. Asked to reproduce those pixels, the block can only put surfaces inside its box on their rays (a
haze in front of the cameras), and the parts of that haze inside the block's own cell survive the merge's clip and
fusion (the fusion takes its depth from the blocks' surfaces, not from the photos, so nothing there contradicts them).

So, in a block's photos, every pixel whose content lies outside the block's box while its ray passes through the box
(the box's part of the ray is then free space), or whose ray misses the box altogether (the block cannot draw there at
all), is made background: its colour the capture's background, its alpha 0, as the photo's own transparent
background already is. The block then learns that its part of those rays is empty, which is what they show.

What a pixel shows is found from the capture's sparse points (in the scene's normalised frame): each view's points,
splatted as discs of `radius` pixels into a depth buffer (the front-most point wins, so nearer content hides what is
behind it); a pixel the discs leave empty takes the point projected nearest to it, within `radius_fill` pixels. A pixel
takes that point's place: in the box (kept), outside it and beyond the ray's entry into the box, or with a ray that misses the
box (made background), or outside it in front of the box's entry (kept: what the box holds behind an occluder of a
neighbouring block is unknown, and the haze such a pixel can still ask for lies at the box's side, in the margin the
merge's clip removes). Pixels no point reaches are kept as they are.
"""
from __future__ import annotations

import numpy as np

RADIUS_FRACTION = 0.02  # the splat's radius, of the image's longer side (2 pixels at 96 x 64)
FILL_FRACTION = 0.08  # the second pass, for the pixels the first left empty
NEAR = 1e-6


def pixel_rays(cam) -> tuple[np.ndarray, np.ndarray]:
    """(centre [3], directions [H*W,3]) of the rays through the pixel centres (x + 0.5, y + 0.5) of `cam`, in world
    units whose camera depth is 1 (a point at ray parameter t has view depth t)."""
    w2c = np.asarray(cam.world_to_camera, dtype=np.float64)
    R, t = w2c[:3, :3], w2c[:3, 3]
    centre = -R.T @ t
    ys, xs = np.mgrid[0:cam.height, 0:cam.width]
    pix = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5, np.ones(xs.size)], axis=1)
    d_cam = pix @ np.linalg.inv(np.asarray(cam.K, dtype=np.float64)).T
    return centre, d_cam @ R  # R^T d for every row


def ray_box(centre: np.ndarray, dirs: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    """(t_in, t_out) [N] of rays centre + t dirs through the axis-aligned box [2,3] (slabs; t_in >= 0); t_in > t_out
    where a ray misses it."""
    box = np.asarray(box, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        a = (box[0] - centre) * inv
        b = (box[1] - centre) * inv
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    # a ray parallel to a slab: inside it, that slab does not bound it (nan from 0 * inf); outside it, it misses
    par = dirs == 0
    inside = (centre >= box[0]) & (centre <= box[1])
    lo = np.where(par, np.where(inside, -np.inf, np.inf), lo)
    hi = np.where(par, np.where(inside, np.inf, -np.inf), hi)
    return np.maximum(lo.max(1), 0.0), hi.min(1)


def _splat(cols: np.ndarray, rows: np.ndarray, z: np.ndarray, width: int, height: int, radius: float) -> np.ndarray:
    """int [H*W]: for each pixel, the index of the front-most point (smallest z) whose disc of `radius` pixels (around
    its projection cols, rows) holds the pixel's centre; -1 where none does."""
    r = int(np.ceil(radius))
    best = np.full(width * height, np.inf)
    pix_all, idx_all = [], []
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            x = np.floor(cols).astype(np.int64) + dx
            y = np.floor(rows).astype(np.int64) + dy
            near = (x + 0.5 - cols) ** 2 + (y + 0.5 - rows) ** 2 <= radius * radius
            ok = near & (x >= 0) & (x < width) & (y >= 0) & (y < height)
            if not ok.any():
                continue
            p = y[ok] * width + x[ok]
            np.minimum.at(best, p, z[ok])
            pix_all.append(p)
            idx_all.append(np.flatnonzero(ok))
    out = np.full(width * height, -1, np.int64)
    if not pix_all:
        return out
    p, i = np.concatenate(pix_all), np.concatenate(idx_all)
    win = z[i] == best[p]
    out[p[win]] = i[win]
    return out


def pixel_content(cam, points: np.ndarray, radius: float | None = None,
                  radius_fill: float | None = None) -> np.ndarray:
    """int [H*W]: for each pixel of `cam`, the index (into `points` [N,3], the camera's frame) of the sparse point
    that stands for what the pixel shows (see the module's docstring), -1 where no point reaches it."""
    W, H = int(cam.width), int(cam.height)
    side = max(W, H)
    radius = max(1.0, RADIUS_FRACTION * side) if radius is None else float(radius)
    radius_fill = max(radius, FILL_FRACTION * side) if radius_fill is None else float(radius_fill)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    w2c = np.asarray(cam.world_to_camera, dtype=np.float64)
    xc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = xc[:, 2]
    uvw = xc @ np.asarray(cam.K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        cols, rows = uvw[:, 0] / z, uvw[:, 1] / z
    reach = radius_fill + 1.0
    on = np.flatnonzero((z > NEAR) & (cols > -reach) & (cols < W + reach) & (rows > -reach) & (rows < H + reach))
    which = np.full(W * H, -1, np.int64)
    if not len(on):
        return which
    cols, rows, z = cols[on], rows[on], z[on]
    which = _splat(cols, rows, z, W, H, radius)
    empty = np.flatnonzero(which < 0)
    if len(empty) and radius_fill > radius:  # the nearest point in the image, whatever its depth: a front-most rule
        from scipy.spatial import cKDTree  # over this wider disc would spread near content over what lies behind it

        px = np.stack([empty % W + 0.5, empty // W + 0.5], axis=1)
        dist, idx = cKDTree(np.stack([cols, rows], axis=1)).query(px, distance_upper_bound=radius_fill)
        which[empty] = np.where(np.isfinite(dist), idx, -1)
    return np.where(which >= 0, on[np.maximum(which, 0)], -1)


def outside_content(cam, points: np.ndarray, box, radius: float | None = None,
                    radius_fill: float | None = None) -> np.ndarray:
    """bool [H,W]: the pixels of `cam` whose content (pixel_content: a sparse point) lies outside `box` ([2,3], the
    same frame as `points` [N,3] and the camera) with the box's part of their ray in front of it, or whose ray misses
    the box."""
    W, H = int(cam.width), int(cam.height)
    box = np.asarray(box, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centre, dirs = pixel_rays(cam)
    t_in, t_out = ray_box(centre, dirs, box)
    misses = t_in > t_out
    which = pixel_content(cam, pts, radius, radius_fill)
    seen = which >= 0
    k = np.maximum(which, 0)
    eps = 1e-6 * float(np.max(box[1] - box[0]))  # points on the box's faces (its floor: the ground) are in it
    in_box = np.all((pts >= box[0] - eps) & (pts <= box[1] + eps), axis=1)
    w2c = np.asarray(cam.world_to_camera, dtype=np.float64)
    z = pts @ w2c[2, :3] + w2c[2, 3]  # view depth (the rays' parameter t)
    # the ray reaches the box before its content: the box's part of the ray is empty
    beyond = seen & ~in_box[k] & (z[k] > t_in) & ~misses
    return (misses | beyond).reshape(H, W)
