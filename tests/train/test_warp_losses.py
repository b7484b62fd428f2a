"""The Warp twins of the training step's fused kernels (SH colour: trisplat.scene.warp_sh; L1 + D-SSIM loss:
trisplat.train.warp_ssim) against the readable torch definitions computed in float64 (the oracles of the Numba kernel
tests), on Warp's CPU device in CI; and that backend='warp' selects them."""
from __future__ import annotations

import pytest
import torch

from trisplat.eval.image_metrics import ssim_torch
from trisplat.render.warp_backend import available
from trisplat.scene.sh import eval_sh_torch

pytestmark = [pytest.mark.skipif(not available(), reason="warp-lang is not installed (pip install 'trisplat[gpu]'); "
                                                         "the Warp kernel tests need it"),
              pytest.mark.filterwarnings("ignore::DeprecationWarning")]


# ------------------------------------------------------------------------------------------------------ SH colour
def _sh_inputs(seed: int, n: int = 300):
    """Coefficients [n,16,3] large enough that many channels clamp; directions of lengths 1e-3..1e3, one zero
    direction and one shorter than the oracle's 1e-12 clamp."""
    g = torch.Generator().manual_seed(seed)
    sh = 0.8 * torch.randn(n, 16, 3, generator=g)
    d = torch.randn(n, 3, generator=g) * 10 ** (6 * torch.rand(n, 1, generator=g) - 3)
    d[0] = 0.0
    d[1] = torch.tensor([3e-13, -2e-13, 1e-13])
    return sh, d, torch.randn(n, 3, generator=g)


def _rows_close(a: torch.Tensor, b: torch.Tensor, rtol: float) -> None:
    """Per vertex: |a - b| <= rtol * (largest entry of b in that row, at least 1e-3)."""
    a, b = a.reshape(len(a), -1).double(), b.reshape(len(b), -1).double()
    scale = b.abs().amax(1).clamp_min(1e-3)
    err = (a - b).abs().amax(1)
    worst = int((err / scale).argmax())
    assert (err <= rtol * scale).all(), f"vertex {worst}: error {err[worst]:.3g} vs scale {scale[worst]:.3g}"


@pytest.mark.parametrize("deg", [0, 1, 2, 3])
def test_warp_sh_matches_the_torch_oracle(deg):
    """Values, clamped channels and the gradients to the coefficients (zero beyond the degree) and to the
    unnormalised directions, against eval_sh_torch in float64."""
    from trisplat.scene.warp_sh import eval_sh_warp

    sh, d, w = _sh_inputs(deg)
    s32, d32 = sh.clone().requires_grad_(), d.clone().requires_grad_()
    out = eval_sh_warp(s32, d32, deg)
    assert type(out.grad_fn).__name__ == "WarpSHBackward" and out.dtype == torch.float32 and out.shape == (300, 3)
    s64, d64 = sh.double().requires_grad_(), d.double().requires_grad_()
    ref = eval_sh_torch(s64, d64, deg)
    assert (ref == 0).any() and (ref > 0).any()  # both sides of the clamp
    torch.testing.assert_close(out.double(), ref, atol=2e-6, rtol=2e-6)
    assert torch.equal(out == 0, ref == 0)
    gs, gd = torch.autograd.grad((out * w).sum(), (s32, d32))
    gs_r, gd_r = torch.autograd.grad((ref * w.double()).sum(), (s64, d64), allow_unused=True)
    gd_r = torch.zeros_like(d64) if gd_r is None else gd_r  # degree 0 does not depend on the direction
    K = (deg + 1) ** 2
    _rows_close(gs[:, :K], gs_r[:, :K], 1e-6)
    assert (gs[:, K:] == 0).all()
    _rows_close(gd, gd_r, 1e-5)
    if deg > 0:  # a direction gradient on every ordinary vertex with an unclamped channel
        live = (ref[2:] > 0).any(1)
        assert (gd[2:].abs().amax(1)[live] > 0).all()


def test_warp_sh_truncated_slice_float64_and_empty_inputs():
    """A sliced (non-contiguous) coefficient tensor; float64 input takes eval_sh (the Numba path on the CPU); no
    vertices."""
    from trisplat.scene.sh import eval_sh
    from trisplat.scene.warp_sh import eval_sh_warp

    sh, d, _ = _sh_inputs(7, 50)
    sliced = sh[:, :9]  # degree 2 view of degree-3 coefficients, as the trainer's SH schedule slices them
    assert not sliced.is_contiguous()
    torch.testing.assert_close(eval_sh_warp(sliced, d), eval_sh_torch(sliced, d), atol=2e-6, rtol=2e-6)
    out64 = eval_sh_warp(sh.double(), d.double())
    assert out64.dtype == torch.float64 and torch.equal(out64, eval_sh(sh.double(), d.double()))
    empty = eval_sh_warp(torch.zeros(0, 4, 3, requires_grad=True), torch.zeros(0, 3))
    assert empty.shape == (0, 3)
    empty.sum().backward()


def test_soft_render_with_the_warp_backend_evaluates_sh_with_warp(monkeypatch):
    """rasterize(..., backend='warp') with SH colours goes through the Warp SH kernels, and its colour gradient
    matches the Numba backend's (which evaluates SH with the Numba kernels)."""
    from trisplat.render import rasterize
    from trisplat.scene import warp_sh

    calls = []
    fwd = warp_sh.WarpSH.forward
    monkeypatch.setattr(warp_sh.WarpSH, "forward", staticmethod(lambda *a: calls.append(1) or fwd(*a)))
    g = torch.Generator().manual_seed(3)
    pos = torch.tensor([[-0.6, -0.5, 2.0], [0.7, -0.4, 2.2], [0.0, 0.6, 1.9], [0.5, 0.5, 2.5]])
    faces = torch.tensor([[0, 1, 2], [1, 3, 2]], dtype=torch.int32)
    sh0 = 0.4 * torch.randn(4, 9, 3, generator=g)
    K = torch.tensor([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    res = {}
    for backend in ("numba", "warp"):
        sh = sh0.clone().requires_grad_()
        out = rasterize(pos, faces, sh, torch.full((4,), 0.8), 0.5, torch.eye(4), K, 32, 24, backend=backend)
        (out.rgb * torch.linspace(0, 1, 3)).sum().backward()
        res[backend] = (out.rgb.detach(), sh.grad)
    assert calls, "the Warp SH kernels were not used"
    torch.testing.assert_close(res["warp"][0], res["numba"][0], atol=2e-5, rtol=0)
    torch.testing.assert_close(res["warp"][1], res["numba"][1], atol=1e-4 * res["numba"][1].abs().max().item(),
                               rtol=0)


# ----------------------------------------------------------------------------------------------- L1 + D-SSIM loss
def _images(h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 3, generator=g), torch.rand(h, w, 3, generator=g)


def _reference(pred: torch.Tensor, gt: torch.Tensor, lam: float) -> tuple[float, torch.Tensor]:
    """Loss value and d loss / d pred from the plain torch definition, in float64 (as test_fused_ssim)."""
    p = pred.double().requires_grad_()
    loss = (1.0 - lam) * (p - gt.double()).abs().mean() + lam * (1.0 - ssim_torch(p, gt.double()))
    loss.backward()
    return loss.item(), p.grad


def _warp(pred: torch.Tensor, gt: torch.Tensor, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    from trisplat.train.warp_ssim import photometric_loss_warp

    p = pred.clone().requires_grad_()
    loss = photometric_loss_warp(p, gt, lam)
    assert type(loss.grad_fn).__name__ == "WarpPhotometricBackward"
    loss.backward()
    return loss, p.grad


def _assert_close(pred, gt, lam, value_rtol=1e-6, grad_rtol=1e-5):
    loss, grad = _warp(pred, gt, lam)
    ref, ref_grad = _reference(pred, gt, lam)
    assert loss.dtype == torch.float32 and loss.ndim == 0
    assert abs(loss.item() - ref) <= value_rtol * abs(ref)
    assert grad.shape == pred.shape and grad.dtype == torch.float32
    assert (grad.double() - ref_grad).abs().max() <= grad_rtol * ref_grad.abs().max()


@pytest.mark.parametrize("hw,lam", [((11, 11), 0.2), ((11, 19), 0.2), ((23, 17), 0.2), ((64, 48), 1.0),
                                    ((97, 130), 0.2), ((31, 45), 0.0)])
def test_warp_photometric_matches_float64_torch(hw, lam):
    """Odd and window-sized images (every pixel a border pixel of some window), lambda 0, 0.2 and 1."""
    pred, gt = _images(*hw, sum(hw))
    _assert_close(pred, gt, lam)


def test_warp_photometric_on_a_natural_image_with_flat_regions():
    """Near-identical smooth images (small loss, D close to C2): where float32 moments lose the most digits (the
    centring of fused_ssim must be there)."""
    h, w = 64, 80
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    base = torch.stack([xx, yy, 0.5 * torch.ones_like(xx)], -1)
    base[20:40, 30:60] = 0.8
    g = torch.Generator().manual_seed(4)
    pred = (base + 1e-3 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    gt = (base + 1e-2 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    _assert_close(pred, gt, 0.2, value_rtol=1e-5, grad_rtol=2e-5)


def test_warp_photometric_equal_pixels_scaling_and_no_grad():
    """sign(0) = 0 (pixels where pred == gt get only the SSIM part); the upstream gradient scales; a forward
    without gradient gives the same value."""
    from trisplat.train.warp_ssim import photometric_loss_warp

    pred, gt = _images(24, 30, 5)
    pred[:, :15] = gt[:, :15]
    _assert_close(pred, gt, 0.2)
    _, grad = _warp(pred, gt, 0.0)
    assert (grad[:, :15] == 0).all() and (grad[:, 15:] != 0).all()
    _, grad = _warp(pred, gt, 0.2)
    p = pred.clone().requires_grad_()
    (3.0 * photometric_loss_warp(p, gt, 0.2)).backward()
    assert torch.allclose(p.grad, 3.0 * grad, rtol=1e-6, atol=0)
    with torch.no_grad():
        value = photometric_loss_warp(pred, gt, 0.2)
    assert value.grad_fn is None and abs(value.item() - _reference(pred, gt, 0.2)[0]) <= 1e-6 * value.item()


def test_warp_photometric_selection():
    """losses.photometric(..., backend='warp') is the Warp loss (the Numba one otherwise); other dtypes and a gt
    that needs a gradient take the torch version; the same shape checks as the Numba loss."""
    from trisplat.train import losses
    from trisplat.train.fused_ssim import photometric_loss, photometric_torch

    pred, gt = _images(30, 30, 10)
    p = pred.clone().requires_grad_()
    loss = losses.photometric(p, gt, 0.2, backend="warp")
    assert type(loss.grad_fn).__name__ == "WarpPhotometricBackward"
    assert type(losses.photometric(p, gt, 0.2).grad_fn).__name__ == "FusedPhotometricBackward"
    torch.testing.assert_close(loss, photometric_loss(pred, gt, 0.2), rtol=2e-6, atol=0)
    assert torch.equal(losses.photometric(p, gt, 0.0, backend="warp"), (pred - gt).abs().mean())
    p64 = pred.double().requires_grad_()
    l64 = losses.photometric(p64, gt.double(), 0.2, backend="warp")
    assert l64.dtype == torch.float64 and torch.equal(l64, photometric_torch(pred.double(), gt.double(), 0.2))
    g = gt.clone().requires_grad_()
    losses.photometric(pred.clone().requires_grad_(), g, 0.2, backend="warp").backward()
    assert g.grad is not None and g.grad.abs().max() > 0
    with pytest.raises(ValueError, match=r"10x30 px is smaller than the 11x11 px SSIM window"):
        losses.photometric(torch.rand(10, 30, 3), torch.rand(10, 30, 3), 0.2, backend="warp")


@pytest.mark.parametrize("module,names", [("trisplat.scene.warp_sh", ("sh_forward", "sh_backward")),
                                          ("trisplat.train.warp_ssim", ("vertical_moments", "ssim_terms",
                                                                        "blur_t_rows", "pixel_grad"))])
def test_warp_step_kernels_compile_for_cuda_without_a_gpu(tmp_path, module, names):
    """The SH and loss kernels through Warp's CUDA code generation and NVRTC to H100 (sm_90) PTX, as the
    rasterizer's are in test_render_warp: no GPU needed, so their CUDA build is checked on every CI run."""
    import importlib

    import warp as wp

    paths = wp.compile_aot_module(importlib.import_module(module), arch=90, module_dir=tmp_path, use_ptx=True)
    ptx = [p for p in paths if str(p).endswith(".ptx")]
    assert ptx and ptx[0].stat().st_size > 1_000
    text = ptx[0].read_text()
    for name in names:
        assert name in text
