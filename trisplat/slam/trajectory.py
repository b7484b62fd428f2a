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


def ate_summary(est_c2w, ref_c2w) -> dict | None:
    """metrics.json's "ate" entry for per-frame estimated and reference camera-to-world poses (a reference may be
    None: that frame is left out): RMSE, max and median in metres over the frames with a reference, or None with
    fewer than 3 of them."""
    have = [k for k, r in enumerate(ref_c2w) if r is not None]
    if len(have) < 3:
        return None
    rmse, err = ate_rmse(np.array([est_c2w[k] for k in have]), np.array([ref_c2w[k] for k in have]))
    return {"rmse_m": rmse, "max_m": float(err.max()), "median_m": float(np.median(err)), "frames": len(have),
            "alignment": "rigid SE(3) (Horn/Umeyama, no scale) of estimated onto reference camera centres"}


def rpe_per_second(est_c2w: np.ndarray, ref_c2w: np.ndarray, stamps: np.ndarray, delta_s: float = 1.0
                   ) -> dict | None:
    """Relative pose error over delta_s seconds (the TUM benchmark's RPE): for every frame i, the frame j nearest
    to stamps[i] + delta_s (within half the median frame interval), the error
    E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) of the estimate P against the reference Q; RMSE of its translation (metres)
    and rotation angle (degrees), each divided by the pairs' mean time span (per second). None when no pair."""
    stamps = np.asarray(stamps, np.float64)
    order = np.argsort(stamps)
    s = stamps[order]
    tol = 0.5 * float(np.median(np.diff(s))) if len(s) > 1 else 0.0
    pairs = []
    for i in range(len(stamps)):
        k = int(np.searchsorted(s, stamps[i] + delta_s))
        cands = [c for c in (k - 1, k) if 0 <= c < len(s)]
        if not cands:
            continue
        c = min(cands, key=lambda c: abs(s[c] - stamps[i] - delta_s))
        j = int(order[c])
        if abs(s[c] - stamps[i] - delta_s) <= tol and stamps[j] > stamps[i]:
            pairs.append((i, j))
    if not pairs:
        return None
    et, er, span = [], [], []
    for i, j in pairs:
        E = np.linalg.inv(np.linalg.inv(ref_c2w[i]) @ ref_c2w[j]) @ (np.linalg.inv(est_c2w[i]) @ est_c2w[j])
        et.append(np.linalg.norm(E[:3, 3]))
        er.append(np.degrees(log_so3_angle(E[:3, :3])))
        span.append(stamps[j] - stamps[i])
    dt = float(np.mean(span))
    return {"translation_m_per_s": float(np.sqrt(np.mean(np.square(et)))) / dt,
            "rotation_deg_per_s": float(np.sqrt(np.mean(np.square(er)))) / dt, "pairs": len(pairs), "delta_s": dt}
