"""Hard (opaque) rendering: an ordinary z-buffer rasterizer in Numba; each pixel shows its nearest face."""
from __future__ import annotations

import dataclasses
import math
import threading

import numba
import numpy as np
import torch
from numba import njit, prange

from trisplat.io.colour import linear_to_srgb_torch, srgb_to_linear_torch
from trisplat.render import kernel_math
from trisplat.render.inputs import check_supersample, validate
from trisplat.render.rasterize import camera_center
from trisplat.render.types import RenderOutput, downsample, stack_views
from trisplat.scene.sh import eval_sh

DEPTH_SLABS = 64  # front-to-back passes by nearest-vertex depth (more: better culling; an ad-hoc timing at 1M faces,
#                  800x800, 2 threads: z-buffer 81 ms at 8 slabs, 57 at 32, 53 at 128, faces copied in order)
ORDER_CHUNKS = 64  # parallel chunks of the depth-order counting sort
HIZ_BLOCK = 8  # pixels per side of the occlusion-culling blocks (each keeps the farthest depth it shows)
BANDS_PER_THREAD = 1  # horizontal image bands per Numba thread (no atomics: a band owns its pixels)
KERNEL_MATH_STAMP = "f283f9c65ec7a742"  # kernel_math.source_stamp() last checked against (kernel_math docstring)
_CACHE = kernel_math.source_stamp() == KERNEL_MATH_STAMP
km = kernel_math.compiled(njit(inline="always"), "trisplat.render.kernel_math.cpu_hard")  # the shared z-buffer maths


_workspace = threading.local()


def _scratch(name: str, shape: tuple, dtype) -> np.ndarray:
    """A scratch array kept between calls in this thread (grown when too small, never shrunk). Rendering many views
    of a large mesh then touches no fresh pages: page faults on ~110 MB of per-face scratch cost about 30 ms a frame
    at 1M faces. Only internal buffers come from here; every array handed to the caller is new."""
    n = int(np.prod(shape))
    buf = getattr(_workspace, name, None)
    if buf is None or buf.dtype != np.dtype(dtype) or buf.size < n:
        buf = np.empty(n, dtype)
        setattr(_workspace, name, buf)
    return buf[:n].reshape(shape)


@njit(parallel=True, cache=_CACHE, fastmath=True)
def hard_setup(pos, faces, w2c, K, near, width, height, uvz, box, znear):
    """Per face (kernel_math.hard_setup_face): screen vertices and 1/z (uvz [F,9]: u, v, 1/z per vertex), pixel-centre
    box [F,4] (first row, last row, first column, last column; (1, 0, ...) when culled: behind the near plane,
    degenerate or off-screen) and the largest 1/z (its nearest vertex)."""
    for f in prange(faces.shape[0]):
        km.hard_setup_face(f, pos, faces, w2c, K, near, width, height, uvz, box, znear)


@njit(cache=_CACHE, inline="always")
def _slab(zn, lo, scale, nslabs):
    return min(nslabs - 1, int((1.0 / zn - lo) * scale))


@njit(parallel=True, cache=_CACHE)
def depth_order(box, znear, uvz, nslabs, order, uvz_o, box_o, znear_o):
    """Visible faces grouped by depth slab of their nearest vertex, nearest slab first, input order inside a slab
    (a stable counting sort, parallel over chunks of faces: per-chunk histograms, then each chunk scatters its
    faces to its own offsets, so the result is the same as the serial sort). Writes the face ids to order[:n] and
    copies their rows of uvz, box and znear to uvz_o, box_o, znear_o in that order, so that the z-buffer streams
    through memory instead of jumping between faces (it is memory-bound). Returns n, the visible faces."""
    F = box.shape[0]
    nch = ORDER_CHUNKS
    lo_c = np.full(nch, np.inf)
    hi_c = np.zeros(nch)
    for c in prange(nch):
        lo, hi = np.inf, 0.0
        for f in range(c * F // nch, (c + 1) * F // nch):
            if box[f, 0] <= box[f, 1]:
                z = 1.0 / znear[f]
                lo = min(lo, z)
                hi = max(hi, z)
        lo_c[c], hi_c[c] = lo, hi
    lo, hi = lo_c.min(), hi_c.max()
    scale = nslabs / (hi - lo) if hi > lo else 0.0
    count = np.zeros((nch, nslabs), np.int64)
    for c in prange(nch):
        for f in range(c * F // nch, (c + 1) * F // nch):
            if box[f, 0] <= box[f, 1]:
                count[c, _slab(znear[f], lo, scale, nslabs)] += 1
    start = np.empty((nch, nslabs), np.int64)  # slab-major, chunk-minor offsets
    run = 0
    for s in range(nslabs):
        for c in range(nch):
            start[c, s] = run
            run += count[c, s]
    for c in prange(nch):  # reads in face order; writes go to one sequential stream per slab
        fill = start[c].copy()
        for f in range(c * F // nch, (c + 1) * F // nch):
            if box[f, 0] <= box[f, 1]:
                s = _slab(znear[f], lo, scale, nslabs)
                i = fill[s]
                fill[s] += 1
                order[i] = f
                for k in range(9):
                    uvz_o[i, k] = uvz[f, k]
                for k in range(4):
                    box_o[i, k] = box[f, k]
                znear_o[i] = znear[f]
    return run


@njit(cache=_CACHE, inline="always")
def _clip(rnx, c, xlo, xhi):
    """Clip the row's x range to the closed half-plane nx * x + c <= 0 (rnx = 1/nx, 0 for a horizontal edge)."""
    if rnx > 0:
        xhi = min(xhi, -c * rnx)
    elif rnx < 0:
        xlo = max(xlo, -c * rnx)
    elif c > 0:
        xlo = xhi + 1
    return xlo, xhi


@njit(cache=_CACHE, fastmath=True, inline="always")
def _block_min(zbuf, width, y0, y1, x0, x1):
    """Smallest 1/z over zbuf[y0:y1, x0:x1] (row-major, `width` wide); the common full 8-wide case unrolled."""
    m = np.float32(np.inf)
    if x1 - x0 == 8:
        for yy in range(y0, y1):
            r = yy * width + x0
            m = min(m, min(min(min(zbuf[r], zbuf[r + 1]), min(zbuf[r + 2], zbuf[r + 3])),
                           min(min(zbuf[r + 4], zbuf[r + 5]), min(zbuf[r + 6], zbuf[r + 7]))))
    else:
        for yy in range(y0, y1):
            for xx in range(x0, x1):
                m = min(m, zbuf[yy * width + xx])
    return m


@njit(parallel=True, cache=_CACHE, fastmath=True)
def hard_zbuffer(uvz, box, znear, width, height, nbands, zbuf, fid):
    """Nearest face per pixel centre (largest 1/z), the faces given front to back by slab (depth_order); fid gets
    the row index into these arrays. Each band of rows is one task. Occlusion culling: every HIZ_BLOCK x HIZ_BLOCK
    block keeps the smallest 1/z it shows (0 while a pixel is empty); a face whose nearest vertex is farther than
    that in every block it touches is skipped. A block's value is recomputed only when a face overwrote a pixel
    holding it (writes only raise 1/z, so otherwise the block minimum cannot change): the values stay exact."""
    Bk = HIZ_BLOCK
    band_h = ((height + nbands - 1) // nbands + Bk - 1) // Bk * Bk
    nbx = (width + Bk - 1) // Bk
    evals = np.zeros(nbands, np.int64)
    for b in prange(nbands):
        r0, r1 = b * band_h, min(height, (b + 1) * band_h) - 1
        if r0 > r1:
            continue
        hz = np.zeros(((r1 - r0) // Bk + 1) * nbx, np.float32)
        ne = 0
        for f in range(box.shape[0]):
            fr0, fr1 = box[f, 0], box[f, 1]
            if fr1 < r0 or fr0 > r1:
                continue
            ya, yb = max(fr0, r0), min(fr1, r1)
            bx0, bx1 = box[f, 2] // Bk, box[f, 3] // Bk
            by0, by1 = (ya - r0) // Bk, (yb - r0) // Bk
            zn = znear[f]
            visible = False
            for by in range(by0, by1 + 1):
                for bx in range(bx0, bx1 + 1):
                    if zn > hz[by * nbx + bx]:
                        visible = True
            if not visible:
                continue
            # Edge functions (unnormalised; only signs matter here) and the screen-space plane of 1/z.
            n0x, n0y, d0, n1x, n1y, d1, n2x, n2y, d2, A, Bp, C = km.hard_lines(
                uvz[f, 0], uvz[f, 1], uvz[f, 2], uvz[f, 3], uvz[f, 4], uvz[f, 5], uvz[f, 6], uvz[f, 7], uvz[f, 8])
            q0 = np.float32(1.0) / n0x if n0x != 0 else np.float32(0.0)
            q1 = np.float32(1.0) / n1x if n1x != 0 else np.float32(0.0)
            q2 = np.float32(1.0) / n2x if n2x != 0 else np.float32(0.0)
            ff = np.int32(f)
            stale = False  # a pixel holding its block's minimum was overwritten
            for iy in range(ya, yb + 1):
                py = np.float32(iy) + np.float32(0.5)
                c0, c1, c2 = n0y * py + d0, n1y * py + d1, n2y * py + d2
                xlo, xhi = _clip(q0, c0, np.float32(0.5), np.float32(width - 0.5))
                xlo, xhi = _clip(q1, c1, xlo, xhi)
                xlo, xhi = _clip(q2, c2, xlo, xhi)
                if xlo > xhi:
                    continue
                ixa = max(0, int(math.ceil(xlo - np.float32(0.5))))
                ixb = min(width - 1, int(math.floor(xhi - np.float32(0.5))))
                zrow = Bp * py + C
                base = iy * width
                hrow = ((iy - r0) // Bk) * nbx
                ne += ixb - ixa + 1
                for ix in range(ixa, ixb + 1):
                    zi = A * (np.float32(ix) + np.float32(0.5)) + zrow
                    old = zbuf[base + ix]
                    if zi > old:
                        if old <= hz[hrow + ix // Bk]:
                            stale = True
                        zbuf[base + ix] = zi
                        fid[base + ix] = ff
            if stale:  # recompute the farthest depth of the blocks this face touched
                for by in range(by0, by1 + 1):
                    ya_, yb_ = r0 + by * Bk, min(r0 + by * Bk + Bk, r1 + 1)
                    for bx in range(bx0, bx1 + 1):
                        xa_, xb_ = bx * Bk, min(bx * Bk + Bk, width)
                        hz[by * nbx + bx] = _block_min(zbuf, width, ya_, yb_, xa_, xb_)
        evals[b] = ne
    return evals.sum()


@njit(parallel=True, cache=_CACHE, fastmath=True)
def hard_resolve(uvz, order, pos, faces, w2c, colors, fid, width, height, perspective, bg, rgb, depth, normal,
                 face_id, won):
    """Interpolate the winning face's vertex colours, its depth and camera-facing normal at every pixel centre.
    fid holds rows of the gathered arrays (uvz); order maps them to face ids, written to face_id [H,W]; won[f] = 1
    for every face that wins a pixel (threads may write the same 1 to the same face: no reads, no conflict)."""
    for iy in prange(height):
        py = iy + 0.5
        last = -1  # per-face values are reused along a row while the winning face stays the same
        u0 = v0 = z0 = u1 = v1 = z1 = u2 = v2 = z2 = ia = 0.0
        i0 = i1 = i2 = 0
        nx = ny = nz = 0.0
        f = -1
        for ix in range(width):
            g = fid[iy * width + ix]
            if g < 0:
                for c in range(3):
                    rgb[iy, ix, c] = bg[c]
                    normal[iy, ix, c] = 0.0
                depth[iy, ix] = 0.0
                face_id[iy, ix] = -1
                continue
            if g != last:
                last = g
                f = order[g]
                won[f] = 1.0
                u0, v0, z0 = uvz[g, 0], uvz[g, 1], uvz[g, 2]
                u1, v1, z1 = uvz[g, 3], uvz[g, 4], uvz[g, 5]
                u2, v2, z2 = uvz[g, 6], uvz[g, 7], uvz[g, 8]
                ia = 1.0 / ((u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0))
                i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
                nx, ny, nz = km.hard_face_normal(pos, faces, f, w2c)
            face_id[iy, ix] = f
            b0, b1, b2, dep = km.hard_pixel(u0, v0, z0, u1, v1, z1, u2, v2, z2, ia, ix + 0.5, py, perspective)
            for c in range(3):
                rgb[iy, ix, c] = b0 * colors[i0, c] + b1 * colors[i1, c] + b2 * colors[i2, c]
            depth[iy, ix] = dep
            normal[iy, ix, 0], normal[iy, ix, 1], normal[iy, ix, 2] = nx, ny, nz


def _hard_linear_light(vi, near: float, perspective_correct: bool, ss: int, backend: str | None) -> RenderOutput:
    """rasterize_hard with linear_light: each camera's colours (SH evaluated there) and the background decoded to
    linear, rendered, the pixels encoded back to sRGB."""
    outs = []
    for b in range(vi.world_to_camera.shape[0]):
        w2c = vi.world_to_camera[b]
        col = vi.colors if vi.colors.ndim == 2 else eval_sh(vi.colors, vi.positions - camera_center(w2c))
        out = rasterize_hard(vi.positions, vi.faces, srgb_to_linear_torch(col), w2c, vi.K[b], vi.width, vi.height,
                             srgb_to_linear_torch(vi.background), near, perspective_correct, ss, backend)
        outs.append(dataclasses.replace(out, rgb=linear_to_srgb_torch(out.rgb)))
    return outs[0] if not vi.batched else stack_views(outs)


def rasterize_hard(positions, faces, colors, world_to_camera, K, width, height, background=None, near: float = 0.01,
                   perspective_correct: bool = False, supersample: int = 1, backend: str | None = None,
                   linear_light: bool = False) -> RenderOutput:
    """Opaque z-buffer render: each pixel centre shows the nearest face covering it (no gradients).

    supersample s > 1: each pixel is the mean of an s x s grid of such samples (supersampling anti-aliasing, the
    box filter of the soft renderer's `supersample`; render.types.downsample says what each output becomes).

    positions [V,3], faces int [F,3], colors [V,3] RGB or [V,(d+1)^2,3] SH; world_to_camera [4,4] or [B,4,4];
    K [3,3] or [B,3,3]; near: faces with a vertex nearer than this (scene units) are culled. Colours are interpolated
    with screen-space barycentrics (perspective-correct on request). Returns RenderOutput: rgb, alpha (0/1; the
    covered share of the samples when supersampled), depth (view depth, 0 where empty), normal (camera-facing unit
    face normal, camera frame), face_id (-1 where empty), max_weight (1 for faces that win at least one sample),
    pairs_evaluated (sample/face depth tests). backend: 'numba' (CPU) or 'cuda' (the numba-cuda kernels on the
    tensors' GPU, see render.cuda_backend; needs the gpu extra); None: cuda for CUDA tensors when numba-cuda can run
    there, else numba (which renders on the CPU and returns CPU tensors). linear_light: colours and background decoded
    from sRGB to linear light, interpolated and averaged over the supersamples there, each pixel encoded back to sRGB
    (RenderOptions.linear_light; how a glTF viewer shows the same vertex colours).
    """
    vi = validate(positions, faces, colors, None, 1.0, world_to_camera, K, width, height, background)
    if not near > 0:
        raise ValueError(f"near must be > 0, got {near}")
    ss = check_supersample(supersample)
    if linear_light:
        return _hard_linear_light(vi, near, perspective_correct, ss, backend)
    if backend is None:
        from trisplat.render.device import cuda_unavailable

        backend = "cuda" if vi.positions.device.type == "cuda" and cuda_unavailable() is None else "numba"
    if backend == "cuda":
        from trisplat.render.cuda_backend import rasterize_hard_cuda

        return rasterize_hard_cuda(vi, float(near), bool(perspective_correct), ss)
    if backend != "numba":
        raise ValueError(f"backend must be 'numba' or 'cuda', got {backend!r}")
    outs = []
    with torch.no_grad():
        pos = vi.positions.detach().to(torch.float32).cpu().numpy()
        fc = np.ascontiguousarray(vi.faces.cpu().numpy(), dtype=np.int32)
        F = fc.shape[0]
        for b in range(vi.world_to_camera.shape[0]):
            w2c, Kb = vi.world_to_camera[b], vi.K[b]
            col = vi.colors
            if col.ndim == 3:
                R, t = w2c[:3, :3], w2c[:3, 3]
                col = eval_sh(col, vi.positions - (-(R.T @ t)))
            col = np.ascontiguousarray(col.detach().to(torch.float32).cpu().numpy())
            W, H = vi.width * ss, vi.height * ss
            Kb = torch.cat([Kb[:2] * ss, Kb[2:]])
            w2c_np = w2c.cpu().numpy().astype(np.float64)
            uvz = _scratch("uvz", (F, 9), np.float32)
            box = _scratch("box", (F, 4), np.int32)
            znear = _scratch("znear", (F,), np.float32)
            hard_setup(pos, fc, w2c_np, Kb.cpu().numpy().astype(np.float64), float(near), W, H, uvz, box, znear)
            order = _scratch("order", (F,), np.int32)
            uvz_o = _scratch("uvz_o", (F, 9), np.float32)
            box_o = _scratch("box_o", (F, 4), np.int32)
            znear_o = _scratch("znear_o", (F,), np.float32)
            n = depth_order(box, znear, uvz, DEPTH_SLABS, order, uvz_o, box_o, znear_o)
            order, uvz_o, box_o, znear_o = order[:n], uvz_o[:n], box_o[:n], znear_o[:n]
            zbuf = _scratch("zbuf", (W * H,), np.float32)
            zbuf[:] = 0.0
            fid = _scratch("fid", (W * H,), np.int32)
            fid[:] = -1
            nb = max(1, min(H, numba.get_num_threads() * BANDS_PER_THREAD))
            evals = hard_zbuffer(uvz_o, box_o, znear_o, W, H, nb, zbuf, fid)
            rgb = np.empty((H, W, 3), np.float32)
            depth = np.empty((H, W), np.float32)
            normal = np.empty((H, W, 3), np.float32)
            face_id_np = np.empty((H, W), np.int64)
            won_np = np.zeros(F, np.float32)
            bg = vi.background.to(torch.float32).cpu().numpy()
            hard_resolve(uvz_o, order, pos, fc, w2c_np, col, fid, W, H, bool(perspective_correct), bg, rgb, depth,
                         normal, face_id_np, won_np)
            face_id = torch.from_numpy(face_id_np)
            won = torch.from_numpy(won_np).to(vi.positions.dtype)
            dt = vi.positions.dtype
            outs.append(downsample(RenderOutput(
                rgb=torch.from_numpy(rgb).to(dt), alpha=(face_id >= 0).to(dt), depth=torch.from_numpy(depth).to(dt),
                normal=torch.from_numpy(normal).to(dt), max_weight=won, face_id=face_id, pairs_evaluated=int(evals),
                faces_visible=int(order.shape[0])), ss))
    return outs[0] if not vi.batched else stack_views(outs)
