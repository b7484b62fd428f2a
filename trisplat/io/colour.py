"""The sRGB transfer function (IEC 61966-2-1), as glTF 2.0 specifies it for colour textures and display output."""
from __future__ import annotations

import numpy as np

SRGB_LINEAR_SEGMENT = 0.04045  # sRGB-encoded value below which the curve is linear
LINEAR_SEGMENT = 0.0031308  # the same point in linear light
SRGB_SLOPE = 12.92


def srgb_to_linear(x) -> np.ndarray:
    """Decode sRGB-encoded values in [0, 1] to linear light (float64 for float64 input, else float32)."""
    x = np.asarray(x)
    dt = np.float64 if x.dtype == np.float64 else np.float32
    x = x.astype(dt, copy=False)
    return np.where(x <= SRGB_LINEAR_SEGMENT, x / SRGB_SLOPE, ((np.maximum(x, SRGB_LINEAR_SEGMENT) + 0.055) / 1.055) ** 2.4
                    ).astype(dt)


def linear_to_srgb(x) -> np.ndarray:
    """Encode linear light in [0, 1] (clipped) to sRGB values in [0, 1]."""
    x = np.clip(np.asarray(x), 0.0, 1.0)
    dt = np.float64 if x.dtype == np.float64 else np.float32
    x = x.astype(dt, copy=False)
    return np.where(x <= LINEAR_SEGMENT, x * SRGB_SLOPE,
                    1.055 * np.maximum(x, LINEAR_SEGMENT) ** (1.0 / 2.4) - 0.055).astype(dt)


def linear_to_srgb_slope(x) -> np.ndarray:
    """d linear_to_srgb / dx at linear values x (12.92 on the linear segment, 0.44 at 1): how much an error in linear
    light grows once encoded."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= LINEAR_SEGMENT, SRGB_SLOPE, 1.055 / 2.4 * np.maximum(x, LINEAR_SEGMENT) ** (1.0 / 2.4 - 1.0))


def srgb_to_linear_torch(x):
    """srgb_to_linear for torch tensors, differentiable: negative values count as 0, values above 1 follow the same
    curve (a colour the optimiser pushes past white still gets a gradient back). CPU float32 tensors go through one
    fused Numba pass (trisplat.render.colour_kernels), anything else through srgb_to_linear_ops."""
    from trisplat.render import colour_kernels

    if colour_kernels.applies(x):
        return colour_kernels.srgb_to_linear_fused(x)
    return srgb_to_linear_ops(x)


def srgb_to_linear_ops(x):
    """srgb_to_linear_torch in torch operations (any device; the fused kernels' readable twin and test oracle)."""
    import torch

    x = x.clamp_min(0.0)
    return torch.where(x <= SRGB_LINEAR_SEGMENT, x / SRGB_SLOPE,
                       ((x.clamp_min(SRGB_LINEAR_SEGMENT) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb_torch(x):
    """linear_to_srgb for torch tensors, differentiable: negative values count as 0, values above 1 follow the same
    curve (clip the result for display). CPU float32 tensors go through one fused Numba pass
    (trisplat.render.colour_kernels), anything else through linear_to_srgb_ops."""
    from trisplat.render import colour_kernels

    if colour_kernels.applies(x):
        return colour_kernels.linear_to_srgb_fused(x)
    return linear_to_srgb_ops(x)


def linear_to_srgb_ops(x):
    """linear_to_srgb_torch in torch operations (any device; the fused kernels' readable twin and test oracle)."""
    import torch

    x = x.clamp_min(0.0)
    return torch.where(x <= LINEAR_SEGMENT, x * SRGB_SLOPE, 1.055 * x.clamp_min(LINEAR_SEGMENT) ** (1.0 / 2.4) - 0.055)
