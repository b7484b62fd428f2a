"""The sRGB transfer function and its inverse as one parallel Numba pass each, with their gradient (issue 50).

The readable twins and test oracles are `trisplat.io.colour.srgb_to_linear_ops` and `linear_to_srgb_ops` (torch
operations), which these match in value and gradient:

  srgb_to_linear(x) = c / 12.92                      where c <= 0.04045,   ((c + 0.055) / 1.055)^2.4   elsewhere
  linear_to_srgb(x) = 12.92 c                        where c <= 0.0031308, 1.055 c^(1 / 2.4) - 0.055   elsewhere
  with c = max(x, 0); the gradient is the curve's slope where x >= 0, 0 where x < 0 (and NaN stays NaN).

The slope is kept from the forward pass (from the value: 2.4 y / (c + 0.055) and 1.055 c^(1/2.4) / (2.4 c)), so the
backward is one product. The passes compute in float32 (as torch does on float32 tensors), within a few float32
roundings of torch's values. Why: a surface in linear light (TriangleScene.linear_light) decodes every vertex colour and
encodes every rendered pixel at each step; torch's version is about ten operations and as many in its backward,
~15 ms of a 1-thread step on bonsai's 221k-vertex surface, mostly on one thread.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from trisplat.io.colour import LINEAR_SEGMENT, SRGB_LINEAR_SEGMENT, SRGB_SLOPE

# the segment points as float32 values: torch compares a float32 tensor with them so (the value at the point itself
# takes the linear branch in both)
_SRGB_SEG32 = np.float32(SRGB_LINEAR_SEGMENT)
_LINEAR_SEG32 = np.float32(LINEAR_SEGMENT)


_F = np.float32
_A, _INV_B, _GAMMA, _INV_SLOPE, _SLOPE = _F(0.055), _F(1.0 / 1.055), _F(2.4), _F(1.0 / SRGB_SLOPE), _F(SRGB_SLOPE)
_B, _INV_GAMMA = _F(1.055), _F(1.0 / 2.4)
# float32 throughout, branch-free selects and exp/log for the power: the loops vectorise (3x faster than float64
# powers). No "nnan"/"ninf" among the fast-math flags: NaN must stay NaN.
_FAST = {"afn", "arcp", "contract"}


@njit(parallel=True, cache=True, fastmath=_FAST)
def _to_linear(x, y, slope):
    for i in prange(x.shape[0]):
        xi = x[i]
        c = xi if xi > _F(0.0) else _F(0.0)
        curve = math.exp(_GAMMA * math.log((c + _A) * _INV_B))
        lin = c <= _SRGB_SEG32
        yi = c * _INV_SLOPE if lin else curve
        y[i] = yi if xi == xi else xi  # (NaN stays NaN)
        s = _INV_SLOPE if lin else _GAMMA * curve / (c + _A)
        slope[i] = s if xi >= _F(0.0) else _F(0.0)


@njit(parallel=True, cache=True, fastmath=_FAST)
def _to_srgb(x, y, slope):
    for i in prange(x.shape[0]):
        xi = x[i]
        c = xi if xi > _F(0.0) else _F(0.0)
        lin = c <= _LINEAR_SEG32
        root = math.exp(_INV_GAMMA * math.log(c if not lin else _F(1.0)))  # c^(1 / 2.4) (log of 1 on the line)
        yi = c * _SLOPE if lin else _B * root - _A
        y[i] = yi if xi == xi else xi
        s = _SLOPE if lin else _B * root * _INV_GAMMA / c
        slope[i] = s if xi >= _F(0.0) else _F(0.0)


@njit(parallel=True, cache=True)
def _times(g, slope, out):
    for i in prange(g.shape[0]):
        out[i] = g[i] * slope[i]


class _Curve(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, to_linear):
        xs = x.detach().contiguous()
        y, slope = torch.empty_like(xs), torch.empty_like(xs)
        (_to_linear if to_linear else _to_srgb)(xs.view(-1).numpy(), y.view(-1).numpy(), slope.view(-1).numpy())
        ctx.save_for_backward(slope)
        return y

    @staticmethod
    def backward(ctx, g):
        (slope,) = ctx.saved_tensors
        g = g.contiguous()
        out = torch.empty_like(slope)
        _times(g.view(-1).numpy(), slope.view(-1).numpy(), out.view(-1).numpy())
        return out, None


def applies(x: torch.Tensor) -> bool:
    """Whether these kernels take x (a CPU float32 tensor; anything else goes to the torch operations)."""
    return isinstance(x, torch.Tensor) and x.device.type == "cpu" and x.dtype == torch.float32


def srgb_to_linear_fused(x: torch.Tensor) -> torch.Tensor:
    """trisplat.io.colour.srgb_to_linear_ops's value and gradient (CPU float32)."""
    return _Curve.apply(x, True)


def linear_to_srgb_fused(x: torch.Tensor) -> torch.Tensor:
    """trisplat.io.colour.linear_to_srgb_ops's value and gradient (CPU float32)."""
    return _Curve.apply(x, False)


__all__ = ["applies", "srgb_to_linear_fused", "linear_to_srgb_fused"]
