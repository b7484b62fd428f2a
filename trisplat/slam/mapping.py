"""Mapping: joint refinement of the map's triangles over a window of keyframes with photometric (L1 + D-SSIM),
depth L1, normal-alignment and equiangularity terms."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from trisplat.slam.exposure import apply_exposure, fit_exposure
from trisplat.slam.map import SlamMap
from trisplat.train.losses import depth_to_normal, photometric


@dataclass
class MapConfig:
    iters: int = 25
    """refinement iterations per keyframe (count)"""
    first_iters: int = 60
    """iterations after the first keyframe (count)"""
    window: int = 5
    """keyframes in the refinement window: the newest ones (count); half the iterations use the newest keyframe"""
    downscale: int = 2
    """mapping while tracking (the window) renders and compares its keyframes at 1/this of the processing
    resolution (photos box-filtered, depth edge-aware as the capture's); the final refinement and the bundle
    adjustment stay at full resolution. 7-Scenes frames 0-199 at 320x240: 2 takes 21 CPU-s of mapping where 1 took
    43 (the loop 52 CPU-s against 75), ATE 1.95 against 1.96 cm (issue 52)"""
    downscale_min_width: int = 160
    """... only while the keyframes stay at least this wide (pixels) at 1/downscale: smaller frames map at their
    own resolution (at 80x60 the map is too coarse to hold poses to a centimetre)"""
    lr_position: float = 2e-4
    """Adam step of vertex positions (metres)"""
    lr_color: float = 1e-2
    """Adam step of the SH DC colour coefficients"""
    lr_opacity: float = 5e-2
    """Adam step of the opacity logits"""
    lambda_dssim: float = 0.2
    w_color: float = 0.5
    w_depth: float = 10.0
    """depth L1 weight (per metre)"""
    w_normal: float = 0.05
    """weight of 1 - n_rendered . n_depth on covered pixels with a valid depth normal"""
    w_equiangular: float = 0.01
    """weight of the equiangularity penalty 1 - 4 sqrt(3) area / sum(edge^2) (0 for equilateral faces)"""
    outlier_depth: float = 0.1
    """pixels whose rendered and observed depths differ by more than this (metres) carry no depth/normal term"""
    exposure_ridge: float = 0.01
    """per-keyframe exposure (--slam.exposure): weight of the pull of each keyframe's gain and bias towards 1 and 0,
    per usable pixel (trisplat.slam.exposure.fit_exposure). 7-Scenes, held-out map PSNR from the same map: 0.01 ->
    22.25 dB, 0.1 -> 21.98"""


@dataclass
class Keyframe:
    """A keyframe's observation at the processing resolution and its (tracked) camera-to-world."""

    frame: int
    rgb: torch.Tensor
    depth: torch.Tensor
    c2w: np.ndarray
    normal: torch.Tensor | None = None
    normal_ok: torch.Tensor | None = None
    exposure: np.ndarray | None = None
    """[2,3] gains and biases through which this photo sees the map (trisplat.slam.exposure); None: as it is"""
    fit_exposure: bool = False
    """solve the exposure again each time mapping visits this keyframe"""
    smaller: dict = field(default_factory=dict)
    """downscale factor -> this keyframe at 1/factor (its own cached normals), made on first use (at_scale)"""


def at_scale(kf: Keyframe, f: int) -> Keyframe:
    """The keyframe seen at 1/f of its resolution (f = 1: itself): photo box-filtered, depth edge-aware
    (trisplat.data.rgbd_stream), the pose and exposure those of `kf` now (a loop closure moves it)."""
    if f <= 1:
        return kf
    small = kf.smaller.get(f)
    if small is None:
        from trisplat.data.rgbd_stream import _box_down, downscale_depth

        rgb = torch.from_numpy(np.ascontiguousarray(_box_down(kf.rgb.numpy(), f), np.float32))
        depth = torch.from_numpy(np.ascontiguousarray(downscale_depth(kf.depth.numpy(), f), np.float32))
        small = kf.smaller[f] = Keyframe(kf.frame, rgb, depth, kf.c2w)
    small.c2w, small.exposure, small.fit_exposure = kf.c2w, kf.exposure, kf.fit_exposure
    return small


def equiangularity(positions: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Per-face 1 - 4 sqrt(3) area / (a^2 + b^2 + c^2): 0 for equilateral triangles, 1 for degenerate ones [F]."""
    t = positions[faces.long()]
    e0, e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 1], t[:, 0] - t[:, 2]
    area = 0.5 * torch.linalg.cross(e0, -e2, dim=1).norm(dim=1)
    s = (e0 * e0).sum(1) + (e1 * e1).sum(1) + (e2 * e2).sum(1)
    return 1.0 - 4.0 * np.sqrt(3.0) * area / s.clamp_min(1e-20)


def keyframe_loss(smap: SlamMap, kf: Keyframe, K: torch.Tensor, sigma: float, cfg: MapConfig) -> torch.Tensor:
    H, W = kf.depth.shape
    out = smap.render(np.linalg.inv(kf.c2w), K, W, H, sigma)
    if kf.normal is None:
        kf.normal, kf.normal_ok = depth_to_normal(kf.depth.double(), K)
        kf.normal = kf.normal.float()
    alpha = out.alpha
    surf = out.depth / alpha.clamp_min(1e-6)
    valid = kf.depth > 0
    with torch.no_grad():  # where the map shows what the photo shows
        mask = valid & (alpha > 0.5) & ((surf - kf.depth).abs() < cfg.outlier_depth)
    rgb = out.rgb
    if kf.exposure is not None:
        if kf.fit_exposure:  # on the pixels where the map's surface is the photo's (not its background, not occluders)
            kf.exposure = fit_exposure(rgb, kf.rgb, mask, cfg.exposure_ridge)
        rgb = apply_exposure(rgb, kf.exposure, alpha)
    n = mask.sum().clamp_min(1)
    loss = cfg.w_color * photometric(rgb, kf.rgb, cfg.lambda_dssim)
    loss = loss + cfg.w_depth * ((surf - kf.depth).abs() * mask).sum() / n
    # Observed surface not covered: pull alpha up there (depth says something is there).
    loss = loss + 0.1 * ((1 - alpha) * valid).sum() / valid.sum().clamp_min(1)
    nm = mask & kf.normal_ok
    if cfg.w_normal > 0 and bool(nm.any()):
        loss = loss + cfg.w_normal * ((alpha - (out.normal * kf.normal).sum(-1)) * nm).sum() / nm.sum()
    return loss


def refine(smap: SlamMap, keyframes: list[Keyframe], K: np.ndarray, sigma: float, iters: int, cfg: MapConfig,
           rng: np.random.Generator, sigma_end: float | None = None, window: int | None = None) -> float:
    """Refine positions, colours and opacities over the newest `window` keyframes (half the iterations on the newest),
    or over all of them in shuffled rounds when window is 0; sigma moves linearly to sigma_end when given (the
    soft-to-hard schedule). Returns the last loss."""
    if smap.num_faces == 0 or not keyframes or iters <= 0:
        return float("nan")
    sc = smap.scene
    for t in (sc.positions, sc.sh, sc.opacity_logit):
        t.requires_grad_(True)
    opt = torch.optim.Adam([
        {"params": [sc.positions], "lr": cfg.lr_position},
        {"params": [sc.sh], "lr": cfg.lr_color},
        {"params": [sc.opacity_logit], "lr": cfg.lr_opacity},
    ])
    win = cfg.window if window is None else window
    pool = keyframes[-win:] if win > 0 else keyframes
    f = max(1, int(cfg.downscale)) if win > 0 else 1
    if f > 1 and pool[-1].depth.shape[1] // f < cfg.downscale_min_width:
        f = 1
    Kt = torch.as_tensor(K, dtype=torch.float64)
    if f > 1:
        Kt = Kt.clone()
        Kt[:2] /= f
    last = float("nan")
    # A window (mapping while tracking) gives half the iterations to its newest keyframe, which nothing has fitted
    # yet. Over every keyframe (window 0: the final refinement) each keyframe counts alike: the keyframes are visited
    # in shuffled rounds, so each one is fitted once before any is fitted twice.
    order: list[int] = []
    for it in range(iters):
        if win > 0:
            kf = pool[-1] if (it % 2 == 0 or len(pool) == 1) else pool[int(rng.integers(len(pool)))]
        else:
            if not order:
                order = [int(i) for i in rng.permutation(len(pool))]
            kf = pool[order.pop()]
        sig = sigma if sigma_end is None else sigma + (sigma_end - sigma) * it / max(1, iters - 1)
        small = at_scale(kf, f)
        loss = keyframe_loss(smap, small, Kt, sig, cfg)
        if small is not kf:
            kf.exposure = small.exposure
        if cfg.w_equiangular > 0:
            loss = loss + cfg.w_equiangular * equiangularity(sc.positions, sc.faces).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        last = float(loss.detach())
    for t in (sc.positions, sc.sh, sc.opacity_logit):
        t.requires_grad_(False)
    return last
