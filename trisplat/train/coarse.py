"""Coarse-to-fine training: a view and its photo at 1/f of the training resolution (the early steps'
schedules.coarse). The camera keeps its field of view; the photo is area-averaged over f x f pixels, in linear light
where the model blends in linear light (as the renderer averages its supersamples)."""
from __future__ import annotations

import torch

from trisplat.io.colour import linear_to_srgb_ops, srgb_to_linear_ops
from trisplat.render.types import box_downsample


def coarse_intrinsics(K: torch.Tensor, f: int) -> torch.Tensor:
    """K [3,3] of an image 1/f the size (pixel centres at +0.5, so the principal point scales too); differentiable
    (refined intrinsics keep their gradient)."""
    if f == 1:
        return K
    return torch.cat([K[:2] / f, K[2:]])


def coarse_size(width: int, height: int, f: int) -> tuple[int, int]:
    """(width, height) of the coarse image: the training image's whole f x f blocks (a remainder row or column on
    the right or bottom is left out, which keeps the principal point at K / f)."""
    return width // f, height // f


def coarse_photo(gt: torch.Tensor, f: int, linear_light: bool = False) -> torch.Tensor:
    """[H,W,3] sRGB photo -> [H//f, W//f, 3], each pixel the mean of its f x f block (in linear light if asked)."""
    if f == 1:
        return gt
    H, W = gt.shape[0] // f * f, gt.shape[1] // f * f
    x = gt[:H, :W].contiguous()
    if not linear_light:
        return box_downsample(x, f)
    return linear_to_srgb_ops(box_downsample(srgb_to_linear_ops(x), f)).clamp(0.0, 1.0)
