"""The normalising similarity (translation + one uniform scale, never a rotation) and its application.

Rule ('auto'):
- 'cameras' (default; 3DGS / NeRF++ style): centre = mean camera centre; radius = CAMERA_RADIUS_MARGIN x the largest
  distance of a camera centre from it. Cameras then lie within the sphere of radius 1/1.1 about the origin.
  Captures that know their object box (NeRF-synthetic) use the box centre instead of the mean camera centre.
- 'points', used by 'auto' when the cameras barely move compared with how far away the content is (forward-facing
  and RGB-D captures: camera spread < FORWARD_FACING_RATIO x the median distance of the points from the mean
  camera centre): the box holding the camera centres and the central POINT_PERCENTILE_RANGE of the points on every
  axis; centre = box centre, radius = half its diagonal. Content and cameras then lie within the unit sphere.
- 'none': identity. A radius of zero (one camera, no points) gives scale 1.
x_norm = N @ x_capture with N = [[s I, -s c], [0, 1]], s = 1 / radius.
"""
from __future__ import annotations

import numpy as np

CAMERA_RADIUS_MARGIN = 1.1  # radius of the camera centres is enlarged by this factor (unitless)
FORWARD_FACING_RATIO = 0.25  # camera spread / median point distance below which 'auto' uses the points
POINT_PERCENTILE_RANGE = (2.0, 98.0)  # percent: robust box of the points on each axis
MIN_RADIUS = 1e-12  # capture units: radius below this counts as zero


def similarity(center: np.ndarray, radius: float) -> np.ndarray:
    s = 1.0 / radius if radius > MIN_RADIUS else 1.0
    N = np.eye(4)
    N[:3, :3] *= s
    N[:3, 3] = -s * np.asarray(center, dtype=np.float64)
    return N


def robust_box(points: np.ndarray) -> np.ndarray:
    """[2,3] per-axis percentile box of the points (POINT_PERCENTILE_RANGE)."""
    lo, hi = POINT_PERCENTILE_RANGE
    return np.stack([np.percentile(points, lo, axis=0), np.percentile(points, hi, axis=0)])


def choose_rule(centers: np.ndarray, points: np.ndarray | None, requested: str) -> str:
    if requested != "auto":
        if requested == "points" and (points is None or len(points) == 0):
            raise ValueError("normalize='points' needs a capture with points (COLMAP points or RGB-D depth)")
        return requested
    if points is None or len(points) == 0:
        return "cameras"
    c = centers.mean(0)
    spread = np.linalg.norm(centers - c, axis=1).max()
    depth = np.median(np.linalg.norm(points - c, axis=1))
    return "points" if spread < FORWARD_FACING_RATIO * depth else "cameras"


def normalization(
    centers: np.ndarray, points: np.ndarray | None, requested: str = "auto", center: np.ndarray | None = None
) -> tuple[np.ndarray, str]:
    """(N [4,4], rule used) for camera centres [C,3] and optional points [P,3], both in the capture frame.

    center: the known centre of the content (object box), used by the 'cameras' rule instead of the camera mean.
    """
    rule = choose_rule(centers, points, requested)
    if rule == "none":
        return np.eye(4), rule
    if rule == "cameras":
        c = centers.mean(0) if center is None else np.asarray(center, dtype=np.float64)
        r = CAMERA_RADIUS_MARGIN * float(np.linalg.norm(centers - c, axis=1).max())
        return similarity(c, r), rule
    box = robust_box(points)
    lo = np.minimum(box[0], centers.min(0))
    hi = np.maximum(box[1], centers.max(0))
    return similarity(0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))), rule


def apply_to_points(N: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ N[:3, :3].T + N[:3, 3]


def apply_to_world_to_camera(N: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """World-to-camera of the normalised frame: the camera frame is scaled by s too, so R stays a rotation.

    x_cam_norm = s x_cam = S @ w2c @ N^-1 @ x_norm with S = diag(s, s, s, 1).
    """
    s = float(np.cbrt(np.linalg.det(N[:3, :3])))
    S = np.diag([s, s, s, 1.0])
    out = S @ w2c @ np.linalg.inv(N)
    out[3] = [0.0, 0.0, 0.0, 1.0]
    return out
