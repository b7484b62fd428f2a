"""SE(3) for tracking: the exponential map in torch (differentiable); trajectory files and ATE re-exported from
trisplat.slam.trajectory (numpy only)."""
from __future__ import annotations

import torch

from trisplat.slam.trajectory import (  # noqa: F401  (re-exported)
    ate_rmse,
    log_so3_angle,
    read_tum_trajectory,
    write_tum_trajectory,
)

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

