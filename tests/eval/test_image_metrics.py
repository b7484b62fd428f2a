"""PSNR and SSIM on known inputs, SSIM against scikit-image, and the torch SSIM's gradient."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from trisplat.eval.image_metrics import gaussian_window_1d, psnr, psnr_torch, ssim, ssim_torch


def _pair(seed: int, shape=(37, 45, 3), noise=0.1):
    rng = np.random.default_rng(seed)
    # smooth-ish content so SSIM is not trivially near zero
    base = rng.random(shape)
    base = (base + np.roll(base, 1, 0) + np.roll(base, 1, 1)) / 3
    return base, np.clip(base + noise * rng.standard_normal(shape), 0, 1)


def _skimage_ssim(a, b):
    return structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=-1)


def test_identical_images():
    a, _ = _pair(0)
    assert psnr(a, a) == math.inf
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-6)


def test_psnr_of_known_error():
    a = np.full((8, 9, 3), 0.5)
    for err in (0.1, 0.01, 0.25):
        b = a.copy()
        b[::2] += err  # half the rows off by +err, half by -err: MSE = err^2 exactly
        b[1::2] -= err
        assert psnr(a, b) == pytest.approx(-20 * math.log10(err), abs=1e-9)
    rng = np.random.default_rng(1)
    noise = rng.standard_normal((64, 64, 3)) * 0.05
    a = np.full((64, 64, 3), 0.5)
    assert psnr(a, a + noise) == pytest.approx(10 * math.log10(1 / np.mean(noise**2)), abs=1e-9)
    assert psnr(a, a + noise) == pytest.approx(-20 * math.log10(0.05), abs=0.3)  # sigma 0.05 -> ~26 dB


def test_psnr_accepts_torch_and_numpy_alike():
    a, b = _pair(2)
    assert psnr(torch.from_numpy(a).float(), torch.from_numpy(b).float()) == pytest.approx(psnr(a, b), abs=1e-4)
    t = psnr_torch(torch.from_numpy(a), torch.from_numpy(b))
    assert float(t) == pytest.approx(psnr(a, b), abs=1e-9)


@pytest.mark.parametrize("seed,noise", [(3, 0.02), (4, 0.1), (5, 0.3)])
def test_ssim_matches_skimage(seed, noise):
    a, b = _pair(seed, noise=noise)
    assert ssim(a, b) == pytest.approx(_skimage_ssim(a, b), abs=1e-5)
    # values across a range, so agreement is not an accident of one level
    assert 0.0 < ssim(a, b) < 1.0


def test_ssim_prefers_brightness_shift_to_noise_of_equal_mse():
    a, _ = _pair(6, shape=(40, 40, 3))
    a = 0.2 + 0.6 * a  # room to shift without clipping
    shifted = a + 0.1
    noise = np.random.default_rng(11).standard_normal(a.shape)
    noisy = a + noise * (0.1 / np.sqrt(np.mean(noise**2)))  # same MSE as the shift
    assert psnr(a, shifted) == pytest.approx(psnr(a, noisy), abs=1e-9)
    assert ssim(a, shifted) > ssim(a, noisy) + 0.2
    assert ssim(a, shifted) == pytest.approx(_skimage_ssim(a, shifted), abs=1e-5)


def test_ssim_rejects_bad_shapes():
    with pytest.raises(ValueError, match="differ in shape"):
        ssim(np.zeros((20, 20, 3)), np.zeros((20, 21, 3)))
    with pytest.raises(ValueError, match=r"\[H,W,3\]"):
        ssim(np.zeros((20, 20)), np.zeros((20, 20)))
    with pytest.raises(ValueError, match="image a must be a float image in \\[0,1\\], got dtype uint8"):
        psnr(np.zeros((20, 20, 3), np.uint8), np.zeros((20, 20, 3)))
    with pytest.raises(ValueError, match="float image"):
        ssim(torch.zeros(20, 20, 3), torch.zeros(20, 20, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="smaller than the 11x11"):
        ssim(np.zeros((8, 20, 3)), np.zeros((8, 20, 3)))


def test_gaussian_window_matches_scipy():
    from scipy.ndimage import gaussian_filter1d

    impulse = np.zeros(21)
    impulse[10] = 1.0
    ref = gaussian_filter1d(impulse, 1.5, truncate=3.5)[5:16]
    np.testing.assert_allclose(gaussian_window_1d(dtype=torch.float64).numpy(), ref, atol=1e-12)


def test_ssim_torch_batched_equals_per_image():
    a1, b1 = _pair(7, shape=(24, 30, 3))
    a2, b2 = _pair(8, shape=(24, 30, 3))
    x = torch.from_numpy(np.stack([a1, a2])).float()
    y = torch.from_numpy(np.stack([b1, b2])).float()
    per = ssim_torch(x, y, reduction="none")
    assert per.shape == (2,)
    assert float(per[0]) == pytest.approx(_skimage_ssim(a1, b1), abs=1e-5)
    assert float(per[1]) == pytest.approx(_skimage_ssim(a2, b2), abs=1e-5)
    assert float(ssim_torch(x, y)) == pytest.approx(float(per.mean()), abs=1e-6)


def test_ssim_torch_gradient_matches_finite_differences():
    a, b = _pair(9, shape=(11, 12, 3), noise=0.2)
    x = torch.from_numpy(a).requires_grad_(True)  # the render: where the training loss needs gradients
    y = torch.from_numpy(b)
    assert torch.autograd.gradcheck(lambda p: ssim_torch(p, y), (x,), eps=1e-6, atol=1e-6)
    # and both inputs at once, checked along random directions
    assert torch.autograd.gradcheck(lambda p, q: ssim_torch(p, q, reduction="none"),
                                    (x, y.clone().requires_grad_(True)), eps=1e-6, atol=1e-6, fast_mode=True)


def test_ssim_loss_decreases_under_gradient_descent():
    a, b = _pair(10, shape=(32, 32, 3), noise=0.2)
    x = torch.from_numpy(b).float().requires_grad_(True)
    ref = torch.from_numpy(a).float()
    opt = torch.optim.Adam([x], lr=0.02)
    start = 1 - float(ssim_torch(x.detach(), ref))
    for _ in range(25):
        opt.zero_grad()
        loss = 1 - ssim_torch(x, ref)
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.5 * start
