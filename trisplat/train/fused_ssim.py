"""Fused CPU photometric loss (1 - l) L1 + l (1 - SSIM) with its exact gradient w.r.t. the render (Numba kernels).

Same definition as `trisplat.eval.image_metrics.ssim_torch` (reduction 'mean'): x = pred, y = gt, [H,W,3] images;
G = g g^T the 11x11 Gaussian window (sigma 1.5 px) applied per channel over the 'valid' region (Ho = H - 10,
Wo = W - 10 outputs); with local means mu_x = G*x, mu_y = G*y, variances and covariance v_x, v_y, v_xy:
    A = 2 mu_x mu_y + C1,  B = 2 v_xy + C2,  C = mu_x^2 + mu_y^2 + C1,  D = v_x + v_y + C2,  S = A B / (C D)
    C1 = 0.01^2, C2 = 0.03^2 (data range 1);  loss = (1 - l) mean|x - y| + l (1 - mean S)
(mean|.| over the H W 3 values, mean S over the Ho Wo 3 outputs).

The moments are taken of the centred images x' = x - c, y' = y - c (c: per-channel mean of x and y together), which
changes none of the above (mu_x = mu'_x + c; variances do not move) but keeps the float32 moments small, so that
v_x = e'_xx - mu'_x^2 does not cancel away the digits it would for bright flat regions:
    mu'_x = G*x',  mu'_y = G*y',  e'_xx = G*(x' x'),  e'_yy = G*(y' y'),  e'_xy = G*(x' y')
    v_x = e'_xx - mu'_x^2,  v_y = e'_yy - mu'_y^2,  v_xy = e'_xy - mu'_x mu'_y.
Gradient, with w = -l / (Ho Wo 3) = dloss/dS and one reciprocal 1/(C D) per output:
    g_mu = w dS/dmu'_x = w [2 (mu_y B - mu'_y A) - 2 S (mu_x D - mu'_x C)] / (C D)
    g_xx = w dS/de'_xx = -w S C / (C D)          (= -w S / D)
    g_xy = w dS/de'_xy = 2 w A / (C D)
and, with G^T the transposed ('full') blur from the valid outputs back to every pixel,
    dloss/dx = G^T g_mu + 2 x' G^T g_xx + y' G^T g_xy + (1 - l) sign(x - y) / (H W 3)     (sign(0) = 0, as torch's abs).
gt gets no gradient.

The kernels work on channel-last images viewed as [H, W*3] rows (no permutes): a vertical tap adds whole rows, a
horizontal tap is a shift of 3 floats. Blurs accumulate in float32 (weights sum to 1, 11 taps); the sums behind the
means are float64 per row. Stages (parallel over rows or row blocks, no atomics, scratch allocated once per call):
  _row_sums         per-row sums of |x - y| and of x + y per channel (for c)
  _centre_rows      x' = x - c, y' = y - c
  _ssim_rows        per output row: vertical then horizontal blur of the five moments (_blur_moments), S and
                    (g_mu, g_xx, g_xy) (_ssim_terms_row), then their transposed horizontal blur (_blur_t_row)
  _pixel_grad_rows  per pixel row: the transposed vertical blur combined into dloss/dx, plus the L1 sign term
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange

from trisplat.eval.image_metrics import SSIM_K1, SSIM_K2, SSIM_SIGMA_PX, SSIM_WINDOW_PX, gaussian_window_1d, ssim_torch

_G = gaussian_window_1d(SSIM_WINDOW_PX, SSIM_SIGMA_PX, dtype=torch.float64).numpy().astype(np.float32)
_C1 = np.float32(SSIM_K1**2)
_C2 = np.float32(SSIM_K2**2)
_TWO = np.float32(2.0)  # float32 constants: a Python float literal would promote the kernels' arithmetic to float64
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)


@njit(cache=True, fastmath=True)
def _blur_moments(x, y, i, g, v, m):
    """Moments of output row i: vertical taps (rows i..i+s-1) into v [5, W*3], then horizontal taps into m [5, Wo*3].

    Order of the five: mu_x, mu_y, e_xx, e_yy, e_xy. One simple loop per moment so that each vectorises.
    """
    s = g.shape[0]
    n = x.shape[1]
    vx, vy, vxx, vyy, vxy = v[0], v[1], v[2], v[3], v[4]
    vx[:] = 0.0
    vy[:] = 0.0
    vxx[:] = 0.0
    vyy[:] = 0.0
    vxy[:] = 0.0
    for a in range(s):
        ga = g[a]
        xr = x[i + a]
        yr = y[i + a]
        for k in range(n):
            vx[k] += ga * xr[k]
        for k in range(n):
            vy[k] += ga * yr[k]
        for k in range(n):
            vxx[k] += ga * (xr[k] * xr[k])
        for k in range(n):
            vyy[k] += ga * (yr[k] * yr[k])
        for k in range(n):
            vxy[k] += ga * (xr[k] * yr[k])
    no = m.shape[1]
    for q in range(5):
        vq = v[q]
        mq = m[q]
        mq[:] = 0.0
        for b in range(s):
            gb = g[b]
            for k in range(no):
                mq[k] += gb * vq[k + 3 * b]


@njit(cache=True, fastmath=True)
def _ssim_terms_row(m, cm, c1, c2, w, gmu, gxx, gxy):
    """Per-output SSIM of one row from its centred moments m [5, Wo*3] (shift cm per column); writes
    w dS/d(mu'_x, e'_xx, e'_xy) into gmu, gxx, gxy; returns sum S in float64."""
    mx, my, exx, eyy, exy = m[0], m[1], m[2], m[3], m[4]
    acc = 0.0
    for k in range(m.shape[1]):
        px = mx[k]
        py = my[k]
        ux = px + cm[k]
        uy = py + cm[k]
        a = _TWO * ux * uy + c1
        b = _TWO * (exy[k] - px * py) + c2
        c = ux * ux + uy * uy + c1
        d = (exx[k] - px * px) + (eyy[k] - py * py) + c2
        inv_cd = _ONE / (c * d)
        s = a * b * inv_cd
        acc += s
        gmu[k] = w * inv_cd * (_TWO * (uy * b - py * a) - _TWO * s * (ux * d - px * c))
        gxx[k] = -w * s * c * inv_cd
        gxy[k] = _TWO * w * a * inv_cd
    return acc


@njit(cache=True, fastmath=True)
def _blur_t_row(d, g, h):
    """One row of the transposed horizontal blur: output column k' of d [Wo*3] fed pixels k' + 3b with weight g[b],
    so h [W*3] = sum_b g[b] d shifted by 3b."""
    h[:] = 0.0
    no = d.shape[0]
    for b in range(g.shape[0]):
        gb = g[b]
        for k in range(no):
            h[k + 3 * b] += gb * d[k]


@njit(parallel=True, cache=True, fastmath=True)
def _ssim_rows(x, y, g, cm, c1, c2, w, row_sum, hmu, hxx, hxy, v, m, d):
    """Stage 1, per output row i (contiguous row blocks, one scratch slot v [5, W*3], m [5, Wo*3], d [3, Wo*3] each):
    the five moments, row_sum[i] = sum S, and the gradient maps blurred back along the row into hmu/hxx/hxy [Ho, W*3].
    """
    ho = row_sum.shape[0]
    nblk = v.shape[0]
    for blk in prange(nblk):
        vb, mb, db = v[blk], m[blk], d[blk]
        for i in range(blk * ho // nblk, (blk + 1) * ho // nblk):
            _blur_moments(x, y, i, g, vb, mb)
            row_sum[i] = _ssim_terms_row(mb, cm, c1, c2, w, db[0], db[1], db[2])
            _blur_t_row(db[0], g, hmu[i])
            _blur_t_row(db[1], g, hxx[i])
            _blur_t_row(db[2], g, hxy[i])


@njit(parallel=True, cache=True, fastmath=True)
def _pixel_grad_rows(x, y, xc, yc, g, hmu, hxx, hxy, l1w, out):
    """Stage 2, per pixel row p: the transposed vertical blur (output row i fed pixel rows i + a with weight g[a])
    combined into out[p] = l1w sign(x - y) + sum_a g[a] (hmu + 2 x' hxx + y' hxy)[p - a], over 0 <= p - a < Ho
    (x', y' = xc, yc the centred images)."""
    s = g.shape[0]
    ho = hmu.shape[0]
    n = x.shape[1]
    for p in prange(x.shape[0]):
        xr = x[p]
        yr = y[p]
        xcr = xc[p]
        ycr = yc[p]
        o = out[p]
        for k in range(n):
            dxy = xr[k] - yr[k]
            o[k] = l1w if dxy > 0 else (-l1w if dxy < 0 else _ZERO)
        for a in range(max(0, p - ho + 1), min(s, p + 1)):
            ga = g[a]
            mu = hmu[p - a]
            xx = hxx[p - a]
            xy = hxy[p - a]
            for k in range(n):
                o[k] += ga * (mu[k] + _TWO * xcr[k] * xx[k] + ycr[k] * xy[k])


@njit(parallel=True, cache=True, fastmath=True)
def _centre_rows(x, y, crow, xc, yc):
    """xc = x - crow, yc = y - crow, row by row (crow [W*3]: the per-channel shift repeated along the row)."""
    for p in prange(x.shape[0]):
        xr, yr, xcr, ycr = x[p], y[p], xc[p], yc[p]
        for k in range(x.shape[1]):
            xcr[k] = xr[k] - crow[k]
            ycr[k] = yr[k] - crow[k]


@njit(parallel=True, cache=True, fastmath=True)
def _row_sums(x, y, out):
    """Per pixel row p, in float64: out[p, 0] = sum |x - y|, out[p, 1 + ch] = sum over the row of x + y in channel ch."""
    for p in prange(x.shape[0]):
        xr = x[p]
        yr = y[p]
        l1 = 0.0
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for j in range(x.shape[1] // 3):
            k = 3 * j
            l1 += abs(xr[k] - yr[k]) + abs(xr[k + 1] - yr[k + 1]) + abs(xr[k + 2] - yr[k + 2])
            s0 += xr[k] + yr[k]
            s1 += xr[k + 1] + yr[k + 1]
            s2 += xr[k + 2] + yr[k + 2]
        out[p, 0] = l1
        out[p, 1] = s0
        out[p, 2] = s1
        out[p, 3] = s2


def _loss_and_grad(x: np.ndarray, y: np.ndarray, lam: float, want_grad: bool) -> tuple[float, np.ndarray | None]:
    """Loss value (float64) and, if want_grad, dloss/dx [H,W,3] float32, for contiguous float32 [H,W,3] x, y."""
    H, W, _ = x.shape
    s = _G.shape[0]
    ho, wo = H - s + 1, W - s + 1
    n, no = 3 * W, 3 * wo
    x2, y2 = x.reshape(H, n), y.reshape(H, n)

    sums = np.empty((H, 4), np.float64)
    _row_sums(x2, y2, sums)
    sums = sums.sum(0)
    l1 = float(sums[0]) / (H * n)

    # Centre both images on the per-channel mean of the pair (see the module docstring): on near-identical natural
    # images this cuts the float32 error of the loss about 10x and of its gradient 2-8x (vs a float64 reference).
    crow = np.tile((sums[1:] / (2 * H * W)).astype(np.float32), W)
    xc, yc = np.empty_like(x2), np.empty_like(y2)
    _centre_rows(x2, y2, crow, xc, yc)

    w = np.float32(-lam / (ho * no))
    nblk = max(1, min(ho, numba.get_num_threads()))
    hmaps = [np.empty((ho, n), np.float32) for _ in range(3)]
    ssim_rows = np.empty(ho, np.float64)
    _ssim_rows(xc, yc, _G, crow[:no], _C1, _C2, w, ssim_rows, *hmaps,
               np.empty((nblk, 5, n), np.float32), np.empty((nblk, 5, no), np.float32), np.empty((nblk, 3, no), np.float32))
    ssim = float(ssim_rows.sum()) / (ho * no)
    value = (1.0 - lam) * l1 + lam * (1.0 - ssim)
    if not want_grad:
        return value, None

    grad = np.empty((H, n), np.float32)
    _pixel_grad_rows(x2, y2, xc, yc, _G, *hmaps, np.float32((1.0 - lam) / (H * n)), grad)
    return value, grad.reshape(H, W, 3)


class FusedPhotometric(torch.autograd.Function):
    """loss(pred, gt, lambda) as above; the whole gradient is computed in forward (when pred needs one) and scaled
    by the incoming gradient in backward. CPU float32 [H,W,3] only; gt gets no gradient."""

    @staticmethod
    def forward(ctx, pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
        x = pred.detach().contiguous().numpy()
        y = gt.detach().to(torch.float32).contiguous().numpy()
        value, grad = _loss_and_grad(x, y, float(lambda_dssim), ctx.needs_input_grad[0])
        if grad is not None:
            ctx.save_for_backward(torch.from_numpy(grad))
        return torch.tensor(value, dtype=torch.float32)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        (grad,) = ctx.saved_tensors
        return grad * grad_out, None, None


def _check_inputs(pred: torch.Tensor, gt: torch.Tensor) -> None:
    if pred.ndim != 3 or pred.shape[-1] != 3 or gt.ndim != 3 or gt.shape[-1] != 3:
        raise ValueError(f"photometric loss expects [H,W,3] images, got pred {tuple(pred.shape)} and gt {tuple(gt.shape)}")
    if pred.shape != gt.shape:
        raise ValueError(f"photometric loss inputs differ in shape: pred {tuple(pred.shape)} vs gt {tuple(gt.shape)}")
    h, w = pred.shape[:2]
    if h < SSIM_WINDOW_PX or w < SSIM_WINDOW_PX:
        raise ValueError(f"image {h}x{w} px is smaller than the {SSIM_WINDOW_PX}x{SSIM_WINDOW_PX} px SSIM window")


def photometric_torch(pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """The plain torch autograd version (any device and dtype): (1 - l) mean|pred - gt| + l (1 - ssim_torch)."""
    _check_inputs(pred, gt)
    l1 = (pred - gt).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim_torch(pred, gt))


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """Scalar (1 - lambda) L1 + lambda (1 - SSIM) of pred vs gt ([H,W,3], at least 11x11 px), differentiable in pred.

    The fused Numba kernels serve CPU float32 renders; anything else (another device or dtype, or a gt that needs a
    gradient) takes the torch autograd path `photometric_torch`, which computes the same thing.
    """
    _check_inputs(pred, gt)
    fused = (pred.device.type == "cpu" and pred.dtype == torch.float32 and gt.device.type == "cpu"
             and not gt.requires_grad)
    if not fused:
        return photometric_torch(pred, gt, lambda_dssim)
    return FusedPhotometric.apply(pred, gt, lambda_dssim)
