"""Tracking: one frame's camera pose by minimising photometric (L1 + D-SSIM) and depth L1 losses through the
differentiable renderer, coarse to fine, with Adam on an se(3) increment and a convergence test.

Where the pose gradient comes from: the map's vertices are moved into the camera frame in torch,
p_cam = exp(xi) (R0 p + t0), and rendered with an identity world_to_camera, so d loss / d xi is autograd of the
renderer's exact position gradients through exp_se3 (`trisplat.slam.se3`), not an image-gradient approximation.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from trisplat.render.rasterize import rasterize
from trisplat.slam.se3 import exp_se3
from trisplat.slam.track_kernels import (
    NOISE_A,
    NOISE_B,
    NOISE_Z0,
    SERIAL_BELOW,
    normal_equations,
    normal_equations_serial,
)
from trisplat.train.losses import photometric

IDENTITY = torch.eye(4, dtype=torch.float64)


@dataclass
class TrackConfig:
    """Tracking settings. Levels are extra downscale factors of the processing resolution, coarse to fine."""

    levels: tuple[int, ...] = (4, 2, 1)
    max_iters: tuple[int, ...] = (12, 10, 8)
    optimizer: str = "dense"
    """'dense': Gauss-Newton / Levenberg-Marquardt on the analytic SE(3) Jacobian of photometric and depth residuals
    (the map rendered once at the guess, the observation warped onto it; track_dense); 'gn': the renderer's exact
    gradient preconditioned by the Gauss-Newton metric of point-to-plane depth residuals, with a backtracking line
    search on the loss; 'adam': Adam on the increment (lr_* below)"""
    photo_sigma: float = 0.05
    """'dense': scale of a photometric residual (grey level in [0,1]): residuals are divided by it ..."""
    depth_sigma: float = 0.01
    """... and of a depth residual (metres) at 1 m, so both terms are unitless in the normal equations"""
    depth_residual: Literal["projective", "point_to_plane"] = "projective"
    """'dense': the depth term. 'projective': D_obs(pi(T X)) - (T X)_z, along the observed camera's axis;
    'point_to_plane': n . (P_obs - T X), the distance from the moved map point to the plane of the observed point
    P_obs (the observed depth at pi(T X) on the same ray) with the observation's normal n there (KinectFusion's and
    Open3D's ICP term): equal to the projective residual times (n . T X) / (T X)_z, so it shrinks where the view
    grazes the surface; the correspondence is held fixed in its Jacobian -[n, (T X) x n]"""
    depth_noise: float = 0.0
    """'dense': how much a depth residual's scale follows a structured-light sensor's noise with depth z (metres):
    depth_sigma x (1 - depth_noise + depth_noise x q(z)), q(z) = (0.0012 + 0.0019 (z - 0.4)^2) / q(1) (Kinect v1's
    axial noise, Nguyen, Izadi and Lovell 2012: 1.9 mm at 1 m, 6.1 mm at 2 m, 14 mm at 3 m). 0: the same scale at
    every depth"""
    huber: float = 1.0
    """'dense': Huber threshold of the scaled residuals (weights 1 below, huber/|r| above)"""
    depth_edge: float = 0.05
    """'dense': pixels whose rendered or observed depth differs from a neighbour's by more than this fraction are
    depth edges (occlusion boundaries) and are left out"""
    rerender_m: float = 0.005
    """'dense': when the pose moved more than this (metres) or rerender_deg from the guess, the map is rendered again
    at the new pose and the finest level is solved once more"""
    rerender_deg: float = 0.5
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


def _grey(rgb: np.ndarray) -> np.ndarray:
    if rgb.ndim != 3:
        return rgb
    return (rgb[..., 0] + rgb[..., 1] + rgb[..., 2]) * (1.0 / 3.0)  # the channels' mean (faster than .mean(-1))


def _edges(depth: np.ndarray, frac: float) -> np.ndarray:
    """[H,W] bool: invalid depth, or a 4-neighbour differing by more than frac of the depth (a depth edge)."""
    bad = depth <= 0
    d = depth
    for sl_a, sl_b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                       ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        jump = np.abs(d[sl_a] - d[sl_b]) > frac * np.minimum(d[sl_a], d[sl_b])
        jump |= (d[sl_a] <= 0) | (d[sl_b] <= 0)
        bad[sl_a] |= jump
        bad[sl_b] |= jump
    return bad


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """img sampled at pixel coordinates (x, y) (pixel centres at integers); returns (values, x0, y0) with x0, y0 the
    upper-left neighbours (the caller checks the 4 neighbours); coordinates must lie in [0, W-1) x [0, H-1)."""
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    ax, ay = x - x0, y - y0
    v = ((1 - ay) * ((1 - ax) * img[y0, x0] + ax * img[y0, x0 + 1])
         + ay * ((1 - ax) * img[y0 + 1, x0] + ax * img[y0 + 1, x0 + 1]))
    return v, x0, y0


def _se3_left(dx: np.ndarray) -> np.ndarray:
    from trisplat.slam.se3 import exp_se3

    return exp_se3(torch.as_tensor(dx, dtype=torch.float64)).numpy()


@dataclass
class _Level:
    X: np.ndarray  # [N,3] map points in the guess's camera frame
    Ir: np.ndarray  # [N] their rendered grey
    Io: np.ndarray  # [h,w] observed grey
    gIo: tuple  # its x / y gradients
    Do: np.ndarray  # [h,w] observed depth
    gDo: tuple
    Dbad: np.ndarray  # observed depth edge / invalid
    K: np.ndarray
    photo: bool  # the photometric term is used (the observation is not flat, e.g. a black frame)
    n_valid: int  # valid observed depth pixels
    Xall: np.ndarray  # [M,3] every covered map pixel's point, depth edges included (coverage)
    No: np.ndarray  # [h,w,3] the observation's normals (point_to_plane; zero where unknown), else [1,1,3] zeros


def _make_level(rgb_r, surf_r, ok_r, rgb_o, depth_o, K, cfg: TrackConfig) -> _Level:
    def points(mask):
        v, u = np.nonzero(mask)
        z = surf_r[v, u].astype(np.float64)
        return np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * z, (v + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1), v, u

    ok = ok_r & ~_edges(np.where(ok_r, surf_r, 0.0), cfg.depth_edge)
    X, v, u = points(ok)
    Io = _grey(rgb_o).astype(np.float64)
    Do = depth_o.astype(np.float64)
    gy, gx = np.gradient(Io)
    dy, dx = np.gradient(Do)
    bad = _edges(Do, cfg.depth_edge)
    No = depth_normals(Do, bad, K) if cfg.depth_residual == "point_to_plane" else np.zeros((1, 1, 3))
    return _Level(X, _grey(rgb_r)[v, u].astype(np.float64), Io, (gx, gy), Do, (dx, dy), bad,
                  K, float(Io.std()) > 1e-3, int((Do > 0).sum()), points(ok_r & (surf_r > 0))[0], No)


def depth_normals(depth: np.ndarray, bad: np.ndarray, K: np.ndarray) -> np.ndarray:
    """[h,w,3] unit normals of a depth map's surface (camera frame, facing the camera: n . P < 0), from the central
    differences of the back-projected points; zero where the pixel or one of its 4 neighbours is `bad` (invalid
    depth, a depth edge) or on the border."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    P = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * depth, (v + 0.5 - K[1, 2]) / K[1, 1] * depth, depth], -1)
    n = np.zeros((h, w, 3))
    du = P[1:-1, 2:] - P[1:-1, :-2]
    dv = P[2:, 1:-1] - P[:-2, 1:-1]
    c = np.cross(du, dv)
    norm = np.linalg.norm(c, axis=-1, keepdims=True)
    c = np.where(norm > 0, c / np.maximum(norm, 1e-300), 0.0)
    c *= -np.sign(np.sum(c * P[1:-1, 1:-1], -1, keepdims=True) + 1e-300)  # towards the camera
    ok = ~(bad[1:-1, 1:-1] | bad[1:-1, 2:] | bad[1:-1, :-2] | bad[2:, 1:-1] | bad[:-2, 1:-1])
    n[1:-1, 1:-1] = np.where(ok[..., None], c, 0.0)
    return n


def _coverage(L: _Level, T: np.ndarray, outlier: float) -> tuple[float, float]:
    """(fraction of the observation's valid-depth pixels that some covered map pixel moved by T lands on within
    `outlier` metres, the mean |depth residual| of those landings): _coverage_reference in one Numba pass."""
    from trisplat.slam.track_kernels import coverage

    distinct, hits, total = coverage(np.ascontiguousarray(L.Xall, np.float64), np.ascontiguousarray(L.Do, np.float64),
                                     np.ascontiguousarray(L.K, np.float64), np.ascontiguousarray(T, np.float64),
                                     float(outlier))
    if hits == 0:
        return 0.0, 0.0
    return distinct / max(1, L.n_valid), total / hits


def _coverage_reference(L: _Level, T: np.ndarray, outlier: float) -> tuple[float, float]:
    """What _coverage computes, with numpy arrays of every point (the tests' oracle)."""
    Q = L.Xall @ T[:3, :3].T + T[:3, 3]
    h, w = L.Do.shape
    z = Q[:, 2]
    zs = np.where(z > 1e-3, z, 1.0)
    u = np.floor(L.K[0, 0] * Q[:, 0] / zs + L.K[0, 2]).astype(np.int64)
    v = np.floor(L.K[1, 1] * Q[:, 1] / zs + L.K[1, 2]).astype(np.int64)
    ins = (z > 1e-3) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z = u[ins], v[ins], z[ins]
    d = L.Do[v, u]
    hit = (d > 0) & (np.abs(d - z) < outlier)
    if not hit.any():
        return 0.0, 0.0
    landed = np.zeros(h * w, np.bool_)  # distinct pixels landed on (a mask: np.unique's sort is slower)
    landed[v[hit] * w + u[hit]] = True
    return int(np.count_nonzero(landed)) / max(1, L.n_valid), float(np.abs(d[hit] - z[hit]).mean())


def _residuals(L: _Level, T: np.ndarray, cfg: TrackConfig) -> dict:
    """The level's map points moved by T (guess camera -> observed camera) and projected into the observation, kept
    where the observed depth there is valid, off depth edges and within outlier_depth: their depth residuals "rD"
    (metres), photometric residuals "rI" (grey levels; None for a flat observation), the [n,6] Jacobians "JD", "JI"
    of a left perturbation exp(xi) T (translation first), "n" kept and "inside" (projected into the image)."""
    Q = L.X @ T[:3, :3].T + T[:3, 3]
    K = L.K
    h, w = L.Do.shape
    z = Q[:, 2]
    front = z > 1e-3
    zs = np.where(front, z, 1.0)
    x = K[0, 0] * Q[:, 0] / zs + K[0, 2] - 0.5  # pixel coordinates (centres at integers)
    y = K[1, 1] * Q[:, 1] / zs + K[1, 2] - 0.5
    inside = front & (x >= 0) & (x < w - 1) & (y >= 0) & (y < h - 1)
    idx = np.nonzero(inside)[0]
    x, y = x[idx], y[idx]
    Do, x0, y0 = _bilinear(L.Do, x, y)
    rD = Do - z[idx]
    ok = ~(L.Dbad[y0, x0] | L.Dbad[y0, x0 + 1] | L.Dbad[y0 + 1, x0] | L.Dbad[y0 + 1, x0 + 1])
    ok &= np.abs(rD) < cfg.outlier_depth
    idx, x, y, rD = idx[ok], x[ok], y[ok], rD[ok]
    Qk = Q[idx]
    X, Y = Qk[:, 0], Qk[:, 1]
    iz = 1.0 / Qk[:, 2]
    fx, fy = K[0, 0], K[1, 1]
    zero = np.zeros_like(iz)
    # d(u, v)/dxi in closed form: d pi/dQ . [I | -Q^] (ALGORITHM.md section 5's left perturbation)
    Ju = np.stack([fx * iz, zero, -fx * X * iz * iz, -fx * X * Y * iz * iz, fx * (1 + X * X * iz * iz), -fx * Y * iz], 1)
    Jv = np.stack([zero, fy * iz, -fy * Y * iz * iz, -fy * (1 + Y * Y * iz * iz), fy * X * Y * iz * iz, fy * X * iz], 1)
    Jz = np.stack([zero, zero, np.ones_like(iz), Y, -X, zero], 1)
    if cfg.depth_residual == "point_to_plane":
        # the observation's normal at the nearest pixel; points where it is unknown are left out
        n = L.No[np.floor(y + 0.5).astype(np.int64), np.floor(x + 0.5).astype(np.int64)]
        keep = np.any(n != 0, axis=1)
        idx, x, y, rD, Qk, n = idx[keep], x[keep], y[keep], rD[keep], Qk[keep], n[keep]
        Ju, Jv, Jz = Ju[keep], Jv[keep], Jz[keep]
        nQ = np.sum(n * Qk, 1)
        JD = -np.concatenate([n, np.cross(Qk, n)], 1)
        rD = nQ * rD / Qk[:, 2]  # n . (P_obs - Q), P_obs = Q x D_obs / Q_z on the same ray
    else:
        gx, gy = _bilinear(L.gDo[0], x, y)[0], _bilinear(L.gDo[1], x, y)[0]
        JD = gx[:, None] * Ju + gy[:, None] * Jv - Jz
    out = {"rD": rD, "JD": JD, "rI": None, "JI": None, "n": len(idx), "z": Qk[:, 2], "inside": len(inside)}
    if L.photo:  # only where the depth agrees: occlusions differ in colour too
        out["rI"] = _bilinear(L.Io, x, y)[0] - L.Ir[idx]
        gx, gy = _bilinear(L.gIo[0], x, y)[0], _bilinear(L.gIo[1], x, y)[0]
        out["JI"] = gx[:, None] * Ju + gy[:, None] * Jv
    return out


def depth_scale(z: np.ndarray, cfg: TrackConfig) -> np.ndarray:
    """The scale (metres) of a depth residual at depth z (metres): TrackConfig.depth_noise."""
    q = (NOISE_A + NOISE_B * (z - NOISE_Z0) ** 2) / (NOISE_A + NOISE_B * (1.0 - NOISE_Z0) ** 2)
    return cfg.depth_sigma * (1.0 - cfg.depth_noise + cfg.depth_noise * q)


def _normal_equations_reference(L: _Level, T: np.ndarray, cfg: TrackConfig, w_photo: float):
    """(mean robust cost, points kept, H = J^T W J [6,6], g = J^T W r [6]) of the scaled, Huber-weighted residuals of
    `_residuals` at T, in numpy: the readable reference of track_kernels.normal_equations (the tests' oracle)."""
    o = _residuals(L, T, cfg)
    ds = depth_scale(o["z"], cfg)[:, None]
    terms = [(o["rD"] / ds[:, 0], o["JD"] / ds, 1.0)]
    if o["rI"] is not None:
        terms.append((o["rI"] / cfg.photo_sigma, o["JI"] / cfg.photo_sigma, w_photo))
    cost, H, g = 0.0, np.zeros((6, 6)), np.zeros(6)
    for r, J, weight in terms:
        a = np.abs(r)
        cost += weight * float(np.where(a <= cfg.huber, 0.5 * a * a, cfg.huber * (a - 0.5 * cfg.huber)).sum())
        wr = weight * np.minimum(1.0, cfg.huber / np.maximum(a, 1e-12))
        H += (J * wr[:, None]).T @ J
        g += (J * wr[:, None]).T @ r
    return cost / max(1, o["n"]), o["n"], H, g


def _normal_equations(L: _Level, T: np.ndarray, cfg: TrackConfig, w_photo: float):
    """What _normal_equations_reference computes, in one Numba pass (track_kernels; 5x less of the tracker's time
    than the numpy arrays of every point's residuals and Jacobians)."""
    kernel = normal_equations if len(L.X) >= SERIAL_BELOW else normal_equations_serial
    cost, n, H, g = kernel(L.X, L.Ir, L.Io, L.gIo[0], L.gIo[1], L.Do, L.gDo[0], L.gDo[1], L.Dbad, L.K,
                           np.ascontiguousarray(T, np.float64), float(cfg.outlier_depth), float(cfg.depth_sigma),
                           float(cfg.photo_sigma), float(cfg.huber), float(w_photo), bool(L.photo),
                           float(cfg.depth_noise), L.No, cfg.depth_residual == "point_to_plane")
    return cost / max(1, n), int(n), H, g


def _solve_level(L: _Level, T: np.ndarray, cfg: TrackConfig, iters: int, w_photo: float):
    """Levenberg-Marquardt on the level: the normal equations (J^T W J + lambda diag) dx = -J^T W r of the scaled,
    Huber-weighted depth and photometric residuals; a step is kept when it lowers the cost, else lambda grows.
    Returns (T, cost, iterations, converged)."""
    lam = 1e-4
    cost, n, H, g = _normal_equations(L, T, cfg, w_photo)
    its, converged = 0, False
    for _ in range(iters):
        its += 1
        if n < 20:
            break
        accepted = False
        while lam < 1e6:
            dx = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-9), g)
            Tn = _se3_left(dx) @ T
            cn, nn, Hn, gn = _normal_equations(L, Tn, cfg, w_photo)
            if nn >= 20 and cn <= cost:
                accepted = True
                lam = max(lam / 10, 1e-7)
                break
            lam *= 10
        if not accepted:
            converged = True
            break
        step = np.abs(dx).max()
        gain = cost - cn
        T, cost, n, H, g = Tn, cn, nn, Hn, gn
        if step < cfg.min_step or gain < cfg.tol * cost:
            converged = True
            break
    return T, cost, its, converged


def track_dense(positions: torch.Tensor, faces: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
                sigma: float, pyramid: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]], w2c_init: np.ndarray,
                cfg: TrackConfig) -> TrackResult:
    """world_to_camera [4,4] of one frame by dense Gauss-Newton / Levenberg-Marquardt on the analytic SE(3)
    Jacobian. The map is rendered once at the guess (finest level; coarser levels box-filter it); each map pixel's
    3-D point X moves with the correction T (guess camera -> observed camera) and is projected into the observation:
    photometric residual I_obs(pi(T X)) - I_map and depth residual D_obs(pi(T X)) - (T X)_z, scaled by photo_sigma /
    depth_sigma, Huber-weighted, pixels on depth edges (rendered or observed) and with a depth residual above
    outlier_depth left out. Jacobians: dr/dxi = grad(image) . d pi / dQ . [I | -Q^] (minus e_z . [I | -Q^] for the
    depth term; xi a left perturbation, translation first, ALGORITHM.md section 5). Levels coarse to fine, the finest
    at the processing resolution; when the pose moved more than rerender_m / rerender_deg the map is rendered again
    at the new pose and the finest level solved once more. Coverage and residual (TrackResult) come from the finest
    level at the final pose."""
    from trisplat.data.rgbd_stream import _box_down, downscale_depth

    pos = positions.detach()
    faces, colors, opacities = faces.detach(), colors.detach(), opacities.detach()
    w2c0 = np.asarray(w2c_init, np.float64)
    rgb_f, depth_f, K_f = pyramid[-1]
    H, W = depth_f.shape
    # levels relative to the finest entry of the pyramid
    fin = cfg.levels[-1]
    T = np.eye(4)
    total, converged_all = 0, True

    def render(w2c):
        with torch.no_grad():
            o = rasterize(pos, faces, colors, opacities, torch.tensor(float(sigma)), torch.as_tensor(w2c), K_f, W, H,
                          opacity_mode="mean")
        a = o.alpha.numpy().astype(np.float64)
        ok = a > cfg.min_alpha
        surf = np.where(ok, o.depth.numpy() / np.maximum(a, 1e-6), 0.0)
        return o.rgb.numpy().astype(np.float64), surf, ok

    def level_data(rend, li):
        rgb_r, surf_r, ok_r = rend
        f = cfg.levels[li] // fin
        rgb_o, depth_o, K = pyramid[li]
        if f > 1:
            rgb_r = _box_down(rgb_r, f)
            surf_r = downscale_depth(surf_r, f)
            ok_r = surf_r > 0
        return _make_level(rgb_r, surf_r, ok_r, rgb_o.numpy(), depth_o.numpy(), K.numpy(), cfg)

    rend = render(w2c0)
    if not rend[2].any():
        return TrackResult(w2c0, float("inf"), 0, False, 0.0, 0.0)
    w_photo = 1.0
    L = None
    cost = None  # the robust cost of the last level solved at T (its solve computed it): None = to compute
    for li in range(len(pyramid)):
        L = level_data(rend, li)
        if len(L.X) < 20:
            cost = None
            continue
        T, cost, its, conv = _solve_level(L, T, cfg, cfg.max_iters[li], w_photo)
        total += its
        converged_all &= conv
    w2c = T @ w2c0
    from scipy.spatial.transform import Rotation

    if (np.linalg.norm(T[:3, 3]) > cfg.rerender_m
            or np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()) > cfg.rerender_deg):
        rend = render(w2c)
        if rend[2].any():
            L = level_data(rend, len(pyramid) - 1)
            T2, cost, its, conv = _solve_level(L, np.eye(4), cfg, cfg.max_iters[-1], w_photo)
            total += its
            converged_all &= conv
            w2c = T2 @ w2c
            T = T2
        else:
            T, cost = np.eye(4), None
    else:
        pass  # L is the finest level at w2c0, T the correction to apply
    if L is None or len(L.X) < 20:
        return TrackResult(w2c, float("inf"), total, False, 0.0, 0.0)
    if cost is None:
        cost = _normal_equations(L, T, cfg, w_photo)[0]
    coverage, residual = _coverage(L, T, cfg.outlier_depth)
    return TrackResult(w2c, float(cost), total, converged_all, min(1.0, coverage), residual)


def track_frame(positions: torch.Tensor, faces: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
                sigma: float, pyramid: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]], w2c_init: np.ndarray,
                cfg: TrackConfig) -> TrackResult:
    """Estimate world_to_camera [4,4] of one frame. pyramid: per level of cfg.levels, (rgb [h,w,3], depth [h,w],
    K [3,3] float64) of the observation. Map tensors are used detached."""
    if cfg.optimizer == "dense":
        return track_dense(positions, faces, colors, opacities, sigma, pyramid, w2c_init, cfg)
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
