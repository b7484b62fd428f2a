"""Tracking: one frame's camera pose by minimising photometric (L1 + D-SSIM) and depth L1 losses through the
differentiable renderer, coarse to fine, with Adam on an se(3) increment and a convergence test.

Where the pose gradient comes from: the map's vertices are moved into the camera frame in torch,
p_cam = exp(xi) (R0 p + t0), and rendered with an identity world_to_camera, so d loss / d xi is autograd of the
renderer's exact position gradients through exp_se3 (`trisplat.slam.se3`), not an image-gradient approximation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from trisplat.render.rasterize import rasterize
from trisplat.slam.se3 import exp_se3
from trisplat.train.losses import photometric

IDENTITY = torch.eye(4, dtype=torch.float64)


@dataclass
class TrackConfig:
    """Tracking settings. Levels are extra downscale factors of the processing resolution, coarse to fine."""

    levels: tuple[int, ...] = (4, 2, 1)
    max_iters: tuple[int, ...] = (12, 10, 8)
    optimizer: str = "gn"
    """'gn': the exact gradient preconditioned by the Gauss-Newton metric of point-to-plane depth residuals, with a
    backtracking line search on the loss; 'adam': Adam on the increment (lr_* below)"""
    damping: float = 1e-4
    """relative Levenberg damping of the metric (x its mean eigenvalue)"""
    """iteration cap per level (count); a level stops earlier once converged"""
    lr_translation: float = 2e-3
    """Adam step of the translation increment at the coarsest level (metres)"""
    lr_rotation: float = 2e-3
    """Adam step of the rotation increment at the coarsest level (radians)"""
    lr_level_decay: float = 0.5
    """learning rates are multiplied by this at each finer level (unitless)"""
    lambda_dssim: float = 0.2
    w_color: float = 0.5
    """weight of the photometric term (unitless, colours in [0,1])"""
    w_depth: float = 10.0
    """weight of the depth L1 term (per metre)"""
    min_alpha: float = 0.9
    """pixels count only where the rendered alpha exceeds this (well-covered pixels)"""
    outlier_depth: float = 0.1
    """pixels whose rendered and observed depths differ by more than this (metres) are ignored"""
    tol: float = 1e-3
    """converged when no iteration in the last `patience` improved the best loss by this fraction ..."""
    patience: int = 5
    min_step: float = 2e-6
    """... or when an iteration moved the pose by less than this (metres / radians)"""


@dataclass
class TrackResult:
    w2c: np.ndarray
    loss: float
    iterations: int
    converged: bool
    coverage: float
    """fraction of valid-depth pixels that were well covered at the finest level"""
    residual: float = 0.0
    """mean |rendered - observed| depth (metres) over those pixels at the finest level"""


def pose_loss(pos_cam: torch.Tensor, faces, colors, opacities, sigma: float, rgb: torch.Tensor, depth: torch.Tensor,
              K: torch.Tensor, cfg: TrackConfig, supersample: int = 1, **render_options) -> tuple[torch.Tensor, float, float]:
    """Tracking loss of camera-frame vertex positions [V,3] against one observation (rgb [H,W,3], depth [H,W] metres,
    0 invalid); returns (loss, coverage, mean depth residual in metres). Coarse levels render `supersample` x finer
    and box-filter down, so the map's small triangles cover the coarse pixels as they cover the fine ones.
    render_options go to rasterize."""
    H, W = depth.shape
    out = rasterize(pos_cam, faces, colors, opacities, torch.tensor(float(sigma)), IDENTITY, K, W, H,
                    opacity_mode="mean", supersample=supersample, **render_options)
    alpha = out.alpha
    surf = out.depth / alpha.clamp_min(1e-6)
    valid = depth > 0
    with torch.no_grad():
        covered = alpha > cfg.min_alpha
        mask = valid & covered & ((surf - depth).abs() < cfg.outlier_depth)
        coverage = float(mask.sum()) / max(1, int(valid.sum()))
    if not bool(mask.any()):
        return out.rgb.sum() * 0.0, 0.0, 0.0
    n = mask.sum()
    l_depth = ((surf - depth).abs() * mask).sum() / n
    pm = torch.where((covered & (alpha > 0))[..., None], out.rgb, rgb)  # uncovered pixels contribute nothing
    l_rgb = photometric(pm, rgb, cfg.lambda_dssim) * (H * W) / n
    return cfg.w_color * l_rgb + cfg.w_depth * l_depth, coverage, float(l_depth.detach())


def _evaluate(pc0, xi, faces, colors, opacities, sigma, rgb, depth, K, cfg, li):
    T = exp_se3(xi)
    pc = (pc0 @ T[:3, :3].T + T[:3, 3]).float()
    return pose_loss(pc, faces, colors, opacities, sigma, rgb, depth, K, cfg, cfg.levels[li])


def _level_adam(pc0, faces, colors, opacities, sigma, rgb, depth, K, cfg: TrackConfig, li: int):
    """Adam on the se(3) increment; returns (best xi, its loss, coverage, depth residual, iterations, converged)."""
    decay = cfg.lr_level_decay**li
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([{"params": [v], "lr": cfg.lr_translation * decay},
                            {"params": [w], "lr": cfg.lr_rotation * decay}])
    hist: list[float] = []
    best = (float("inf"), torch.zeros(6, dtype=torch.float64), 0.0, 0.0)
    its, converged = 0, False
    for _ in range(cfg.max_iters[li]):
        xi = torch.cat([v, w])
        loss, cov, dres = _evaluate(pc0, xi, faces, colors, opacities, sigma, rgb, depth, K, cfg, li)
        lv = float(loss.detach())
        its += 1
        if lv < best[0]:
            best = (lv, xi.detach().clone(), cov, dres)
        hist.append(lv)
        if cov == 0.0:
            break
        opt.zero_grad()
        loss.backward()
        before = xi.detach().clone()
        opt.step()
        step = (torch.cat([v, w]).detach() - before).abs().max().item()
        # Converged: the pose stopped moving, or no new best loss (by a relative margin tol) for `patience`
        # iterations (Adam oscillates around the optimum, so a single worse step is not the test).
        if step < cfg.min_step * decay or (
            len(hist) > cfg.patience and min(hist[-cfg.patience:]) > (1 - cfg.tol) * min(hist[: -cfg.patience])
        ):
            converged = True
            break
    return best[1], best[0], best[2], best[3], its, converged


def point_to_plane_metric(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Gauss-Newton metric [6,6] = mean over valid pixels of J J^T, J = (n, q x n): the Jacobian of point-to-plane
    residuals n . (exp(xi) q - q) at xi = 0 for the observed camera-frame points q and depth normals n
    (translation first, as exp_se3)."""
    from trisplat.train.losses import depth_to_normal

    n, ok = depth_to_normal(depth.double(), K)
    H, W = depth.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                          indexing="ij")
    z = depth.double()
    q = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    J = torch.cat([n, torch.linalg.cross(q, n, dim=-1)], -1)[ok]
    if len(J) < 6:
        return torch.eye(6, dtype=torch.float64)
    return J.T @ J / len(J)


def _level_gn(pc0, faces, colors, opacities, sigma, rgb, depth, K, cfg: TrackConfig, li: int):
    """Preconditioned descent: direction -M^-1 g (g the exact autograd gradient, M the point-to-plane Gauss-Newton
    metric scaled by the mean depth residual, as iteratively reweighted least squares does for an L1 loss) with a
    backtracking line search; converged when a step no longer lowers the loss by the fraction tol or moves the
    pose by less than min_step. Returns (xi, loss, coverage, depth residual, iterations, converged)."""
    M = point_to_plane_metric(depth, K)
    M = M + cfg.damping * torch.trace(M) / 6 * torch.eye(6, dtype=torch.float64)
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    loss, cov, dres = _evaluate(pc0, xi, faces, colors, opacities, sigma, rgb, depth, K, cfg, li)
    its, converged, alpha = 1, False, 1.0
    if cov == 0.0:
        return xi.detach(), float(loss.detach()), cov, dres, its, False
    lv = float(loss.detach())
    for _ in range(cfg.max_iters[li]):
        (g,) = torch.autograd.grad(loss, xi)
        d = -torch.linalg.solve(M, g) * (max(dres, 1e-4) / max(cfg.w_depth, 1e-12))
        accepted = None
        a = min(alpha * 2.0, 4.0)
        while a >= 1.0 / 64:
            cand = (xi.detach() + a * d).requires_grad_(True)
            l2, c2, r2 = _evaluate(pc0, cand, faces, colors, opacities, sigma, rgb, depth, K, cfg, li)
            its += 1
            if c2 > 0 and float(l2.detach()) < lv:
                accepted = (cand, l2, c2, r2, a)
                break
            a *= 0.5
        if accepted is None:
            converged = True
            break
        cand, l2, c2, r2, alpha = accepted
        step = (a * d).abs().max().item()
        gain = lv - float(l2.detach())
        xi, loss, cov, dres, lv = cand, l2, c2, r2, float(l2.detach())
        if gain < cfg.tol * lv or step < cfg.min_step:
            converged = True
            break
    return xi.detach(), lv, cov, dres, its, converged


def track_frame(positions: torch.Tensor, faces: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
                sigma: float, pyramid: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]], w2c_init: np.ndarray,
                cfg: TrackConfig) -> TrackResult:
    """Estimate world_to_camera [4,4] of one frame. pyramid: per level of cfg.levels, (rgb [h,w,3], depth [h,w],
    K [3,3] float64) of the observation. Map tensors are used detached."""
    pos = positions.detach().double()
    faces, colors, opacities = faces.detach(), colors.detach(), opacities.detach()
    w2c = torch.as_tensor(w2c_init, dtype=torch.float64).clone()
    total, converged_all, loss_v, coverage, residual = 0, True, float("nan"), 0.0, 0.0
    for li, (rgb, depth, K) in enumerate(pyramid):
        pc0 = pos @ w2c[:3, :3].T + w2c[:3, 3]
        level = _level_gn if cfg.optimizer == "gn" else _level_adam
        xi, lv, cov, dres, its, converged = level(pc0, faces, colors, opacities, sigma, rgb, depth, K, cfg, li)
        total += its
        converged_all &= converged
        w2c = exp_se3(xi) @ w2c
        loss_v, coverage, residual = lv, cov, dres
    return TrackResult(w2c.numpy(), loss_v, total, converged_all, coverage, residual)
