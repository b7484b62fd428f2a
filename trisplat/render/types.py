"""RenderOutput and RenderOptions, the typed hand-off between the rasterizer and everything that uses images;
downsample: the box filter that turns a supersampled RenderOutput into its 1x image; stack_views: per-camera outputs
as one batch."""
from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class RenderOptions:
    """Settings of one rasterize() call. Every threshold has a unit.

    near: near-plane distance (view-space z, scene units); faces with any vertex nearer are culled whole.
    far: far-plane distance; faces entirely beyond are culled.
    supersample: render at s x resolution and area-downsample (s in 1, 2, 4).
    tile_size: tile edge in pixels (the per-tile depth sort granularity).
    opacity_mode: 'min' (Triangle Splatting+: the arg-min vertex gets the gradient) or 'mean' (SLAM variant).
    perspective_correct: interpolate colours with perspective-correct barycentrics instead of screen-space ones.
    linear_light: blend in linear light: the per-vertex sRGB colours (and the background) are decoded to linear
    (IEC 61966-2-1), interpolated, composited and averaged over the supersamples there, and the pixel is encoded back
    to sRGB; as a glTF viewer shows the same vertex colours (COLOR_0 is linear). False: all of it on the sRGB values.
    alpha_max: cap on per-pixel alpha (0.99). alpha_min: skip below (1/255). transmittance_min: early stop (1e-4).
    backend: 'numba' (CPU kernels), 'cuda' (numba-cuda kernels on the tensors' GPU; needs the gpu extra; tile_size
    8, 16, 24 or 32) or 'reference' (dense PyTorch, the spec in code; slow, for tests).
    min_area_px: faces whose projected area is below this (square pixels) are culled as degenerate.
    grazing_cos: faces seen edge-on, |cos(face normal, ray to centroid)| below this (unitless), are culled.
    reference_block: pixel block edge (pixels) of the dense reference (memory per block ~ faces x block^2).
    check_values: scan the inputs' values (NaN/Inf, face indices in range, opacities in [0, 1]) and refuse bad ones
    with a precise error. False skips the scans (shapes and dtypes are still checked) for a caller that guarantees
    them: the trainer checks its parameters every step, and the scans cost a pass over every array (bonsai's
    414k-face surface with SH degree 3: 7 ms of a 190 ms step).
    """

    near: float = 0.01
    far: float = 1e10
    supersample: int = 1
    tile_size: int = 16
    opacity_mode: str = "min"
    perspective_correct: bool = False
    linear_light: bool = False
    alpha_max: float = 0.99
    alpha_min: float = 1.0 / 255.0
    transmittance_min: float = 1e-4
    backend: str = "numba"
    min_area_px: float = 1e-6
    grazing_cos: float = 1e-4
    reference_block: int = 32
    check_values: bool = True


@dataclass
class RenderOutput:
    """What one view (or a batch of B views, with a leading B axis) renders to.

    rgb [H,W,3], alpha [H,W], depth [H,W] (expected view depth, sum of w_n z_n; divide by alpha for the
    surface depth), normal [H,W,3] (composited camera-facing unit face normals, camera frame),
    max_weight [F] (per face, the largest blending weight a*T over all pixels), face_id [H,W] int64 (face where the
    accumulated weight first passes 0.5, -1 if none), and counters: pairs_evaluated (pixel/face pairs the
    kernel evaluated), faces_visible (faces that survived culling).
    rgb, alpha, depth and normal are differentiable w.r.t. positions, colours/SH and opacities.
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor
    max_weight: torch.Tensor
    face_id: torch.Tensor
    pairs_evaluated: int = 0
    faces_visible: int = 0


class _BoxPool(torch.autograd.Function):
    """Area (box) downsampling of an [H*s, W*s, C] image by s, and its gradient (each sample gets 1/s^2 of its
    pixel's). The same as x.reshape(H, s, W, s, C).mean(dim=(1, 3)), which torch reduces along the strided axes
    about 2.5x slower, forward and backward: a 2x2-supersampled render at 399x266 with its backward took 364 ms
    with that, 307 ms with this (bonsai, 218k faces, 2 cores; docs/benchmarks.md, issue 24, bonsai J). Plain tensor
    operations: any device."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, s: int) -> torch.Tensor:
        H, W, C = x.shape[0] // s, x.shape[1] // s, x.shape[2]
        rows = x.reshape(H, s, W, s * C)  # a row of output pixels: s rows of samples, s samples x C per pixel
        acc = rows[:, 0].clone()
        for i in range(1, s):
            acc += rows[:, i]
        acc = acc.reshape(H, W, s, C)
        out = acc[:, :, 0].clone()
        for j in range(1, s):
            out += acc[:, :, j]
        ctx.s = s
        return out.div_(s * s)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        s = ctx.s
        H, W, C = g.shape
        return (g / (s * s))[:, None, :, None, :].expand(H, s, W, s, C).reshape(H * s, W * s, C), None


def box_downsample(x: torch.Tensor, s: int) -> torch.Tensor:
    """Area (box) downsampling of an [H*s, W*s, C] image by s: the gradient flows through."""
    return _BoxPool.apply(x, s)



def downsample(out: RenderOutput, s: int) -> RenderOutput:
    """One view rendered at s x resolution -> the image at 1x: rgb, alpha, depth and normal area-averaged over each
    pixel's s x s samples (the box filter of supersampling anti-aliasing), face_id taken at the sample nearest the
    pixel centre, per-face outputs and counters unchanged."""
    if s == 1:
        return out
    return RenderOutput(
        rgb=box_downsample(out.rgb, s),
        alpha=box_downsample(out.alpha[..., None], s)[..., 0],
        depth=box_downsample(out.depth[..., None], s)[..., 0],
        normal=box_downsample(out.normal, s),
        max_weight=out.max_weight,
        face_id=out.face_id[s // 2 :: s, s // 2 :: s].contiguous(),
        pairs_evaluated=out.pairs_evaluated,
        faces_visible=out.faces_visible,
    )


def stack_views(outs: list[RenderOutput]) -> RenderOutput:
    """Per-camera RenderOutputs as one batched RenderOutput: a leading B axis on every image and per-face output,
    the counters summed."""
    return RenderOutput(
        rgb=torch.stack([o.rgb for o in outs]),
        alpha=torch.stack([o.alpha for o in outs]),
        depth=torch.stack([o.depth for o in outs]),
        normal=torch.stack([o.normal for o in outs]),
        max_weight=torch.stack([o.max_weight for o in outs]),
        face_id=torch.stack([o.face_id for o in outs]),
        pairs_evaluated=sum(o.pairs_evaluated for o in outs),
        faces_visible=sum(o.faces_visible for o in outs),
    )
