"""The photometric loss (1 - l) L1 + l (1 - SSIM) and its exact gradient w.r.t. the render, in NVIDIA Warp (the
backend="warp" twin of the Numba kernels in trisplat.train.fused_ssim).

Same definition and maths as fused_ssim (see its docstring for the formulas): 11x11 Gaussian window (sigma 1.5 px)
over the 'valid' region, the moments taken of the images centred on the per-channel mean of the pair (float32
moments that do not cancel in bright flat regions), the gradient from w dS/d(mu'_x, e'_xx, e'_xy) blurred back by
the transposed window, plus the L1 sign term (sign(0) = 0). Blurs accumulate in float32, the sums behind the means
in float64 per row, as in the Numba kernels. Channel-last images are viewed as [H, W*3] rows (no permutes).

One thread per row or per (row, column) entry, no atomics, on the tensors' device (CUDA on torch's current stream,
or Warp's CPU device), buffers are torch tensors handed over with wp.from_torch (views):
  row_sums        per pixel row (float64): sum |x - y| and per channel sum x + y  -> the L1 term and the centre c
  vertical_moments   per (output row, column): vertical taps of x', y', x'x', y'y', x'y'  -> v [5, Ho, W*3]
  ssim_terms      per (output row, output column): horizontal taps -> the five moments, S and the three gradient
                  maps w dS/d(mu'_x, e'_xx, e'_xy)  -> S [Ho, Wo*3], d [3, Ho, Wo*3]
  row_sums_1      per output row (float64): sum S
  blur_t_rows     per (output row, column): the transposed horizontal blur of d  -> h [3, Ho, W*3]
  pixel_grad      per (pixel row, column): the transposed vertical blur of h combined into dloss/dx, plus the L1 term
The loss value stays a device tensor (no host synchronisation).
"""
from __future__ import annotations

import torch

from trisplat.eval.image_metrics import SSIM_K1, SSIM_K2, SSIM_SIGMA_PX, SSIM_WINDOW_PX, gaussian_window_1d
from trisplat.render.warp_backend import INSTALL_HINT, warp_scope

try:
    import warp as wp
except ImportError as exc:
    raise ImportError(INSTALL_HINT) from exc

if wp.config.log_level < wp.LOG_WARNING:  # no greeting or per-module load lines from the library
    wp.config.log_level = wp.LOG_WARNING
wp.set_module_options({"enable_backward": False})  # the gradient is written by hand below

_C1 = wp.constant(wp.float32(SSIM_K1**2))
_C2 = wp.constant(wp.float32(SSIM_K2**2))


@wp.kernel
def row_sums(x: wp.array2d(dtype=wp.float32), y: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.float64)):
    """Per pixel row p, in float64: out[p, 0] = sum |x - y|, out[p, 1 + ch] = sum over the row of x + y in channel
    ch."""
    p = wp.tid()
    l1 = wp.float64(0.0)
    s0 = wp.float64(0.0)
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    for j in range(x.shape[1] // 3):
        k = 3 * j
        l1 += wp.float64(wp.abs(x[p, k] - y[p, k]) + wp.abs(x[p, k + 1] - y[p, k + 1])
                         + wp.abs(x[p, k + 2] - y[p, k + 2]))
        s0 += wp.float64(x[p, k] + y[p, k])
        s1 += wp.float64(x[p, k + 1] + y[p, k + 1])
        s2 += wp.float64(x[p, k + 2] + y[p, k + 2])
    out[p, 0] = l1
    out[p, 1] = s0
    out[p, 2] = s1
    out[p, 3] = s2


@wp.kernel
def row_sums_1(a: wp.array2d(dtype=wp.float32), out: wp.array(dtype=wp.float64)):
    """out[i] = sum of row i of a, in float64."""
    i = wp.tid()
    acc = wp.float64(0.0)
    for k in range(a.shape[1]):
        acc += wp.float64(a[i, k])
    out[i] = acc


@wp.kernel
def vertical_moments(x: wp.array2d(dtype=wp.float32), y: wp.array2d(dtype=wp.float32),
                     c: wp.array(dtype=wp.float32), g: wp.array(dtype=wp.float32),
                     v: wp.array3d(dtype=wp.float32)):
    """v[:, i, k] = vertical taps (rows i..i+s-1) of x', y', x'x', y'y', x'y' at column k (x' = x - c per
    channel)."""
    i, k = wp.tid()
    ck = c[k % 3]
    vx = wp.float32(0.0)
    vy = wp.float32(0.0)
    vxx = wp.float32(0.0)
    vyy = wp.float32(0.0)
    vxy = wp.float32(0.0)
    for a in range(g.shape[0]):
        ga = g[a]
        xa = x[i + a, k] - ck
        ya = y[i + a, k] - ck
        vx += ga * xa
        vy += ga * ya
        vxx += ga * (xa * xa)
        vyy += ga * (ya * ya)
        vxy += ga * (xa * ya)
    v[0, i, k] = vx
    v[1, i, k] = vy
    v[2, i, k] = vxx
    v[3, i, k] = vyy
    v[4, i, k] = vxy


@wp.kernel
def ssim_terms(v: wp.array3d(dtype=wp.float32), c: wp.array(dtype=wp.float32), g: wp.array(dtype=wp.float32),
               w: wp.float32, S: wp.array2d(dtype=wp.float32), d: wp.array3d(dtype=wp.float32)):
    """Per output (i, k): the horizontal taps of v give the centred moments; S[i, k] and d[:, i, k] = w dS/d(mu'_x,
    e'_xx, e'_xy)."""
    i, k = wp.tid()
    px = wp.float32(0.0)
    py = wp.float32(0.0)
    exx = wp.float32(0.0)
    eyy = wp.float32(0.0)
    exy = wp.float32(0.0)
    for b in range(g.shape[0]):
        gb = g[b]
        kb = k + 3 * b
        px += gb * v[0, i, kb]
        py += gb * v[1, i, kb]
        exx += gb * v[2, i, kb]
        eyy += gb * v[3, i, kb]
        exy += gb * v[4, i, kb]
    cm = c[k % 3]
    two = wp.float32(2.0)
    ux = px + cm
    uy = py + cm
    A = two * ux * uy + _C1
    B = two * (exy - px * py) + _C2
    C = ux * ux + uy * uy + _C1
    D = (exx - px * px) + (eyy - py * py) + _C2
    inv_cd = wp.float32(1.0) / (C * D)
    s = A * B * inv_cd
    S[i, k] = s
    d[0, i, k] = w * inv_cd * (two * (uy * B - py * A) - two * s * (ux * D - px * C))
    d[1, i, k] = -w * s * C * inv_cd
    d[2, i, k] = two * w * A * inv_cd


@wp.kernel
def blur_t_rows(d: wp.array3d(dtype=wp.float32), g: wp.array(dtype=wp.float32), h: wp.array3d(dtype=wp.float32)):
    """The transposed horizontal blur, per (output row i, pixel column k): h[:, i, k] = sum_b g[b] d[:, i, k - 3b]
    over 0 <= k - 3b < Wo*3."""
    i, k = wp.tid()
    no = d.shape[2]
    h0 = wp.float32(0.0)
    h1 = wp.float32(0.0)
    h2 = wp.float32(0.0)
    for b in range(g.shape[0]):
        kb = k - 3 * b
        if kb >= 0 and kb < no:
            gb = g[b]
            h0 += gb * d[0, i, kb]
            h1 += gb * d[1, i, kb]
            h2 += gb * d[2, i, kb]
    h[0, i, k] = h0
    h[1, i, k] = h1
    h[2, i, k] = h2


@wp.kernel
def pixel_grad(x: wp.array2d(dtype=wp.float32), y: wp.array2d(dtype=wp.float32), c: wp.array(dtype=wp.float32),
               g: wp.array(dtype=wp.float32), h: wp.array3d(dtype=wp.float32), l1w: wp.float32,
               out: wp.array2d(dtype=wp.float32)):
    """out[p, k] = l1w sign(x - y) + sum_a g[a] (hmu + 2 x' hxx + y' hxy)[p - a, k] over 0 <= p - a < Ho."""
    p, k = wp.tid()
    ho = h.shape[1]
    ck = c[k % 3]
    xk = x[p, k]
    yk = y[p, k]
    xc = xk - ck
    yc = yk - ck
    o = wp.float32(0.0)
    if xk > yk:
        o = l1w
    elif xk < yk:
        o = -l1w
    for a in range(wp.max(0, p - ho + 1), wp.min(g.shape[0], p + 1)):
        q = p - a
        o += g[a] * (h[0, q, k] + wp.float32(2.0) * xc * h[1, q, k] + yc * h[2, q, k])
    out[p, k] = o


_WINDOWS: dict = {}


def _window(device: torch.device) -> torch.Tensor:
    """The 1-D Gaussian taps (float32, as fused_ssim's) on `device`, made once per device."""
    key = str(device)
    if key not in _WINDOWS:
        g = gaussian_window_1d(SSIM_WINDOW_PX, SSIM_SIGMA_PX, dtype=torch.float64).to(torch.float32)
        _WINDOWS[key] = g.to(device)
    return _WINDOWS[key]


def loss_and_grad_warp(x: torch.Tensor, y: torch.Tensor, lam: float, want_grad: bool
                       ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Loss value (float64 0-d tensor on the device) and, if want_grad, dloss/dx [H,W,3] float32, for contiguous
    float32 [H,W,3] x, y on one device (at least 11x11 px)."""
    dev = x.device
    H, W, _ = x.shape
    g = _window(dev)
    s = g.shape[0]
    ho, wo = H - s + 1, W - s + 1
    n, no = 3 * W, 3 * wo
    x2, y2 = x.reshape(H, n), y.reshape(H, n)
    e = lambda *shape, dt=torch.float32: torch.empty(*shape, dtype=dt, device=dev)  # noqa: E731
    sums, v, S, d, srow = e(H, 4, dt=torch.float64), e(5, ho, n), e(ho, no), e(3, ho, no), e(ho, dt=torch.float64)
    with warp_scope(dev) as wp_:
        A = wp_.from_torch
        wx, wy, wg = A(x2), A(y2), A(g)
        wp_.launch(row_sums, dim=H, inputs=[wx, wy, A(sums)])
        tot = sums.sum(0)
        c = (tot[1:] / (2 * H * W)).to(torch.float32)  # the per-channel mean of the pair (see fused_ssim)
        wc = A(c)
        wp_.launch(vertical_moments, dim=(ho, n), inputs=[wx, wy, wc, wg, A(v)])
        w = -lam / (ho * no)
        wp_.launch(ssim_terms, dim=(ho, no), inputs=[A(v), wc, wg, w, A(S), A(d)])
        wp_.launch(row_sums_1, dim=ho, inputs=[A(S), A(srow)])
        value = (1.0 - lam) * (tot[0] / (H * n)) + lam * (1.0 - srow.sum() / (ho * no))
        if not want_grad:
            return value, None
        h = v[:3]  # the vertical moments are spent: their storage takes the transposed horizontal blur
        wp_.launch(blur_t_rows, dim=(ho, n), inputs=[A(d), wg, A(h)])
        grad = e(H, n)
        wp_.launch(pixel_grad, dim=(H, n), inputs=[wx, wy, wc, wg, A(h), float((1.0 - lam) / (H * n)), A(grad)])
    return value, grad.reshape(H, W, 3)


class WarpPhotometric(torch.autograd.Function):
    """loss(pred, gt, lambda) with the Warp kernels on the tensors' device; the whole gradient is computed in forward
    (when pred needs one) and scaled by the incoming gradient in backward. float32 [H,W,3]; gt gets no gradient."""

    @staticmethod
    def forward(ctx, pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
        x = pred.detach().contiguous()
        y = gt.detach().to(torch.float32).contiguous()
        value, grad = loss_and_grad_warp(x, y, float(lambda_dssim), ctx.needs_input_grad[0])
        if grad is not None:
            ctx.save_for_backward(grad)
        return value.to(torch.float32)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        (grad,) = ctx.saved_tensors
        return grad * grad_out, None, None


def photometric_loss_warp(pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """fused_ssim.photometric_loss with the Warp kernels: float32 renders on a device Warp runs on (CPU or CUDA)
    with gt on the same device and without a gradient; anything else takes the torch autograd path
    (fused_ssim.photometric_torch), which computes the same thing."""
    from trisplat.train.fused_ssim import _check_inputs, photometric_torch

    _check_inputs(pred, gt)
    ok = (pred.dtype == torch.float32 and pred.device.type in ("cpu", "cuda") and gt.device == pred.device
          and not gt.requires_grad)
    if not ok:
        return photometric_torch(pred, gt, lambda_dssim)
    return WarpPhotometric.apply(pred, gt, lambda_dssim)
