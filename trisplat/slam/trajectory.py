"""Camera trajectories without torch: TUM trajectory files and ATE (rigid alignment: trisplat.sfm.align)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from trisplat.io.atomic import atomic_write_text
from trisplat.sfm.align import umeyama


def log_so3_angle(R: np.ndarray) -> float:
    """Rotation angle (radians) of a [3,3] rotation matrix."""
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


def write_tum_trajectory(path: str | Path, stamps, c2ws) -> Path:
    """TUM trajectory file: one line 'stamp tx ty tz qx qy qz qw' (camera-to-world) per pose."""
    path = Path(path)
    lines = ["# trisplat slam: timestamp tx ty tz qx qy qz qw (camera-to-world, OpenCV camera axes, metres)"]
    for t, T in zip(stamps, c2ws):
        q = Rotation.from_matrix(T[:3, :3]).as_quat(canonical=True)  # x, y, z, w (scalar last, as TUM), w >= 0
        lines.append(f"{t:.6f} " + " ".join(f"{x:.9f}" for x in (*T[:3, 3], *q)))
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [N], camera-to-world [N,4,4]) of a TUM trajectory file."""
    path = Path(path)
    stamps, poses = [], []
    for no, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        vals = line.split()
        try:
            nums = [float(x) for x in vals]
        except ValueError:
            raise ValueError(f"{path}:{no}: malformed trajectory line (need 8 numbers)") from None
        if len(nums) != 8:
            raise ValueError(f"{path}:{no}: malformed trajectory line: {len(nums)} values, need 8")
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(nums[4:8]).as_matrix()  # TUM's qx qy qz qw: scipy's scalar-last order
        T[:3, 3] = nums[1:4]
        stamps.append(nums[0])
        poses.append(T)
    return np.array(stamps), np.array(poses).reshape(-1, 4, 4)


def ate_rmse(est_c2w: np.ndarray, ref_c2w: np.ndarray) -> tuple[float, np.ndarray]:
    """Absolute trajectory error: RMSE (same units as the poses) of camera centres after the rigid (SE(3), no scale)
    alignment of the estimate onto the reference; also returns the per-frame errors."""
    e, r = est_c2w[:, :3, 3], ref_c2w[:, :3, 3]
    if len(e) < 3:
        raise ValueError(f"ATE needs at least 3 poses with a reference, got {len(e)}")
    _, R, t = umeyama(e, r, scale=False)
    err = np.linalg.norm(e @ R.T + t - r, axis=1)
    return float(np.sqrt(np.mean(err**2))), err
