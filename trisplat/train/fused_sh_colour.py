"""Vertex colours from the trainable scene's two SH parameters, without joining them into one table (issue 50).

The trainable scene keeps the SH coefficients as two parameters with their own learning rates, sh_dc [V,1,3] and
sh_rest [V,R,3]. The renderer evaluates SH from one table [V,K,3] (trisplat.scene.sh.eval_sh); for it the trainer
joined the two with torch.cat at every step, and the table's gradient was split back into two strided views that the
gradient accumulation then copied: the 42 MB table of bonsai's 221k-vertex surface moved three more times per step,
~20 ms of a 1-thread step. Here the colours are evaluated from the two parameters directly (coefficient k is
sh_dc[:, 0] for k = 0, sh_rest[:, k - 1] after), by the same kernels' maths (trisplat.scene.sh_kernels: its basis,
its derivatives and its normalisation of the directions), and the gradients go into two contiguous tensors, one per
parameter. The trainer passes the colours [V,3] to the renderer, which then does what it did after its own SH
evaluation.

The readable twin and test oracle is `sh_colours_torch`: eval_sh_torch(torch.cat([sh_dc, sh_rest], 1)[:, :K], dirs).
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from trisplat.scene.sh import eval_sh_torch
from trisplat.scene.sh_kernels import CHUNKS, NORM_EPS, _basis, _basis_vjp, _unit
from trisplat.timing import stage


@njit(parallel=True, cache=True)
def _forward(dc, rest, dirs, K, out, live, sel, keep):
    """out [N,3] = max(sum_{k<K} Y_k(dirs[n]) c_k + 0.5, 0) with c_0 = dc[n, 0], c_k = rest[n, k - 1]; live [N,3]
    where the clamp passes the gradient (its input >= 0). sel: the rows to evaluate (int64), keep [N] their mask;
    the other rows 0 and not live. sel empty: every row."""
    N = dc.shape[0]
    M = sel.shape[0] if sel.shape[0] > 0 else N
    for n in prange(N if sel.shape[0] > 0 else 0):  # the rows outside sel
        if not keep[n]:
            out[n, 0] = out[n, 1] = out[n, 2] = 0.0
            live[n, 0] = live[n, 1] = live[n, 2] = False
    for ch in prange(CHUNKS):
        Y = np.empty(16)
        for m in range(ch * M // CHUNKS, (ch + 1) * M // CHUNKS):
            n = sel[m] if sel.shape[0] > 0 else m
            x, y, z, _, _ = _unit(dirs, n)
            _basis(x, y, z, K, Y)
            for c in range(3):
                s = 0.5 + Y[0] * dc[n, 0, c]
                for k in range(1, K):
                    s += Y[k] * rest[n, k - 1, c]
                live[n, c] = s >= 0.0
                out[n, c] = max(s, 0.0)


@njit(parallel=True, cache=True)
def _backward(dc, rest, dirs, K, live, g, g_dc, g_rest, g_dirs, sel, keep):
    """Gradients of sum(g * out) w.r.t. dc (g_dc [N,1,3]), rest (g_rest [N,R,3], zero past K - 1) and dirs
    (g_dirs [N,3]); sel and keep as in _forward (the rows outside sel get zeros)."""
    N, R = dc.shape[0], rest.shape[1]
    M = sel.shape[0] if sel.shape[0] > 0 else N
    for n in prange(N if sel.shape[0] > 0 else 0):  # the rows outside sel
        if not keep[n]:
            g_dc[n, 0, 0] = g_dc[n, 0, 1] = g_dc[n, 0, 2] = 0.0
            for r in range(R):  # (a slice assignment here would be a parallel loop of its own, launched per row)
                g_rest[n, r, 0] = g_rest[n, r, 1] = g_rest[n, r, 2] = 0.0
            g_dirs[n, 0] = g_dirs[n, 1] = g_dirs[n, 2] = 0.0
    for ch in prange(CHUNKS):
        Y = np.empty(16)
        gY = np.zeros(16)
        for m in range(ch * M // CHUNKS, (ch + 1) * M // CHUNKS):
            n = sel[m] if sel.shape[0] > 0 else m
            x, y, z, ln, s = _unit(dirs, n)
            _basis(x, y, z, K, Y)
            g0 = g[n, 0] if live[n, 0] else 0.0
            g1 = g[n, 1] if live[n, 1] else 0.0
            g2 = g[n, 2] if live[n, 2] else 0.0
            g_dc[n, 0, 0], g_dc[n, 0, 1], g_dc[n, 0, 2] = Y[0] * g0, Y[0] * g1, Y[0] * g2
            gY[0] = dc[n, 0, 0] * g0 + dc[n, 0, 1] * g1 + dc[n, 0, 2] * g2
            for k in range(1, K):
                g_rest[n, k - 1, 0] = Y[k] * g0
                g_rest[n, k - 1, 1] = Y[k] * g1
                g_rest[n, k - 1, 2] = Y[k] * g2
                gY[k] = rest[n, k - 1, 0] * g0 + rest[n, k - 1, 1] * g1 + rest[n, k - 1, 2] * g2
            for j in range(max(K - 1, 0), R):
                g_rest[n, j, 0] = g_rest[n, j, 1] = g_rest[n, j, 2] = 0.0
            gx, gy, gz = _basis_vjp(x, y, z, K, gY)
            if ln >= NORM_EPS:  # through d / |d|: remove the radial part, divide by the length
                r = gx * x + gy * y + gz * z
                gx, gy, gz = gx - r * x, gy - r * y, gz - r * z
            g_dirs[n, 0], g_dirs[n, 1], g_dirs[n, 2] = gx / s, gy / s, gz / s


class _SHColours(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sh_dc, sh_rest, dirs, K, sel, keep):
        with stage("sh_forward"):
            dc, rest = sh_dc.detach().numpy(), sh_rest.detach().numpy()
            d = np.ascontiguousarray(dirs.detach().to(sh_dc.dtype).numpy())
            out = np.empty((dc.shape[0], 3), dc.dtype)
            live = np.empty((dc.shape[0], 3), np.bool_)
            _forward(dc, rest, d, K, out, live, sel, keep)
        ctx.save_for_backward(sh_dc, sh_rest, dirs)
        ctx.K, ctx.live, ctx.sel, ctx.keep = K, live, sel, keep
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g):
        sh_dc, sh_rest, dirs = ctx.saved_tensors
        with stage("sh_backward"):
            dc, rest = sh_dc.detach().numpy(), sh_rest.detach().numpy()
            d = np.ascontiguousarray(dirs.detach().to(sh_dc.dtype).numpy())
            g_np = np.ascontiguousarray(g.detach().to(sh_dc.dtype).numpy())
            g_dc, g_rest, g_d = np.empty_like(dc), np.empty_like(rest), np.empty_like(d)
            _backward(dc, rest, d, ctx.K, ctx.live, g_np, g_dc, g_rest, g_d, ctx.sel, ctx.keep)
        return torch.from_numpy(g_dc), torch.from_numpy(g_rest), torch.from_numpy(g_d).to(dirs.dtype), None, None, None


def sh_colours_torch(sh_dc: torch.Tensor, sh_rest: torch.Tensor, dirs: torch.Tensor, K: int) -> torch.Tensor:
    """[V,3]: max(sum_{k<K} Y_k(dirs) c_k + 0.5, 0) of the table [sh_dc | sh_rest]'s first K bases (torch ops)."""
    return eval_sh_torch(torch.cat([sh_dc, sh_rest], 1)[:, :K], dirs)


def sh_colours(sh_dc: torch.Tensor, sh_rest: torch.Tensor, dirs: torch.Tensor, K: int,
               only: np.ndarray | None = None) -> torch.Tensor:
    """sh_colours_torch's value and gradients (to sh_dc, sh_rest and dirs); the Numba kernels for contiguous CPU
    float32/64 parameters, torch elsewhere. K past the parameters' R + 1 bases gives them all (as a slice does).

    only: a [V] mask (trisplat.render.vertices_in_view) of the vertices whose colours will be read; the Numba
    kernels evaluate those alone and give the others colour 0 and zero gradients (their true gradient when nothing
    reads them). The torch path evaluates every vertex."""
    K = max(1, min(int(K), sh_rest.shape[1] + 1))
    if all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) and t.is_contiguous()
           for t in (sh_dc, sh_rest)) and sh_dc.dtype == sh_rest.dtype and dirs.device.type == "cpu" \
            and sh_dc.ndim == 3 and sh_dc.shape[1:] == (1, 3) and sh_rest.ndim == 3 and sh_rest.shape[2] == 3 \
            and dirs.is_floating_point():
        if only is None:
            return _SHColours.apply(sh_dc, sh_rest, dirs, K, _EVERY, _EVERY_KEPT)
        keep = np.ascontiguousarray(only, dtype=np.uint8)
        sel = np.flatnonzero(keep).astype(np.int64)
        if sel.shape[0] == 0:  # nothing in view: every colour 0, every gradient 0
            return _NoColours.apply(sh_dc, sh_rest, dirs)
        return _SHColours.apply(sh_dc, sh_rest, dirs, K, sel, keep)
    return sh_colours_torch(sh_dc, sh_rest, dirs, K)


_EVERY, _EVERY_KEPT = np.empty(0, np.int64), np.empty(0, np.uint8)  # the kernels' "every row"


class _NoColours(torch.autograd.Function):
    """No vertex in view: colours 0 [V,3], zero gradients (what the kernels give an empty selection)."""

    @staticmethod
    def forward(ctx, sh_dc, sh_rest, dirs):
        ctx.shapes = (sh_dc, sh_rest, dirs)
        return sh_dc.new_zeros((sh_dc.shape[0], 3))

    @staticmethod
    def backward(ctx, g):
        sh_dc, sh_rest, dirs = ctx.shapes
        return torch.zeros_like(sh_dc), torch.zeros_like(sh_rest), torch.zeros_like(dirs)
