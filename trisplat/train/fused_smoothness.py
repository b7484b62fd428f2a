"""Normal smoothness of a connected surface (mean 1 - cos between the normals of faces sharing an edge) as fused
Numba kernels with the exact gradient, computed in one call of three parallel passes.

The loss is the one `trisplat.train.losses.normal_smoothness_torch` spells out in torch (its readable twin and the
test oracle):

  c_f = (p1 - p0) x (p2 - p0),  n_f = c_f / max(|c_f|, 1e-12)       (face f = (p0, p1, p2))
  loss = mean over edge-sharing pairs (a, b) of 1 - n_a . n_b

Gradient: g_n[f] = -(sum of the normals of f's pair partners) / E, then g_c = (g_n - (g_n . n) n) / |c| (g_n / 1e-12
where |c| is clamped), g_(p1 - p0) = (p2 - p0) x g_c, g_(p2 - p0) = g_c x (p1 - p0), gathered onto the vertices.

The passes are gathers, each over its own index range, so they split across any number of threads without atomics
and without redundant work: (1) per face its unit normal; (2) per face the sum of its partners' normals (a face's
partners from a compressed table of the pairs) and from it the gradient on the face's three corners; (3) per vertex
the sum of its corners' gradients (a compressed table of the faces at each vertex). The two tables
(`SmoothnessTopology`) depend on the face table only: the trainer builds them once per face table.
Why: torch's version (gathers, cross products, norms and their autograd) ran every fine-tuning step over the whole
surface (`trisplat bench losses` on a 328k-face sphere, 2 threads, idle: torch 65.7 ms, the first fused kernels 17.7
ms); those kernels had every thread read every pair and every face (issue 50: 36 ms of a 1-thread surface step on
bonsai's 409k faces, 31 ms on 2 threads).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch
from numba import njit, prange

NORMALIZE_EPS = 1e-12  # as the torch twin's clamp_min


@dataclass(frozen=True)
class SmoothnessTopology:
    """The pairs and the faces as compressed tables: partner[partner_start[f]:partner_start[f + 1]] are the faces
    paired with face f (a pair listed twice counts twice), corner[corner_start[v]:corner_start[v + 1]] the corners
    (3 * face + k) at vertex v."""

    num_faces: int
    num_vertices: int
    num_pairs: int
    partner_start: np.ndarray
    partner: np.ndarray
    corner_start: np.ndarray
    corner: np.ndarray


@njit(cache=True)
def _compress(keys, values, n):
    """start [n+1], sorted values: a counting sort of `values` by `keys` in [0, n) (stable)."""
    start = np.zeros(n + 1, np.int64)
    for k in keys:
        start[k + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    out = np.empty(len(keys), np.int64)
    for j in range(len(keys)):
        out[fill[keys[j]]] = values[j]
        fill[keys[j]] += 1
    return start, out


def smoothness_topology(faces, pairs, num_vertices: int) -> SmoothnessTopology:
    """The compressed tables of `faces` [F,3] and their edge-sharing `pairs` [E,2] (torch tensors or arrays)."""
    fc = np.asarray(faces.detach().cpu() if isinstance(faces, torch.Tensor) else faces).astype(np.int64)
    pr = np.asarray(pairs.detach().cpu() if isinstance(pairs, torch.Tensor) else pairs).astype(np.int64).reshape(-1, 2)
    F = len(fc)
    pstart, partner = _compress(np.concatenate([pr[:, 0], pr[:, 1]]), np.concatenate([pr[:, 1], pr[:, 0]]), F)
    cstart, corner = _compress(fc.reshape(-1), np.arange(3 * F, dtype=np.int64), int(num_vertices))
    return SmoothnessTopology(F, int(num_vertices), len(pr), pstart, partner, cstart, corner)


@njit(parallel=True, cache=True)
def _smoothness(pos, faces, pstart, partner, cstart, corner, scale, T, n, g_corner, g_pos):
    """Sum over the pairs of n_a . n_b; fills g_pos [V,3] (d loss / d positions for loss = 1 - sum * scale).
    n [F,3] and g_corner [3F,3] are scratch (float64)."""
    F, V = faces.shape[0], pos.shape[0]
    for f in prange(F):
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay, az = pos[i1, 0] - pos[i0, 0], pos[i1, 1] - pos[i0, 1], pos[i1, 2] - pos[i0, 2]
        bx, by, bz = pos[i2, 0] - pos[i0, 0], pos[i2, 1] - pos[i0, 1], pos[i2, 2] - pos[i0, 2]
        cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        d = max(math.sqrt(cx * cx + cy * cy + cz * cz), NORMALIZE_EPS)
        n[f, 0], n[f, 1], n[f, 2] = cx / d, cy / d, cz / d
    part = np.zeros(T)
    for t in prange(T):
        for f in range(t * F // T, (t + 1) * F // T):
            sx, sy, sz = 0.0, 0.0, 0.0
            for j in range(pstart[f], pstart[f + 1]):
                b = partner[j]
                sx += n[b, 0]
                sy += n[b, 1]
                sz += n[b, 2]
            nx, ny, nz = n[f, 0], n[f, 1], n[f, 2]
            part[t] += nx * sx + ny * sy + nz * sz  # every pair twice: once from each face
            gx, gy, gz = -scale * sx, -scale * sy, -scale * sz
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = pos[i1, 0] - pos[i0, 0], pos[i1, 1] - pos[i0, 1], pos[i1, 2] - pos[i0, 2]
            bx, by, bz = pos[i2, 0] - pos[i0, 0], pos[i2, 1] - pos[i0, 1], pos[i2, 2] - pos[i0, 2]
            cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            ln = math.sqrt(cx * cx + cy * cy + cz * cz)
            if ln > NORMALIZE_EPS:
                dot = gx * nx + gy * ny + gz * nz
                gcx, gcy, gcz = (gx - dot * nx) / ln, (gy - dot * ny) / ln, (gz - dot * nz) / ln
            else:
                gcx, gcy, gcz = gx / NORMALIZE_EPS, gy / NORMALIZE_EPS, gz / NORMALIZE_EPS
            # c = A x B: g_A = B x g_c, g_B = g_c x A
            gAx, gAy, gAz = by * gcz - bz * gcy, bz * gcx - bx * gcz, bx * gcy - by * gcx
            gBx, gBy, gBz = gcy * az - gcz * ay, gcz * ax - gcx * az, gcx * ay - gcy * ax
            k = 3 * f
            g_corner[k, 0], g_corner[k, 1], g_corner[k, 2] = -gAx - gBx, -gAy - gBy, -gAz - gBz
            g_corner[k + 1, 0], g_corner[k + 1, 1], g_corner[k + 1, 2] = gAx, gAy, gAz
            g_corner[k + 2, 0], g_corner[k + 2, 1], g_corner[k + 2, 2] = gBx, gBy, gBz
    for v in prange(V):
        sx, sy, sz = 0.0, 0.0, 0.0
        for j in range(cstart[v], cstart[v + 1]):
            k = corner[j]
            sx += g_corner[k, 0]
            sy += g_corner[k, 1]
            sz += g_corner[k, 2]
        g_pos[v, 0], g_pos[v, 1], g_pos[v, 2] = sx, sy, sz
    return 0.5 * part.sum()


def smoothness_and_grad(positions: np.ndarray, faces: np.ndarray, pairs: np.ndarray,
                        topology: SmoothnessTopology | None = None) -> tuple[float, np.ndarray]:
    """(loss, d loss / d positions [V,3] float64) for float positions [V,3], int faces [F,3], int
    pairs [E,2]; `topology`: their smoothness_topology (built here when not given)."""
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    fc = np.ascontiguousarray(faces)  # int32 or int64 as given: no copy
    V, F = len(pos), len(fc)
    topo = topology
    if topo is None or (topo.num_faces, topo.num_vertices) != (F, V):
        topo = smoothness_topology(fc, pairs, V)
    g_pos = np.empty_like(pos)
    E = topo.num_pairs
    if E == 0:
        g_pos[:] = 0
        return 0.0, g_pos
    n = np.empty((F, 3))
    g_corner = np.empty((3 * F, 3))
    total = _smoothness(pos, fc, topo.partner_start, topo.partner, topo.corner_start, topo.corner, 1.0 / E,
                        numba.get_num_threads(), n, g_corner, g_pos)
    return 1.0 - total / E, g_pos


class _NormalSmoothness(torch.autograd.Function):
    @staticmethod
    def forward(ctx, positions, faces, pairs, topology):
        loss, grad = smoothness_and_grad(positions.detach().numpy(), faces.detach().numpy(), pairs.detach().numpy(),
                                         topology)
        ctx.save_for_backward(torch.from_numpy(grad).to(positions.dtype))
        return positions.new_tensor(loss)

    @staticmethod
    def backward(ctx, g):
        (grad,) = ctx.saved_tensors
        return grad * g, None, None, None


def normal_smoothness_fused(positions: torch.Tensor, faces: torch.Tensor, pairs: torch.Tensor,
                            topology: SmoothnessTopology | None = None) -> torch.Tensor:
    """The fused CPU version of trisplat.train.losses.normal_smoothness_torch (same value and gradient); `topology`:
    smoothness_topology(faces, pairs, len(positions)), kept by the caller while the face table stays (built here
    otherwise)."""
    return _NormalSmoothness.apply(positions, faces, pairs, topology)
