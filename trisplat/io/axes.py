"""Up-axis handling for exports: estimate a capture's up direction and the rotation that makes it +Y or +Z."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from trisplat.cameras import Camera

UP_AXES = {"y": np.array([0.0, 1.0, 0.0]), "z": np.array([0.0, 0.0, 1.0])}

# When the capture's up direction is unknown, `up='y'` assumes a Z-up capture (Blender, NeRF-synthetic) and
# `up='z'` assumes a Y-up capture (glTF, most engines): the usual +-90 degree turn about X between the two.
DEFAULT_CAPTURE_UP = {"y": np.array([0.0, 0.0, 1.0]), "z": np.array([0.0, 1.0, 0.0])}

# The cameras' up vectors must agree this much (norm of their mean unit vector, 1 = all parallel) before their
# mean is trusted as the capture's up direction; below it (e.g. cameras all around a sphere) the default is used.
MIN_CAMERA_UP_AGREEMENT = 0.5
# An estimate within this angle (degrees) of a coordinate axis is taken to be that axis exactly: captures made in
# an axis-aligned frame (Blender, NeRF-synthetic, gravity-aligned COLMAP) then rotate by exact quarter turns.
SNAP_TO_AXIS_DEG = 15.0


def estimate_capture_up(cameras: Sequence[Camera]) -> np.ndarray | None:
    """The capture's up direction (unit [3], world frame) as the mean of the cameras' up vectors.

    A camera's up is its -y axis (OpenCV: y points down in the image). Photos are mostly taken upright, so the
    mean is a good estimate; returns None when there are no cameras or they disagree (agreement below
    MIN_CAMERA_UP_AGREEMENT). A mean within SNAP_TO_AXIS_DEG of +-X, +-Y or +-Z is returned as that axis.
    """
    if len(cameras) == 0:
        return None
    ups = np.stack([-c.world_to_camera[1, :3] / np.linalg.norm(c.world_to_camera[1, :3]) for c in cameras])
    mean = ups.mean(axis=0)
    n = float(np.linalg.norm(mean))
    if n < MIN_CAMERA_UP_AGREEMENT:
        return None
    mean = mean / n
    axis = int(np.argmax(np.abs(mean)))
    if np.degrees(np.arccos(min(abs(float(mean[axis])), 1.0))) <= SNAP_TO_AXIS_DEG:
        snapped = np.zeros(3)
        snapped[axis] = np.sign(mean[axis])
        return snapped
    return mean


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3,3] taking unit vector `a` to unit vector `b` (180 degrees about an axis
    perpendicular to `a` when they are opposite)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-12:
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        perp /= np.linalg.norm(perp)
        return 2.0 * np.outer(perp, perp) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def up_rotation(up: str | None, capture_up: np.ndarray | None = None) -> np.ndarray:
    """The [4,4] rotation applied to exports for `up`.

    up=None: identity (the capture's own axes). up='y' / 'z': the smallest rotation taking `capture_up` (the
    capture's up direction, e.g. from `estimate_capture_up`) to +Y / +Z. Without `capture_up`, 'y' assumes a
    Z-up capture, (x, y, z) -> (x, z, -y), and 'z' assumes a Y-up capture, (x, y, z) -> (x, -z, y).
    """
    M = np.eye(4)
    if up is None:
        return M
    if up not in UP_AXES:
        raise ValueError(f"up axis must be None, 'y' or 'z', got {up!r}")
    src = DEFAULT_CAPTURE_UP[up] if capture_up is None else np.asarray(capture_up, dtype=np.float64)
    if src.shape != (3,) or not np.isfinite(src).all() or np.linalg.norm(src) == 0:
        raise ValueError(f"capture_up must be a non-zero finite 3-vector, got {capture_up!r}")
    M[:3, :3] = rotation_between(src, UP_AXES[up])
    return M
