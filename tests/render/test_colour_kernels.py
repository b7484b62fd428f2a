"""The fused sRGB curves (trisplat.render.colour_kernels) against their torch twins (trisplat.io.colour *_ops): value
and gradient on values across both segments, at the segment points, below 0, above 1, NaN, at any thread count."""
from __future__ import annotations

import math

import numba
import pytest
import torch

from trisplat.io.colour import (LINEAR_SEGMENT, SRGB_LINEAR_SEGMENT, linear_to_srgb_ops, linear_to_srgb_torch,
                                srgb_to_linear_ops, srgb_to_linear_torch)
from trisplat.render import colour_kernels


def _values(seg: float) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    x = torch.cat([torch.rand(4001, generator=g) * 1.3 - 0.1, torch.rand(500, generator=g) * 2 * seg,
                   torch.tensor([0.0, -0.0, seg, -1e-8, 1e-8, 1.0, 3.0, -2.0])])
    return x.reshape(-1, 3)  # (4509 values)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("curve", ["to_linear", "to_srgb"])
def test_value_and_gradient_match_the_torch_operations(curve, threads):
    fused, ops, seg = ((srgb_to_linear_torch, srgb_to_linear_ops, SRGB_LINEAR_SEGMENT) if curve == "to_linear" else
                       (linear_to_srgb_torch, linear_to_srgb_ops, LINEAR_SEGMENT))
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        x = _values(seg)
        w = torch.randn(x.shape, generator=torch.Generator().manual_seed(1))
        a, b = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
        ya, yb = fused(a), ops(b)
        assert colour_kernels.applies(a)
        torch.testing.assert_close(ya, yb, rtol=2e-6, atol=1e-7)
        (ya * w).sum().backward()
        (yb * w).sum().backward()
        torch.testing.assert_close(a.grad, b.grad, rtol=2e-5, atol=1e-6)
        assert float(a.grad[x < 0].abs().max()) == 0.0  # negative values are clamped: no gradient
        assert float(a.grad[(x > seg) & (x < 1)].abs().min()) > 0.0
    finally:
        numba.set_num_threads(before)


def test_nan_stays_nan_and_other_dtypes_use_torch():
    x = torch.tensor([float("nan"), 0.5, float("inf")])
    for fused, ops in ((srgb_to_linear_torch, srgb_to_linear_ops), (linear_to_srgb_torch, linear_to_srgb_ops)):
        y, r = fused(x), ops(x)
        assert math.isnan(float(y[0])) and math.isnan(float(r[0]))
        assert float(y[2]) == float(r[2]) == math.inf
        x64 = torch.rand(7, dtype=torch.float64)
        assert not colour_kernels.applies(x64)
        assert torch.equal(fused(x64), ops(x64))  # float64: the torch operations themselves


def test_image_shaped_input_and_no_grad():
    """[H,W,3] renders (the encode of every pixel) and tensors without gradient."""
    x = torch.rand(5, 7, 3) * 0.02
    with torch.no_grad():
        torch.testing.assert_close(linear_to_srgb_torch(x), linear_to_srgb_ops(x), rtol=2e-6, atol=1e-7)
    xt = x.transpose(0, 1)  # not contiguous
    torch.testing.assert_close(srgb_to_linear_torch(xt), srgb_to_linear_ops(xt), rtol=2e-6, atol=1e-7)
