"""The fused Numba photometric loss (L1 + D-SSIM) against the torch autograd definition computed in float64."""
from __future__ import annotations

import pytest
import torch

from trisplat.eval.image_metrics import ssim_torch
from trisplat.train import losses
from trisplat.train.fused_ssim import photometric_loss, photometric_torch


def _images(h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 3, generator=g), torch.rand(h, w, 3, generator=g)


def _reference(pred: torch.Tensor, gt: torch.Tensor, lam: float) -> tuple[float, torch.Tensor]:
    """Loss value and d loss / d pred from the plain torch definition, in float64."""
    p = pred.double().requires_grad_()
    loss = (1.0 - lam) * (p - gt.double()).abs().mean() + lam * (1.0 - ssim_torch(p, gt.double()))
    loss.backward()
    return loss.item(), p.grad


def _fused(pred: torch.Tensor, gt: torch.Tensor, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    p = pred.clone().requires_grad_()
    loss = photometric_loss(p, gt, lam)
    loss.backward()
    return loss, p.grad


def _assert_close(pred: torch.Tensor, gt: torch.Tensor, lam: float) -> None:
    loss, grad = _fused(pred, gt, lam)
    ref, ref_grad = _reference(pred, gt, lam)
    assert loss.dtype == torch.float32 and loss.ndim == 0
    assert abs(loss.item() - ref) <= 1e-6 * abs(ref)
    assert grad.shape == pred.shape and grad.dtype == torch.float32
    assert (grad.double() - ref_grad).abs().max() <= 1e-5 * ref_grad.abs().max()


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("hw", [(11, 11), (11, 19), (23, 17), (64, 48), (97, 130)])
def test_value_and_gradient_match_float64_torch(hw, seed):
    pred, gt = _images(*hw, seed)
    _assert_close(pred, gt, 0.2)


@pytest.mark.parametrize("lam", [0.0, 1.0])
def test_lambda_edge_cases(lam):
    pred, gt = _images(31, 45, 3)
    _assert_close(pred, gt, lam)


def test_natural_image_with_flat_regions():
    """Near-identical smooth images (small loss, D close to C2): where float32 moments lose the most digits."""
    h, w = 64, 80
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    base = torch.stack([xx, yy, 0.5 * torch.ones_like(xx)], -1)
    base[20:40, 30:60] = 0.8
    g = torch.Generator().manual_seed(4)
    pred = (base + 1e-3 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    gt = (base + 1e-2 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    loss, grad = _fused(pred, gt, 0.2)
    ref, ref_grad = _reference(pred, gt, 0.2)
    assert abs(loss.item() - ref) <= 1e-5 * ref
    assert (grad.double() - ref_grad).abs().max() <= 2e-5 * ref_grad.abs().max()


def test_equal_pixels_get_no_l1_gradient():
    """sign(0) = 0 as in torch's abs backward: pixels where pred == gt get only the SSIM part."""
    pred, gt = _images(24, 30, 5)
    pred[:, :15] = gt[:, :15]
    _assert_close(pred, gt, 0.2)
    _, grad = _fused(pred, gt, 0.0)
    assert (grad[:, :15] == 0).all() and (grad[:, 15:] != 0).all()


def test_identical_images_give_zero_loss_and_gradient():
    _, gt = _images(40, 33, 6)
    loss, grad = _fused(gt, gt, 1.0)
    assert abs(loss.item()) < 1e-6
    # Gradient scale for comparison: the same images slightly apart.
    _, scale = _fused(gt + 0.01 * torch.randn(gt.shape, generator=torch.Generator().manual_seed(7)), gt, 1.0)
    assert grad.abs().max() <= 1e-5 * scale.abs().max()
    loss, grad = _fused(gt, gt, 0.2)
    assert abs(loss.item()) < 1e-6


def test_upstream_gradient_scales_and_no_grad_forward():
    pred, gt = _images(20, 20, 8)
    _, grad = _fused(pred, gt, 0.2)
    p = pred.clone().requires_grad_()
    (3.0 * photometric_loss(p, gt, 0.2)).backward()
    assert torch.allclose(p.grad, 3.0 * grad, rtol=1e-6, atol=0)
    with torch.no_grad():
        value = photometric_loss(pred, gt, 0.2)
    assert value.grad_fn is None and abs(value.item() - _reference(pred, gt, 0.2)[0]) <= 1e-6 * value.item()


def test_other_dtypes_and_a_gt_gradient_take_the_torch_path():
    pred, gt = _images(16, 21, 9)
    p64 = pred.double().requires_grad_()
    loss = photometric_loss(p64, gt.double(), 0.2)
    assert loss.dtype == torch.float64 and "Fused" not in type(loss.grad_fn).__name__
    loss.backward()
    ref, ref_grad = _reference(pred, gt, 0.2)
    assert abs(loss.item() - ref) <= 1e-12 and torch.allclose(p64.grad, ref_grad, rtol=0, atol=1e-15)
    g = gt.clone().requires_grad_()
    photometric_loss(pred.clone().requires_grad_(), g, 0.2).backward()
    assert g.grad is not None and g.grad.abs().max() > 0


def test_training_loss_uses_the_fused_path():
    pred, gt = _images(30, 30, 10)
    p = pred.clone().requires_grad_()
    loss = losses.photometric(p, gt, 0.2)
    assert type(loss.grad_fn).__name__ == "FusedPhotometricBackward"
    assert torch.equal(loss, photometric_loss(pred, gt, 0.2))
    assert torch.allclose(loss, photometric_torch(pred, gt, 0.2), rtol=1e-6, atol=0)
    l1 = losses.photometric(p, gt, 0.0)
    assert torch.equal(l1, (pred - gt).abs().mean())


@pytest.mark.parametrize(
    ("pred_shape", "gt_shape", "match"),
    [
        ((20, 20), (20, 20), r"\[H,W,3\] images, got pred \(20, 20\) and gt \(20, 20\)"),
        ((20, 20, 4), (20, 20, 4), r"\[H,W,3\] images, got pred \(20, 20, 4\)"),
        ((2, 20, 20, 3), (2, 20, 20, 3), r"got pred \(2, 20, 20, 3\)"),
        ((20, 20, 3), (20, 21, 3), r"differ in shape: pred \(20, 20, 3\) vs gt \(20, 21, 3\)"),
        ((10, 30, 3), (10, 30, 3), r"10x30 px is smaller than the 11x11 px SSIM window"),
    ],
)
def test_bad_shapes_raise(pred_shape, gt_shape, match):
    with pytest.raises(ValueError, match=match):
        photometric_loss(torch.rand(pred_shape), torch.rand(gt_shape), 0.2)
    with pytest.raises(ValueError, match=match):
        losses.photometric(torch.rand(pred_shape), torch.rand(gt_shape), 0.2)
