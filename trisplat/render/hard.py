"""Hard (opaque) rendering: an ordinary z-buffer rasterizer in Numba; each pixel shows its nearest face."""
from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange

from trisplat.render.inputs import validate
from trisplat.render.types import RenderOutput
from trisplat.scene.sh import eval_sh

# Per-face record (float32): edge lines n_k, d_k (9), 1/z plane in screen space A, B, C (3), s_k (3), 1/z per
# vertex (3), camera-facing unit normal (3).
H_EDGE, H_PLANE, H_S, H_ZI, H_NRM, H_N = 0, 9, 12, 15, 18, 21
BANDS_PER_THREAD = 4  # horizontal image bands per Numba thread (load balance; each band scans all faces)


@njit(parallel=True, cache=True, fastmath=True)
def hard_setup(pos, faces, w2c, K, near, width, height, rec, rows):
    """Project and cull every face; rows[f] = (first, last) pixel row whose centre it may cover, (1, 0) if none."""
    F = faces.shape[0]
    for f in prange(F):
        rows[f, 0], rows[f, 1] = 1, 0
        xc = np.empty((3, 3))
        uv = np.empty((3, 2))
        for k in range(3):
            v = faces[f, k]
            for r in range(3):
                xc[k, r] = w2c[r, 0] * pos[v, 0] + w2c[r, 1] * pos[v, 1] + w2c[r, 2] * pos[v, 2] + w2c[r, 3]
        if min(xc[0, 2], min(xc[1, 2], xc[2, 2])) < near:
            continue
        for k in range(3):
            uv[k, 0] = (K[0, 0] * xc[k, 0] + K[0, 1] * xc[k, 1]) / xc[k, 2] + K[0, 2]
            uv[k, 1] = (K[1, 0] * xc[k, 0] + K[1, 1] * xc[k, 1]) / xc[k, 2] + K[1, 2]
        umin = min(uv[0, 0], min(uv[1, 0], uv[2, 0]))
        umax = max(uv[0, 0], max(uv[1, 0], uv[2, 0]))
        vmin = min(uv[0, 1], min(uv[1, 1], uv[2, 1]))
        vmax = max(uv[0, 1], max(uv[1, 1], uv[2, 1]))
        if math.ceil(umin - 0.5) > math.floor(umax - 0.5) or umax < 0.5 or umin > width - 0.5:
            continue
        iy0 = max(0, int(math.ceil(vmin - 0.5)))
        iy1 = min(height - 1, int(math.floor(vmax - 0.5)))
        if iy0 > iy1:
            continue
        area2 = (uv[1, 0] - uv[0, 0]) * (uv[2, 1] - uv[0, 1]) - (uv[1, 1] - uv[0, 1]) * (uv[2, 0] - uv[0, 0])
        if area2 == 0.0:
            continue
        sg = 1.0 if area2 > 0 else -1.0
        aa = abs(area2)
        lens = np.empty(3)
        for k in range(3):
            k1 = (k + 1) % 3
            ex, ey = uv[k1, 0] - uv[k, 0], uv[k1, 1] - uv[k, 1]
            ln = math.sqrt(ex * ex + ey * ey)
            lens[k] = ln
            nx, ny = sg * ey / ln, -sg * ex / ln
            rec[f, 3 * k], rec[f, 3 * k + 1], rec[f, 3 * k + 2] = nx, ny, -(nx * uv[k, 0] + ny * uv[k, 1])
        # 1/z is affine in screen space over a planar face: solve zinv(uv_k) = 1/z_k.
        zi0, zi1, zi2 = 1.0 / xc[0, 2], 1.0 / xc[1, 2], 1.0 / xc[2, 2]
        ax, ay = uv[1, 0] - uv[0, 0], uv[1, 1] - uv[0, 1]
        bx, by = uv[2, 0] - uv[0, 0], uv[2, 1] - uv[0, 1]
        A = ((zi1 - zi0) * by - (zi2 - zi0) * ay) / area2
        B = ((zi2 - zi0) * ax - (zi1 - zi0) * bx) / area2
        rec[f, H_PLANE], rec[f, H_PLANE + 1] = A, B
        rec[f, H_PLANE + 2] = zi0 - A * uv[0, 0] - B * uv[0, 1]
        for k in range(3):
            rec[f, H_S + k] = lens[(k + 1) % 3] / aa
        rec[f, H_ZI], rec[f, H_ZI + 1], rec[f, H_ZI + 2] = zi0, zi1, zi2
        ax, ay, az = xc[1, 0] - xc[0, 0], xc[1, 1] - xc[0, 1], xc[1, 2] - xc[0, 2]
        bx, by, bz = xc[2, 0] - xc[0, 0], xc[2, 1] - xc[0, 1], xc[2, 2] - xc[0, 2]
        cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        clen = math.sqrt(cx * cx + cy * cy + cz * cz)
        if clen == 0.0:
            continue
        if cx * xc[0, 0] + cy * xc[0, 1] + cz * xc[0, 2] > 0:
            clen = -clen
        rec[f, H_NRM], rec[f, H_NRM + 1], rec[f, H_NRM + 2] = cx / clen, cy / clen, cz / clen
        rows[f, 0], rows[f, 1] = iy0, iy1


@njit(parallel=True, cache=True, fastmath=True)
def hard_zbuffer(rec, rows, width, height, nbands, zbuf, fid):
    """Nearest face per pixel centre (largest 1/z); each band of rows is one task and scans every face."""
    F = rec.shape[0]
    band_h = (height + nbands - 1) // nbands
    evals = np.zeros(nbands, np.int64)
    for b in prange(nbands):
        r0, r1 = b * band_h, min(height, (b + 1) * band_h) - 1
        ne = 0
        for f in range(F):
            fr0, fr1 = rows[f, 0], rows[f, 1]
            if fr1 < r0 or fr0 > r1 or fr0 > fr1:
                continue
            n0x, n0y, d0 = rec[f, 0], rec[f, 1], rec[f, 2]
            n1x, n1y, d1 = rec[f, 3], rec[f, 4], rec[f, 5]
            n2x, n2y, d2 = rec[f, 6], rec[f, 7], rec[f, 8]
            A, B, C = rec[f, H_PLANE], rec[f, H_PLANE + 1], rec[f, H_PLANE + 2]
            for iy in range(max(fr0, r0), min(fr1, r1) + 1):
                py = iy + 0.5
                xlo, xhi = 0.5, width - 0.5
                c0, c1, c2 = n0y * py + d0, n1y * py + d1, n2y * py + d2
                empty = False
                for nx, c in ((n0x, c0), (n1x, c1), (n2x, c2)):
                    if nx > 1e-12:
                        xhi = min(xhi, -c / nx)
                    elif nx < -1e-12:
                        xlo = max(xlo, -c / nx)
                    elif c > 0:
                        empty = True
                if empty or xlo > xhi:
                    continue
                ixa = max(0, int(math.ceil(xlo - 0.5)))
                ixb = min(width - 1, int(math.floor(xhi - 0.5)))
                zrow = B * py + C
                base = iy * width
                for ix in range(ixa, ixb + 1):
                    zi = A * (ix + 0.5) + zrow
                    ne += 1
                    if zi > zbuf[base + ix]:
                        zbuf[base + ix] = zi
                        fid[base + ix] = f
        evals[b] = ne
    return evals.sum()


@njit(parallel=True, cache=True, fastmath=True)
def hard_resolve(rec, faces, colors, fid, width, height, perspective, bg, rgb, depth, normal):
    """Interpolate the winning face's vertex colours, its depth and normal at every pixel centre."""
    for iy in prange(height):
        py = iy + 0.5
        for ix in range(width):
            f = fid[iy * width + ix]
            if f < 0:
                for c in range(3):
                    rgb[iy, ix, c] = bg[c]
                    normal[iy, ix, c] = 0.0
                depth[iy, ix] = 0.0
                continue
            px = ix + 0.5
            L0 = rec[f, 0] * px + rec[f, 1] * py + rec[f, 2]
            L1 = rec[f, 3] * px + rec[f, 4] * py + rec[f, 5]
            L2 = rec[f, 6] * px + rec[f, 7] * py + rec[f, 8]
            b0, b1, b2 = -L1 * rec[f, H_S], -L2 * rec[f, H_S + 1], -L0 * rec[f, H_S + 2]
            zinv = rec[f, H_PLANE] * px + rec[f, H_PLANE + 1] * py + rec[f, H_PLANE + 2]
            if perspective:
                b0, b1, b2 = b0 * rec[f, H_ZI] / zinv, b1 * rec[f, H_ZI + 1] / zinv, b2 * rec[f, H_ZI + 2] / zinv
            v0, v1, v2 = faces[f, 0], faces[f, 1], faces[f, 2]
            for c in range(3):
                rgb[iy, ix, c] = b0 * colors[v0, c] + b1 * colors[v1, c] + b2 * colors[v2, c]
                normal[iy, ix, c] = rec[f, H_NRM + c]
            depth[iy, ix] = 1.0 / zinv


def rasterize_hard(positions, faces, colors, world_to_camera, K, width, height, background=None, near: float = 0.01,
                   perspective_correct: bool = False) -> RenderOutput:
    """Opaque z-buffer render: each pixel centre shows the nearest face covering it (no gradients).

    positions [V,3], faces int [F,3], colors [V,3] RGB or [V,(d+1)^2,3] SH; world_to_camera [4,4] or [B,4,4];
    K [3,3] or [B,3,3]; near: faces with a vertex nearer than this (scene units) are culled. Colours are interpolated
    with screen-space barycentrics (perspective-correct on request). Returns RenderOutput: rgb, alpha (0/1), depth
    (view depth, 0 where empty), normal (camera-facing unit face normal, camera frame), face_id (-1 where empty),
    max_weight (1 for faces that win at least one pixel), pairs_evaluated (pixel/face depth tests).
    """
    ones = np.ones(np.asarray(positions.detach() if isinstance(positions, torch.Tensor) else positions).shape[0])
    vi = validate(positions, faces, colors, ones, 1.0, world_to_camera, K, width, height, background)
    if not near > 0:
        raise ValueError(f"near must be > 0, got {near}")
    outs = []
    with torch.no_grad():
        pos = vi.positions.detach().to(torch.float32).cpu().numpy()
        fc = np.ascontiguousarray(vi.faces.cpu().numpy().astype(np.int32))
        F = fc.shape[0]
        for b in range(vi.world_to_camera.shape[0]):
            w2c, Kb = vi.world_to_camera[b], vi.K[b]
            col = vi.colors
            if col.ndim == 3:
                R, t = w2c[:3, :3], w2c[:3, 3]
                col = eval_sh(col, vi.positions - (-(R.T @ t)))
            col = np.ascontiguousarray(col.detach().to(torch.float32).cpu().numpy())
            rec = np.zeros((F, H_N), np.float32)
            rows = np.zeros((F, 2), np.int32)
            hard_setup(pos, fc, w2c.cpu().numpy().astype(np.float64), Kb.cpu().numpy().astype(np.float64),
                       float(near), vi.width, vi.height, rec, rows)
            W, H = vi.width, vi.height
            zbuf = np.zeros(W * H, np.float32)
            fid = np.full(W * H, -1, np.int64)
            nb = max(1, min(H, numba.get_num_threads() * BANDS_PER_THREAD))
            evals = hard_zbuffer(rec, rows, W, H, nb, zbuf, fid)
            rgb = np.empty((H, W, 3), np.float32)
            depth = np.empty((H, W), np.float32)
            normal = np.empty((H, W, 3), np.float32)
            bg = vi.background.to(torch.float32).cpu().numpy()
            hard_resolve(rec, fc, col, fid, W, H, bool(perspective_correct), bg, rgb, depth, normal)
            face_id = torch.from_numpy(fid.reshape(H, W))
            won = torch.zeros(F, dtype=vi.positions.dtype)
            if F:
                won[face_id[face_id >= 0]] = 1.0
            dt = vi.positions.dtype
            outs.append(RenderOutput(rgb=torch.from_numpy(rgb).to(dt), alpha=(face_id >= 0).to(dt),
                                     depth=torch.from_numpy(depth).to(dt), normal=torch.from_numpy(normal).to(dt),
                                     max_weight=won, face_id=face_id, pairs_evaluated=int(evals),
                                     faces_visible=int((rows[:, 0] <= rows[:, 1]).sum())))
    if not vi.batched:
        return outs[0]
    return RenderOutput(rgb=torch.stack([o.rgb for o in outs]), alpha=torch.stack([o.alpha for o in outs]),
                        depth=torch.stack([o.depth for o in outs]), normal=torch.stack([o.normal for o in outs]),
                        max_weight=torch.stack([o.max_weight for o in outs]),
                        face_id=torch.stack([o.face_id for o in outs]),
                        pairs_evaluated=sum(o.pairs_evaluated for o in outs),
                        faces_visible=sum(o.faces_visible for o in outs))


