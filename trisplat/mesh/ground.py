"""The ground of a capture: the floor plane under the cameras, found in the depth maps, and where it reaches.

A room photographed around an object on a stool: the cameras look down past the stool at the floor, and nobody sees
the stool's foot or the floor right around it. Fused as observed, the stool hangs in a hole of the floor, a piece of
its own (issue 49: bonsai's stool and tree, 31% of the test pixels, apart from the room). The fusion
(`trisplat.mesh.contracted_fusion`) uses the ground in two ways: the floor is closed (solid below the plane, within
the floor's reach, `thickness` deep), and what no view observed between the floor and something solid above it
(within `reach`) is solid too: things stand on the floor.

The floor is the plane, nearly perpendicular to the cameras' mean up (`trisplat.eval.walk.up_direction`), that most
of the depth maps' points below every camera lie on (RANSAC); its normal is the scene's up. Its reach is the convex
hull of those points in the plane, grown by `margin`. A capture where no such plane holds `min_share` of the points
below the cameras has no ground (None): nothing is assumed.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MIN_SHARE = 0.10  # of the points below the cameras, the floor plane's inliers are at least this share
BELOW_CAMERAS = 0.1  # the floor lies at least this far below the lowest camera (normalised units)
PLANE_TOLERANCE = 0.03  # a point within this of the plane is one of its inliers (normalised units)
MAX_TILT = 25.0  # degrees between the floor's normal and the cameras' mean up
# A plane holding a share s of the points is sampled (3 of its points) with probability s^3 per try: 300 tries found
# a 15% floor 64% of the time, and bonsai's floor (15.6% within the tolerance) was missed in 2 of 5 30-minute runs
# (c1, c5), its stool then a piece apart. 5,000 tries find a 10% plane 99.3% of the time; each try is scored on
# SCORE_POINTS points (0.1 ms), the winners on all of them.
RANSAC_ITERATIONS = 5000
SCORE_POINTS = 20_000
MAX_POINTS = 200_000  # points the plane is fitted to (a random subset)


@dataclass(frozen=True)
class Ground:
    """The floor plane: points x with x . up = height (normalised frame); `a`, `b` span the plane; `hull` [K,2] the
    floor's reach as a convex polygon in (x . a, x . b), counter-clockwise; thickness and reach in normalised
    units (see the module docstring)."""

    up: np.ndarray
    height: float
    a: np.ndarray
    b: np.ndarray
    hull: np.ndarray
    thickness: float
    reach: float

    def inside(self, points: np.ndarray) -> np.ndarray:
        """bool [N]: the points [N,3] whose projection on the floor lies within its reach."""
        uv = np.stack([points @ self.a, points @ self.b], 1)
        return inside_convex(uv, self.hull)

    def to_dict(self) -> dict:
        return {"up": [float(x) for x in self.up], "height": float(self.height), "hull_points": len(self.hull),
                "thickness": float(self.thickness), "reach": float(self.reach)}


def inside_convex(uv: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """bool [N]: the 2D points uv [N,2] inside the counter-clockwise convex polygon hull [K,2]."""
    e = np.roll(hull, -1, 0) - hull
    rel = uv[:, None, :] - hull[None]
    return ((e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]) >= 0).all(1)


def plane_axes(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to `up`."""
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return a, np.cross(up, a)


def estimate_ground(cameras: Sequence, depths: Sequence, up: np.ndarray, thickness: float, reach: float,
                    tolerance: float = PLANE_TOLERANCE, margin: float = 0.1, radius: float = np.inf, stride: int = 4,
                    min_share: float = MIN_SHARE, seed: int = 0) -> Ground | None:
    """The floor plane of the depth maps (view depth, inf/nan where nothing was measured), or None. `up` is a first
    guess (the cameras' mean up, a few degrees off: over a room that tilts a floor by more than its own thickness):
    planes are fitted to the points below the cameras (RANSAC, then least squares on the inliers within `tolerance`),
    their normals within MAX_TILT of `up`; the floor is the lowest plane with at least `min_share` of those points
    on it (a stool's or a table's top can hold as many as the floor). Points farther than `radius` from the origin are not used;
    every `stride`-th pixel of each map."""
    from scipy.spatial import ConvexHull

    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    pts = []
    for cam, d in zip(cameras, depths):
        d = np.asarray(d)[::stride, ::stride]
        rows, cols = np.nonzero(np.isfinite(d) & (d > 0))
        if len(rows) == 0:
            continue
        pix = np.stack([(cols * stride + 0.5), (rows * stride + 0.5), np.ones(len(rows))], 1)
        ray = pix @ np.linalg.inv(np.asarray(cam.K, np.float64)).T
        c2w = np.linalg.inv(np.asarray(cam.world_to_camera, np.float64))
        p = (ray * d[rows, cols, None]) @ c2w[:3, :3].T + c2w[:3, 3]
        pts.append(p[np.linalg.norm(p, axis=1) <= radius])
    if not pts:
        return None
    p = np.concatenate(pts)
    lowest_camera = min(float(np.linalg.inv(np.asarray(c.world_to_camera, np.float64))[:3, 3] @ up) for c in cameras)
    p = p[p @ up < lowest_camera - BELOW_CAMERAS]
    if len(p) < 100:
        return None
    rng = np.random.default_rng(seed)
    if len(p) > MAX_POINTS:
        p = p[rng.choice(len(p), MAX_POINTS, replace=False)]
    cos_tilt = np.cos(np.deg2rad(MAX_TILT))
    # all tries at once: normals of random triples, those within MAX_TILT of up scored on a subset of the points
    tri = p[rng.integers(0, len(p), size=(RANSAC_ITERATIONS, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(n, axis=1)
    ok = ln > 1e-12
    n = n[ok] / ln[ok, None]
    n *= np.where(n @ up < 0, -1.0, 1.0)[:, None]
    anchor = tri[ok, 0]
    keep = n @ up >= cos_tilt
    n, anchor = n[keep], anchor[keep]
    if not len(n):
        return None
    sub = p[rng.choice(len(p), min(len(p), SCORE_POINTS), replace=False)]
    share = np.empty(len(n))
    for i in range(0, len(n), 256):  # (256 planes x 20k points at a time: 40 MB)
        share[i:i + 256] = (np.abs(sub @ n[i:i + 256].T - np.einsum("ij,ij->i", anchor[i:i + 256], n[i:i + 256]))
                            < tolerance).mean(0)
    good = np.nonzero(share >= min_share)[0]
    if not len(good):
        return None
    # (height along up under the cameras' centre, normal, height along the normal, inliers) of each plane that holds
    # enough points. The plane's height where the vertical through the cameras' centre meets it, not a sample
    # point's: a floor tilted from the guessed up spans heights (6 degrees over 3 m: 0.3), and a plane through one
    # low floor point and the table counted as the lowest (a synthetic room: the table top came out as the floor)
    # (inliers: the subset's share; the refit below is checked on all the points)
    centre = np.mean([np.linalg.inv(np.asarray(c.world_to_camera, np.float64))[:3, 3] for c in cameras], axis=0)
    h_good = np.einsum("ij,ij->i", anchor[good], n[good])
    under = centre @ up + (h_good - n[good] @ centre) / (n[good] @ up)
    candidates = [(float(under[j]), n[i], float(h_good[j]), float(share[i])) for j, i in enumerate(good)]
    # the floor: the lowest plane that enough points lie on (a stool's or a table's top can hold as many)
    lowest = min(c[0] for c in candidates)
    near = [c for c in candidates if c[0] <= lowest + 4 * tolerance]
    _, n, h, _ = max(near, key=lambda c: c[3])
    for _ in range(3):  # least squares on the inliers
        on = np.abs(p @ n - h) < tolerance
        c = p[on].mean(0)
        n = np.linalg.svd(p[on] - c, full_matrices=False)[2][-1]
        n = n if n @ up > 0 else -n
        h = float(c @ n)
    on = np.abs(p @ n - h) < tolerance
    if on.sum() < min_share * len(p) or n @ up < cos_tilt:
        return None
    a, b = plane_axes(n)
    uv = np.stack([p[on] @ a, p[on] @ b], 1)
    try:
        hull = uv[ConvexHull(uv).vertices]  # counter-clockwise in 2D
    except Exception:  # noqa: BLE001 - degenerate (collinear) points: no reach to speak of
        return None
    centre = hull.mean(0)
    out = hull - centre
    hull = hull + margin * out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    return Ground(up=n, height=h, a=a, b=b, hull=hull, thickness=float(thickness), reach=float(reach))
