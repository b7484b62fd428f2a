"""SE(3) for tracking: the exponential map in torch (differentiable), quaternions, TUM trajectories, ATE."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

SMALL_ANGLE2 = 1e-10  # rad^2: below this the series expansions of the exponential map are used


def hat(w: torch.Tensor) -> torch.Tensor:
    """Skew matrix [3,3] of a 3-vector (hat(w) @ v = w x v)."""
    z = torch.zeros((), dtype=w.dtype)
    return torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]), torch.stack([-w[1], w[0], z])])


def exp_se3(xi: torch.Tensor) -> torch.Tensor:
    """[4,4] matrix exp(xi^) of a twist xi = (v, w) [6] (translation part first, rotation vector last, radians);
    differentiable everywhere, including xi = 0 (series expansions below SMALL_ANGLE2)."""
    v, w = xi[:3], xi[3:]
    th2 = (w * w).sum()
    small = th2 < SMALL_ANGLE2
    th = torch.sqrt(torch.where(small, torch.ones_like(th2), th2))
    A = torch.where(small, 1 - th2 / 6, torch.sin(th) / th)
    B = torch.where(small, 0.5 - th2 / 24, (1 - torch.cos(th)) / torch.where(small, torch.ones_like(th2), th2))
    C = torch.where(small, 1.0 / 6 - th2 / 120, (th - torch.sin(th)) / (th * torch.where(small, torch.ones_like(th2), th2)))
    W = hat(w)
    W2 = W @ W
    eye = torch.eye(3, dtype=xi.dtype)
    R = eye + A * W + B * W2
    V = eye + B * W + C * W2
    top = torch.cat([R, (V @ v)[:, None]], 1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=xi.dtype)
    return torch.cat([top, bottom], 0)


def log_so3_angle(R: np.ndarray) -> float:
    """Rotation angle (radians) of a [3,3] rotation matrix."""
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


def matrix_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) with w >= 0 of a rotation matrix [3,3]."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()
    return -q if q[3] < 0 else q


def quat_xyzw_to_matrix(q) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def write_tum_trajectory(path: str | Path, stamps, c2ws) -> Path:
    """TUM trajectory file: one line 'stamp tx ty tz qx qy qz qw' (camera-to-world) per pose."""
    path = Path(path)
    lines = ["# trisplat slam: timestamp tx ty tz qx qy qz qw (camera-to-world, OpenCV camera axes, metres)"]
    for t, T in zip(stamps, c2ws):
        q = matrix_to_quat_xyzw(T[:3, :3])
        lines.append(f"{t:.6f} " + " ".join(f"{x:.9f}" for x in (*T[:3, 3], *q)))
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)
    return path


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
        T[:3, :3] = quat_xyzw_to_matrix(nums[4:8])
        T[:3, 3] = nums[1:4]
        stamps.append(nums[0])
        poses.append(T)
    return np.array(stamps), np.array(poses).reshape(-1, 4, 4)


def align_rigid(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation R [3,3] and translation t [3] with R @ est_i + t ~ ref_i (Horn/Umeyama, no scale)."""
    mu_e, mu_r = est.mean(0), ref.mean(0)
    H = (est - mu_e).T @ (ref - mu_r)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mu_r - R @ mu_e


def ate_rmse(est_c2w: np.ndarray, ref_c2w: np.ndarray) -> tuple[float, np.ndarray]:
    """Absolute trajectory error: RMSE (same units as the poses) of camera centres after the rigid (SE(3), no scale)
    alignment of the estimate onto the reference; also returns the per-frame errors."""
    e, r = est_c2w[:, :3, 3], ref_c2w[:, :3, 3]
    if len(e) < 3:
        raise ValueError(f"ATE needs at least 3 poses with a reference, got {len(e)}")
    R, t = align_rigid(e, r)
    err = np.linalg.norm(e @ R.T + t - r, axis=1)
    return float(np.sqrt(np.mean(err**2))), err
