"""Depth-normal consistency (2DGS) as one fused Numba kernel with its exact gradient.

The loss is the one `trisplat.train.losses.normal_consistency_torch` spells out in torch (its readable twin and the
test oracle), on a view of H x W pixels with intrinsics K:

  covered  = alpha > min_alpha
  s        = depth / alpha on covered pixels, 0 elsewhere            (surface depth)
  P(u, v)  = ((u - cx) / fx * s, (v - cy) / fy * s, s)               (back-projection, pixel centres u = x + 0.5)
  c        = (P[x+1] - P[x-1]) x (P[y+1] - P[y-1]),  N = +-c / max(|c|, 1e-12) facing the camera
  mask     = covered, not on the border, and s > 0 at the pixel and its 4 neighbours
  loss     = mean over mask of (alpha - normal . N)

Gradients go to the rendered normal, alpha (directly and through s) and depth (through s). The backward is a
gather (every pixel collects from its 4 neighbours), so the kernels are parallel over rows without atomics.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from trisplat.timing import stage
from numba import njit, prange

NORMALIZE_EPS = 1e-12  # as torch.nn.functional.normalize


@njit(cache=True, inline="always")
def _ray(x, y, K):
    return (x + 0.5 - K[0, 2]) / K[0, 0], (y + 0.5 - K[1, 2]) / K[1, 1]


@njit(cache=True, inline="always")
def _differences(surf, K, x, y):
    """Central differences du = P[x+1] - P[x-1], dv = P[y+1] - P[y-1] of the back-projected surface at (x, y)."""
    rxp, ryp = _ray(x + 1, y, K)
    rxm, rym = _ray(x - 1, y, K)
    dux = rxp * surf[y, x + 1] - rxm * surf[y, x - 1]
    duy = ryp * surf[y, x + 1] - rym * surf[y, x - 1]
    duz = surf[y, x + 1] - surf[y, x - 1]
    rxp, ryp = _ray(x, y + 1, K)
    rxm, rym = _ray(x, y - 1, K)
    dvx = rxp * surf[y + 1, x] - rxm * surf[y - 1, x]
    dvy = ryp * surf[y + 1, x] - rym * surf[y - 1, x]
    dvz = surf[y + 1, x] - surf[y - 1, x]
    return dux, duy, duz, dvx, dvy, dvz


@njit(parallel=True, cache=True)
def _forward(normal, depth, alpha, K, min_alpha, surf, nd, mask):
    """surf [H,W], nd [H,W,3] (unit depth normals), mask [H,W]; returns (sum of terms, count)."""
    H, W = depth.shape
    for y in prange(H):
        for x in range(W):
            a = alpha[y, x]
            surf[y, x] = depth[y, x] / max(a, 1e-6) if a > min_alpha else 0.0
    total = np.zeros(H)
    count = np.zeros(H, np.int64)
    for y in prange(1, H - 1):
        for x in range(1, W - 1):
            mask[y, x] = False
            if not (surf[y, x] > 0 and surf[y, x + 1] > 0 and surf[y, x - 1] > 0 and surf[y + 1, x] > 0
                    and surf[y - 1, x] > 0):
                continue
            dux, duy, duz, dvx, dvy, dvz = _differences(surf, K, x, y)
            cx, cy, cz = duy * dvz - duz * dvy, duz * dvx - dux * dvz, dux * dvy - duy * dvx
            ln = max(math.sqrt(cx * cx + cy * cy + cz * cz), NORMALIZE_EPS)
            nx, ny, nz = cx / ln, cy / ln, cz / ln
            rx, ry = _ray(x, y, K)
            s = surf[y, x]
            if nx * rx * s + ny * ry * s + nz * s > 0:  # face the camera
                nx, ny, nz = -nx, -ny, -nz
            nd[y, x, 0], nd[y, x, 1], nd[y, x, 2] = nx, ny, nz
            mask[y, x] = True
            total[y] += alpha[y, x] - (normal[y, x, 0] * nx + normal[y, x, 1] * ny + normal[y, x, 2] * nz)
            count[y] += 1
    return total.sum(), count.sum()


@njit(parallel=True, cache=True)
def _backward(normal, depth, alpha, K, min_alpha, surf, nd, mask, scale, g_normal, g_depth, g_alpha, g_du, g_dv):
    """d(scale * sum over mask of the terms) w.r.t. normal, depth and alpha."""
    H, W = depth.shape
    # Per masked pixel: the gradient on its two central differences du, dv (through c = du x dv and N = c/|c|).
    for y in prange(H):
        for x in range(W):
            for k in range(3):
                g_du[y, x, k] = 0.0
                g_dv[y, x, k] = 0.0
                g_normal[y, x, k] = 0.0
            if not mask[y, x]:
                continue
            for k in range(3):
                g_normal[y, x, k] = -scale * nd[y, x, k]
            dux, duy, duz, dvx, dvy, dvz = _differences(surf, K, x, y)
            cx, cy, cz = duy * dvz - duz * dvy, duz * dvx - dux * dvz, dux * dvy - duy * dvx
            cl = math.sqrt(cx * cx + cy * cy + cz * cz)
            # N = sgn * c / max(|c|, eps); dL/dN = -scale * normal
            nx, ny, nz = nd[y, x, 0], nd[y, x, 1], nd[y, x, 2]
            gx, gy, gz = -scale * normal[y, x, 0], -scale * normal[y, x, 1], -scale * normal[y, x, 2]
            if cl > NORMALIZE_EPS:
                dot = gx * nx + gy * ny + gz * nz
                gx, gy, gz = (gx - dot * nx) / cl, (gy - dot * ny) / cl, (gz - dot * nz) / cl
            else:
                gx, gy, gz = gx / NORMALIZE_EPS, gy / NORMALIZE_EPS, gz / NORMALIZE_EPS
            # the sign flip: N = sgn * c_hat with sgn = nd . c_hat
            sgn = 1.0 if nx * cx + ny * cy + nz * cz >= 0 else -1.0
            gx, gy, gz = sgn * gx, sgn * gy, sgn * gz
            # c = du x dv: g_du = dv x g_c, g_dv = g_c x du
            g_du[y, x, 0] = dvy * gz - dvz * gy
            g_du[y, x, 1] = dvz * gx - dvx * gz
            g_du[y, x, 2] = dvx * gy - dvy * gx
            g_dv[y, x, 0] = gy * duz - gz * duy
            g_dv[y, x, 1] = gz * dux - gx * duz
            g_dv[y, x, 2] = gx * duy - gy * dux
    # Gather: du[x] = P[x+1] - P[x-1], dv[y] = P[y+1] - P[y-1]; P = (ray_x s, ray_y s, s).
    for y in prange(H):
        for x in range(W):
            gpx = gpy = gpz = 0.0
            if x >= 1:
                gpx += g_du[y, x - 1, 0]
                gpy += g_du[y, x - 1, 1]
                gpz += g_du[y, x - 1, 2]
            if x + 1 < W:
                gpx -= g_du[y, x + 1, 0]
                gpy -= g_du[y, x + 1, 1]
                gpz -= g_du[y, x + 1, 2]
            if y >= 1:
                gpx += g_dv[y - 1, x, 0]
                gpy += g_dv[y - 1, x, 1]
                gpz += g_dv[y - 1, x, 2]
            if y + 1 < H:
                gpx -= g_dv[y + 1, x, 0]
                gpy -= g_dv[y + 1, x, 1]
                gpz -= g_dv[y + 1, x, 2]
            rx, ry = _ray(x, y, K)
            g_s = gpx * rx + gpy * ry + gpz
            a = alpha[y, x]
            ga = scale if mask[y, x] else 0.0
            gd = 0.0
            if a > min_alpha:  # s = depth / max(alpha, 1e-6)
                am = max(a, 1e-6)
                gd = g_s / am
                if a > 1e-6:
                    ga -= g_s * depth[y, x] / (am * am)
            g_depth[y, x] = gd
            g_alpha[y, x] = ga


class _NormalConsistency(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal, depth, alpha, K, min_alpha):
        n, d, a = (t.detach().numpy() for t in (normal, depth, alpha))
        k = K.detach().double().numpy()
        H, W = d.shape
        surf = np.empty((H, W), np.float32)
        nd = np.zeros((H, W, 3), np.float32)
        mask = np.zeros((H, W), np.bool_)
        with stage("normal_term"):
            total, count = _forward(n, d, a, k, float(min_alpha), surf, nd, mask)
        ctx.saved = (n, d, a, k, float(min_alpha), surf, nd, mask, int(count))
        return torch.tensor(total / count if count else 0.0, dtype=normal.dtype)

    @staticmethod
    def backward(ctx, grad):
        n, d, a, k, min_alpha, surf, nd, mask, count = ctx.saved
        if count == 0:
            return torch.zeros(n.shape), torch.zeros(d.shape), torch.zeros(a.shape), None, None
        H, W = d.shape
        g_n = np.empty((H, W, 3), np.float32)
        g_d = np.empty((H, W), np.float32)
        g_a = np.empty((H, W), np.float32)
        g_du = np.empty((H, W, 3), np.float32)
        g_dv = np.empty((H, W, 3), np.float32)
        with stage("normal_term"):
            _backward(n, d, a, k, min_alpha, surf, nd, mask, float(grad) / count, g_n, g_d, g_a, g_du, g_dv)
        return torch.from_numpy(g_n), torch.from_numpy(g_d), torch.from_numpy(g_a), None, None


def normal_consistency_fused(normal: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor, K: torch.Tensor,
                             min_alpha: float = 0.5) -> torch.Tensor | None:
    """The fused kernel for CPU float32 contiguous inputs; None when it does not apply (the caller uses torch)."""
    ts = (normal, depth, alpha)
    if any(t.device.type != "cpu" or t.dtype != torch.float32 for t in ts):
        return None
    return _NormalConsistency.apply(normal.contiguous(), depth.contiguous(), alpha.contiguous(), K, min_alpha)
