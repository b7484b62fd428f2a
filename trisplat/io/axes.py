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
# mean is trusted to say which way is up; below it (e.g. cameras all around a sphere) the default is used.
MIN_CAMERA_UP_AGREEMENT = 0.5
# An estimate within this angle (degrees) of a coordinate axis is taken to be that axis exactly: captures made in
# an axis-aligned frame (Blender, NeRF-synthetic, gravity-aligned COLMAP) then rotate by exact quarter turns.
SNAP_TO_AXIS_DEG = 15.0
# The cameras' right vectors pin the vertical down only when they point in at least two clearly different
# directions: the second singular value of the stacked unit right vectors [C,3] above this times sqrt(C) (nerfstudio's
# threshold); below it (every photo taken facing one way) only the direction along the right vectors is removed
# from the mean up vector.
MIN_RIGHT_SPREAD = 0.17
# Capture formats whose frame is Z-up by definition: Blender scenes (the NeRF-synthetic transforms_*.json captures
# are rendered in Blender, whose world is Z-up).
Z_UP_FORMATS = ("blender",)


def estimate_capture_up(cameras: Sequence[Camera], capture_format: str | None = None) -> np.ndarray | None:
    """The capture's up direction (unit [3], world frame).

    A format with an up convention (Z_UP_FORMATS: Blender / NeRF-synthetic) gives +Z. Otherwise it is estimated
    from the cameras, as nerfstudio's 'vertical' orientation does: photos are taken without roll, so every
    camera's right vector (+x, OpenCV) is horizontal whatever its pitch, and the vertical is the direction most
    orthogonal to all of them (the last right singular vector of the stacked right vectors), signed by the mean up
    vector (-y: image y points down). The mean up vector alone is biased by the pitch of cameras looking down at
    an object: 8 of lego's cameras gave an up 24 degrees off +Z. When the right vectors all point one way (a
    forward-facing capture) only their direction is removed from the mean up vector.

    None when there are no cameras or their up vectors disagree (mean of unit up vectors shorter than
    MIN_CAMERA_UP_AGREEMENT). A result within SNAP_TO_AXIS_DEG of +-X, +-Y or +-Z is returned as that axis.
    """
    if len(cameras) == 0:
        return None
    if capture_format in Z_UP_FORMATS:
        return np.array([0.0, 0.0, 1.0])
    rot = np.stack([np.asarray(c.world_to_camera, dtype=np.float64)[:3, :3] for c in cameras])
    rot = rot / np.linalg.norm(rot, axis=2, keepdims=True)  # rows: the camera axes in the world frame
    mean_up = -rot[:, 1].mean(axis=0)
    agreement = float(np.linalg.norm(mean_up))
    if agreement < MIN_CAMERA_UP_AGREEMENT:
        return None
    mean_up /= agreement
    rights = rot[:, 0]
    _, sv, vt = np.linalg.svd(rights, full_matrices=False)
    if len(sv) >= 2 and sv[1] > MIN_RIGHT_SPREAD * np.sqrt(len(rights)):
        up = vt[-1] if float(vt[-1] @ mean_up) >= 0 else -vt[-1]
    else:
        up = mean_up - vt[0] * float(vt[0] @ mean_up)
        if np.linalg.norm(up) < 1e-9:
            return None
    up = up / np.linalg.norm(up)
    axis = int(np.argmax(np.abs(up)))
    if np.degrees(np.arccos(min(abs(float(up[axis])), 1.0))) <= SNAP_TO_AXIS_DEG:
        snapped = np.zeros(3)
        snapped[axis] = np.sign(up[axis])
        return snapped
    return up


def capture_up(data) -> np.ndarray | None:
    """The up direction of a loaded capture (SceneData), as every export and its inverse use it: from its format's
    convention, else estimated from its training cameras (estimate_capture_up)."""
    train = getattr(data, "train_indices", None)
    cams = data.cameras if train is None or len(train) == 0 else [data.cameras[int(i)] for i in train]
    return estimate_capture_up(cams, getattr(data, "format", None) or None)


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
