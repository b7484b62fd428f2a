"""SH colour evaluation in NVIDIA Warp (the backend="warp" twin of the Numba kernels in trisplat.scene.sh_kernels):
colour = max(sum_k Y_k(dir) sh_k + 0.5, 0) and its exact gradient to the coefficients and the directions.

Same maths as the Numba kernels, one thread per vertex: the real SH basis (3DGS band order and signs) at
d / max(|d|, 1e-12), the clamp passing the gradient where its input is >= 0 (as torch.clamp), the direction
gradient through the analytic derivatives of the 16 basis polynomials and the normalisation. Like the Numba kernels
(whose per-vertex scratch is float64), the per-vertex arithmetic is float64 and the buffers float32.

Tensors in, tensors out, on the tensors' device: CUDA tensors run on the GPU (on torch's current stream), CPU
tensors on Warp's CPU device; buffers are torch tensors handed to the kernels through wp.from_torch (views). Only
float32 coefficients take these kernels; other dtypes go through trisplat.scene.sh.eval_sh.
"""
from __future__ import annotations

import torch

from trisplat.render.warp_backend import INSTALL_HINT, warp_scope
from trisplat.scene.sh import C0, C1, C2, C3

try:
    import warp as wp
except ImportError as exc:
    raise ImportError(INSTALL_HINT) from exc

if wp.config.log_level < wp.LOG_WARNING:  # no greeting or per-module load lines from the library
    wp.config.log_level = wp.LOG_WARNING
wp.set_module_options({"enable_backward": False})  # the gradient is written by hand below

vec16d = wp.types.vector(length=16, dtype=wp.float64)
_C0 = wp.constant(wp.float64(C0))
_C1 = wp.constant(wp.float64(C1))
_C20, _C21, _C22, _C23, _C24 = (wp.constant(wp.float64(c)) for c in C2)
_C30, _C31, _C32, _C33, _C34, _C35, _C36 = (wp.constant(wp.float64(c)) for c in C3)
_NORM_EPS = wp.constant(wp.float64(1e-12))  # the oracle's clamp of |dir|


@wp.func
def sh_basis(x: wp.float64, y: wp.float64, z: wp.float64, K: int):
    """The real SH basis Y[:K] at the unit direction (x, y, z) (entries from K on are 0)."""
    Y = vec16d()
    Y[0] = _C0
    if K > 1:
        Y[1] = -_C1 * y
        Y[2] = _C1 * z
        Y[3] = -_C1 * x
    if K > 4:
        xx = x * x
        yy = y * y
        zz = z * z
        two = wp.float64(2.0)
        Y[4] = _C20 * x * y
        Y[5] = _C21 * y * z
        Y[6] = _C22 * (two * zz - xx - yy)
        Y[7] = _C23 * x * z
        Y[8] = _C24 * (xx - yy)
        if K > 9:
            three = wp.float64(3.0)
            four = wp.float64(4.0)
            Y[9] = _C30 * y * (three * xx - yy)
            Y[10] = _C31 * x * y * z
            Y[11] = _C32 * y * (four * zz - xx - yy)
            Y[12] = _C33 * z * (two * zz - three * xx - three * yy)
            Y[13] = _C34 * x * (four * zz - xx - yy)
            Y[14] = _C35 * z * (xx - yy)
            Y[15] = _C36 * x * (xx - three * yy)
    return Y


@wp.func
def sh_basis_vjp(x: wp.float64, y: wp.float64, z: wp.float64, K: int, gY: vec16d):
    """sum_k gY[k] dY_k / d(x, y, z) at the unit direction (x, y, z): the derivatives of the polynomials above."""
    gx = wp.float64(0.0)
    gy = wp.float64(0.0)
    gz = wp.float64(0.0)
    two = wp.float64(2.0)
    three = wp.float64(3.0)
    four = wp.float64(4.0)
    six = wp.float64(6.0)
    eight = wp.float64(8.0)
    if K > 1:
        gy -= _C1 * gY[1]
        gz += _C1 * gY[2]
        gx -= _C1 * gY[3]
    if K > 4:
        g = gY[4] * _C20
        gx += g * y
        gy += g * x
        g = gY[5] * _C21
        gy += g * z
        gz += g * y
        g = gY[6] * _C22
        gx -= two * g * x
        gy -= two * g * y
        gz += four * g * z
        g = gY[7] * _C23
        gx += g * z
        gz += g * x
        g = gY[8] * _C24
        gx += two * g * x
        gy -= two * g * y
        if K > 9:
            xx = x * x
            yy = y * y
            zz = z * z
            g = gY[9] * _C30  # 3xxy - y^3
            gx += six * g * x * y
            gy += g * (three * xx - three * yy)
            g = gY[10] * _C31  # xyz
            gx += g * y * z
            gy += g * x * z
            gz += g * x * y
            g = gY[11] * _C32  # 4yzz - xxy - y^3
            gx -= two * g * x * y
            gy += g * (four * zz - xx - three * yy)
            gz += eight * g * y * z
            g = gY[12] * _C33  # 2z^3 - 3xxz - 3yyz
            gx -= six * g * x * z
            gy -= six * g * y * z
            gz += g * (six * zz - three * xx - three * yy)
            g = gY[13] * _C34  # 4xzz - x^3 - xyy
            gx += g * (four * zz - three * xx - yy)
            gy -= two * g * x * y
            gz += eight * g * x * z
            g = gY[14] * _C35  # xxz - yyz
            gx += two * g * x * z
            gy -= two * g * y * z
            gz += g * (xx - yy)
            g = gY[15] * _C36  # x^3 - 3xyy
            gx += g * (three * xx - three * yy)
            gy -= six * g * x * y
    return wp.vec3d(gx, gy, gz)


@wp.func
def direction(dirs: wp.array2d(dtype=wp.float32), n: int):
    """(d, |d|) of vertex n's direction, in float64."""
    d = wp.vec3d(wp.float64(dirs[n, 0]), wp.float64(dirs[n, 1]), wp.float64(dirs[n, 2]))
    return d, wp.length(d)


@wp.kernel
def sh_forward(sh: wp.array3d(dtype=wp.float32), dirs: wp.array2d(dtype=wp.float32), K: int,
               out: wp.array2d(dtype=wp.float32), live: wp.array2d(dtype=wp.uint8)):
    """out [N,3] = max(sum_{k<K} Y_k(dirs[n]) sh[n,k,:] + 0.5, 0); sh [N,K',3] with K' >= K; live [N,3] = 1 where
    the clamp's input is >= 0 (the clamp passes the gradient there)."""
    n = wp.tid()
    d, ln = direction(dirs, n)
    u = d / wp.max(ln, _NORM_EPS)
    Y = sh_basis(u[0], u[1], u[2], K)
    for c in range(3):
        s = wp.float64(0.5)
        for k in range(K):
            s += Y[k] * wp.float64(sh[n, k, c])
        lv = wp.uint8(0)
        if s >= wp.float64(0.0):
            lv = wp.uint8(1)
        live[n, c] = lv
        out[n, c] = wp.float32(wp.max(s, wp.float64(0.0)))


@wp.kernel
def sh_backward(sh: wp.array3d(dtype=wp.float32), dirs: wp.array2d(dtype=wp.float32), K: int,
                live: wp.array2d(dtype=wp.uint8), g: wp.array2d(dtype=wp.float32),
                g_sh: wp.array3d(dtype=wp.float32), g_dirs: wp.array2d(dtype=wp.float32)):
    """Gradients of sum(g * out) w.r.t. sh (g_sh [N,K',3], zero beyond K) and dirs (g_dirs [N,3])."""
    n = wp.tid()
    d, ln = direction(dirs, n)
    s = wp.max(ln, _NORM_EPS)
    u = d / s
    Y = sh_basis(u[0], u[1], u[2], K)
    gc = wp.vec3d()
    for c in range(3):
        if live[n, c] != wp.uint8(0):
            gc[c] = wp.float64(g[n, c])
    gY = vec16d()
    for k in range(K):
        for c in range(3):
            g_sh[n, k, c] = wp.float32(Y[k] * gc[c])
        gY[k] = (wp.float64(sh[n, k, 0]) * gc[0] + wp.float64(sh[n, k, 1]) * gc[1]
                 + wp.float64(sh[n, k, 2]) * gc[2])
    for k in range(K, sh.shape[1]):
        for c in range(3):
            g_sh[n, k, c] = wp.float32(0.0)
    gd = sh_basis_vjp(u[0], u[1], u[2], K, gY)
    if ln >= _NORM_EPS:  # through d / |d|: remove the radial part, divide by the length
        gd = gd - wp.dot(gd, u) * u
    gd = gd / s
    for c in range(3):
        g_dirs[n, c] = wp.float32(gd[c])


class WarpSH(torch.autograd.Function):
    """colour [N,3] = max(sum_{k<K} Y_k(dirs) sh_k + 0.5, 0) with the Warp kernels on the tensors' device (float32)."""

    @staticmethod
    def forward(ctx, sh, dirs, K):
        sh32 = sh.detach().contiguous()
        d32 = dirs.detach().to(dtype=torch.float32, device=sh.device).contiguous()
        N = sh32.shape[0]
        out = torch.empty(N, 3, dtype=torch.float32, device=sh.device)
        live = torch.empty(N, 3, dtype=torch.uint8, device=sh.device)
        with warp_scope(sh.device) as wp_:
            if N:
                A = wp_.from_torch
                wp_.launch(sh_forward, dim=N, inputs=[A(sh32), A(d32), int(K), A(out), A(live)])
        ctx.save_for_backward(sh32, d32, live)
        ctx.K, ctx.dirs_dtype = int(K), dirs.dtype
        return out

    @staticmethod
    def backward(ctx, g):
        sh32, d32, live = ctx.saved_tensors
        dev = sh32.device
        g32 = g.detach().to(dtype=torch.float32, device=dev).contiguous()
        g_sh = torch.empty_like(sh32)
        g_d = torch.empty_like(d32)
        with warp_scope(dev) as wp_:
            if sh32.shape[0]:
                A = wp_.from_torch
                wp_.launch(sh_backward, dim=sh32.shape[0], inputs=[A(sh32), A(d32), ctx.K, A(live), A(g32), A(g_sh),
                                                                   A(g_d)])
        return g_sh, g_d.to(ctx.dirs_dtype), None


def eval_sh_warp(sh: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """trisplat.scene.sh.eval_sh with the Warp kernels (float32 [N,K,3] coefficients and [N,3] directions, any
    device Warp runs on); other inputs go through eval_sh itself. Same result and gradients as eval_sh."""
    from trisplat.scene.sh import eval_sh, num_sh_bases, sh_degree_from_bases

    if not (sh.ndim == 3 and dirs.ndim == 2 and sh.dtype == torch.float32 and dirs.is_floating_point()
            and sh.device.type in ("cpu", "cuda") and dirs.device == sh.device):
        return eval_sh(sh, dirs, degree)
    K = sh.shape[-2]
    deg = sh_degree_from_bases(K) if degree is None else min(degree, sh_degree_from_bases(K))
    return WarpSH.apply(sh, dirs, num_sh_bases(deg))
