"""Fused SH colour evaluation on the CPU (Numba): colour = max(sum_k Y_k(dir) sh_k + 0.5, 0) and its exact gradient.

The torch version (trisplat.scene.sh.eval_sh_torch) is the readable oracle; it builds [N,K,3] products in the forward
and the backward, which at 100k+ vertices with degree 3 cost as much as the renderer itself. These kernels read the
coefficients once per pass and write the [N,K,3] coefficient gradient once. The direction gradient goes through the
analytic derivatives of the 16 basis polynomials and the normalisation d / max(|d|, 1e-12), like the oracle.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from trisplat.scene.sh import C0, C1, C2, C3
from trisplat.timing import stage

CHUNKS = 64  # parallel chunks over vertices (per-chunk scratch, no allocation per vertex)
NORM_EPS = 1e-12  # the oracle's clamp of |dir|


@njit(cache=True, inline="always")
def _basis(x, y, z, K, Y):
    """Y[:K] = the real SH basis at the unit direction (x, y, z), 3DGS band order and signs (see sh.sh_basis)."""
    Y[0] = C0
    if K > 1:
        Y[1], Y[2], Y[3] = -C1 * y, C1 * z, -C1 * x
    if K > 4:
        xx, yy, zz = x * x, y * y, z * z
        Y[4] = C2[0] * x * y
        Y[5] = C2[1] * y * z
        Y[6] = C2[2] * (2.0 * zz - xx - yy)
        Y[7] = C2[3] * x * z
        Y[8] = C2[4] * (xx - yy)
        if K > 9:
            Y[9] = C3[0] * y * (3.0 * xx - yy)
            Y[10] = C3[1] * x * y * z
            Y[11] = C3[2] * y * (4.0 * zz - xx - yy)
            Y[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            Y[13] = C3[4] * x * (4.0 * zz - xx - yy)
            Y[14] = C3[5] * z * (xx - yy)
            Y[15] = C3[6] * x * (xx - 3.0 * yy)


@njit(cache=True, inline="always")
def _basis_vjp(x, y, z, K, gY):
    """sum_k gY[k] * dY_k / d(x, y, z) at the unit direction (x, y, z): the derivatives of the polynomials above."""
    gx = gy = gz = 0.0
    if K > 1:
        gy -= C1 * gY[1]
        gz += C1 * gY[2]
        gx -= C1 * gY[3]
    if K > 4:
        g = gY[4] * C2[0]
        gx += g * y
        gy += g * x
        g = gY[5] * C2[1]
        gy += g * z
        gz += g * y
        g = gY[6] * C2[2]
        gx -= 2.0 * g * x
        gy -= 2.0 * g * y
        gz += 4.0 * g * z
        g = gY[7] * C2[3]
        gx += g * z
        gz += g * x
        g = gY[8] * C2[4]
        gx += 2.0 * g * x
        gy -= 2.0 * g * y
        if K > 9:
            xx, yy, zz = x * x, y * y, z * z
            g = gY[9] * C3[0]  # 3xxy - y^3
            gx += 6.0 * g * x * y
            gy += g * (3.0 * xx - 3.0 * yy)
            g = gY[10] * C3[1]  # xyz
            gx += g * y * z
            gy += g * x * z
            gz += g * x * y
            g = gY[11] * C3[2]  # 4yzz - xxy - y^3
            gx -= 2.0 * g * x * y
            gy += g * (4.0 * zz - xx - 3.0 * yy)
            gz += 8.0 * g * y * z
            g = gY[12] * C3[3]  # 2z^3 - 3xxz - 3yyz
            gx -= 6.0 * g * x * z
            gy -= 6.0 * g * y * z
            gz += g * (6.0 * zz - 3.0 * xx - 3.0 * yy)
            g = gY[13] * C3[4]  # 4xzz - x^3 - xyy
            gx += g * (4.0 * zz - 3.0 * xx - yy)
            gy -= 2.0 * g * x * y
            gz += 8.0 * g * x * z
            g = gY[14] * C3[5]  # xxz - yyz
            gx += 2.0 * g * x * z
            gy -= 2.0 * g * y * z
            gz += g * (xx - yy)
            g = gY[15] * C3[6]  # x^3 - 3xyy
            gx += g * (3.0 * xx - 3.0 * yy)
            gy -= 6.0 * g * x * y
    return gx, gy, gz


@njit(cache=True, inline="always")
def _unit(dirs, n):
    dx, dy, dz = dirs[n, 0], dirs[n, 1], dirs[n, 2]
    ln = math.sqrt(dx * dx + dy * dy + dz * dz)
    s = max(ln, NORM_EPS)
    return dx / s, dy / s, dz / s, ln, s


@njit(parallel=True, cache=True)
def sh_forward(sh, dirs, K, out, live):
    """out [N,3] = max(sum_{k<K} Y_k(dirs[n]) sh[n,k,:] + 0.5, 0); sh [N,K',3] with K' >= K, dirs [N,3].
    live [N,3] (bool) records where the clamp passes the gradient: its input is >= 0 (as torch.clamp)."""
    N = sh.shape[0]
    for ch in prange(CHUNKS):
        Y = np.empty(16)
        for n in range(ch * N // CHUNKS, (ch + 1) * N // CHUNKS):
            x, y, z, _, _ = _unit(dirs, n)
            _basis(x, y, z, K, Y)
            for c in range(3):
                s = 0.5
                for k in range(K):
                    s += Y[k] * sh[n, k, c]
                live[n, c] = s >= 0.0
                out[n, c] = max(s, 0.0)


@njit(parallel=True, cache=True)
def sh_backward(sh, dirs, K, live, g, g_sh, g_dirs):
    """Gradients of sum(g * out) w.r.t. sh (g_sh [N,K',3], zero beyond K) and dirs (g_dirs [N,3]); live from
    sh_forward."""
    N, Kf = sh.shape[0], sh.shape[1]
    for ch in prange(CHUNKS):
        Y = np.empty(16)
        gY = np.zeros(16)
        for n in range(ch * N // CHUNKS, (ch + 1) * N // CHUNKS):
            x, y, z, ln, s = _unit(dirs, n)
            _basis(x, y, z, K, Y)
            g0 = g[n, 0] if live[n, 0] else 0.0
            g1 = g[n, 1] if live[n, 1] else 0.0
            g2 = g[n, 2] if live[n, 2] else 0.0
            for k in range(K):
                g_sh[n, k, 0] = Y[k] * g0
                g_sh[n, k, 1] = Y[k] * g1
                g_sh[n, k, 2] = Y[k] * g2
                gY[k] = sh[n, k, 0] * g0 + sh[n, k, 1] * g1 + sh[n, k, 2] * g2
            for k in range(K, Kf):
                g_sh[n, k, 0] = g_sh[n, k, 1] = g_sh[n, k, 2] = 0.0
            gx, gy, gz = _basis_vjp(x, y, z, K, gY)
            if ln >= NORM_EPS:  # through d / |d|: remove the radial part, divide by the length
                r = gx * x + gy * y + gz * z
                gx, gy, gz = gx - r * x, gy - r * y, gz - r * z
            g_dirs[n, 0], g_dirs[n, 1], g_dirs[n, 2] = gx / s, gy / s, gz / s


def _arrays(sh: torch.Tensor, dirs: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Contiguous numpy views of the coefficients and the directions (in the coefficients' dtype)."""
    return sh.detach().contiguous().numpy(), np.ascontiguousarray(dirs.detach().to(sh.dtype).numpy())


class FusedSH(torch.autograd.Function):
    """colour [N,3] = max(sum_{k<K} Y_k(dirs) sh_k + 0.5, 0) with the Numba kernels (CPU tensors, float32/64)."""

    @staticmethod
    def forward(ctx, sh, dirs, K):
        with stage("sh_forward"):
            sh_np, d_np = _arrays(sh, dirs)
            out = np.empty((sh_np.shape[0], 3), sh_np.dtype)
            live = np.empty((sh_np.shape[0], 3), np.bool_)
            sh_forward(sh_np, d_np, K, out, live)
        ctx.save_for_backward(sh, dirs)
        ctx.K, ctx.live = K, live
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g):
        sh, dirs = ctx.saved_tensors
        with stage("sh_backward"):
            sh_np, d_np = _arrays(sh, dirs)
            g_np = np.ascontiguousarray(g.detach().to(sh.dtype).numpy())
            g_sh = np.empty_like(sh_np)
            g_d = np.empty_like(d_np)
            sh_backward(sh_np, d_np, ctx.K, ctx.live, g_np, g_sh, g_d)
        return torch.from_numpy(g_sh), torch.from_numpy(g_d).to(dirs.dtype), None
