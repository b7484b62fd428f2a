"""CUDA kernels of the soft and hard rasterizers (numba-cuda): kernel_math's maths launched as GPU threads.

The tile design of 3DGS / gsplat, with the CPU kernels' maths (kernel_math.py, the same THETA layout):
  setup_faces      one thread per face: kernel_math.setup_face (projection, culling, edge lines, 1/inradius, colours
                   -> THETA [F,29], pixel-centre box, centroid depth, exact tile count), float64 like the CPU setup
  emit_pairs       one thread per face: one (tile << 32 | depth bits) key and the face id per overlapped tile; the
                   keys are then sorted on the device with torch (cuda_backend.bin_pairs): per-tile lists, front to back
  raster_forward   one block per tile, one thread per pixel: the tile's faces in shared-memory batches, front-to-back
                   compositing, early stop at T < transmittance_min, per-face max weight (warp max, one atomic)
  raster_backward  the same walk, front to back as on the CPU (the light still to come is the pixel's total minus
                   the running prefix: no division to recover T); per-face THETA gradients summed over each warp
                   (shuffles), one atomic add per warp and entry
  setup_backward   one thread per face: kernel_math.face_backward (THETA gradient -> vertex gradients, float64),
                   atomic adds onto the shared vertices
  hard_setup / hard_pixels / hard_resolve   the z-buffer on the same binning: a tile's faces ordered by their
                   nearest vertex, so a pixel stops at the first face that cannot be nearer than what it shows

Under numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1, how CI tests these kernels without a GPU) the warp shuffles
and votes, which it does not provide, become per-thread identities and every thread adds its own contribution
(_warp_any, _warp_sum, _warp_max, _leader): the sums are the same; the shuffles themselves run only on a GPU.
Blocks have tile_size^2 threads, a whole number of warps (tile sizes 8, 16, 24, 32).
"""
from __future__ import annotations

import numba
import numpy as np
from numba import cuda

from trisplat.render import kernel_math
from trisplat.render.kernel_math import N_THETA, T_COL, T_INVR, T_NRM, T_OP, T_S, T_ZI

KERNEL_MATH_STAMP = "f283f9c65ec7a742"  # kernel_math.source_stamp() last checked against (kernel_math docstring)
_CACHE = kernel_math.source_stamp() == KERNEL_MATH_STAMP
SIMULATOR = bool(numba.config.ENABLE_CUDASIM)
km = kernel_math.compiled(cuda.jit(device=True), "trisplat.render.kernel_math.cuda")
BATCH = 256  # faces per shared-memory batch (29 + 4 + 1 words each: 34 KB per block)
N_HARD = 12  # per-face row of the z-buffer: 9 edge-function coefficients, then A, B, C of the 1/z plane
TILE_SIZES = (8, 16, 24, 32)  # tile_size^2 threads per block: a whole number of warps, at most 1024
FACE_THREADS = 128  # threads per block of the per-face kernels
FULL_MASK = 0xFFFFFFFF

if SIMULATOR:  # no warp shuffles or votes in the simulator: each thread stands for its own warp

    @cuda.jit(device=True)
    def _warp_any(p):
        return p

    @cuda.jit(device=True)
    def _warp_sum(v):
        return v

    @cuda.jit(device=True)
    def _warp_max(v):
        return v

    @cuda.jit(device=True)
    def _leader():
        return True

else:

    @cuda.jit(device=True)
    def _warp_any(p):
        """Whether p holds for any thread of the warp (every thread gets the answer)."""
        return cuda.any_sync(FULL_MASK, p)

    @cuda.jit(device=True)
    def _warp_sum(v):
        """The warp's sum of v, in its first thread (every thread of the warp must call it)."""
        for d in (16, 8, 4, 2, 1):
            v += cuda.shfl_down_sync(FULL_MASK, v, d)
        return v

    @cuda.jit(device=True)
    def _warp_max(v):
        """The warp's largest v, in its first thread (every thread of the warp must call it)."""
        for d in (16, 8, 4, 2, 1):
            v = max(v, cuda.shfl_down_sync(FULL_MASK, v, d))
        return v

    @cuda.jit(device=True)
    def _leader():
        """The thread that holds a warp reduction's result."""
        return cuda.laneid == 0


@cuda.jit(device=True)
def _add(arr, f, k, v):
    """arr[f, k] += the warp's sum of v: a shuffle reduction, then one atomic add."""
    v = _warp_sum(v)
    if _leader():
        cuda.atomic.add(arr, (f, k), v)


# ---- soft rasterizer --------------------------------------------------------------------------------------------

@cuda.jit(cache=_CACHE)
def setup_faces(pos, faces, w2c, K, rgb, opac, opacity_min, near, far, min_area, grazing_cos, width, height, tile,
                theta, rect, key, argmin, ntiles):
    """One thread per face: kernel_math.setup_face -> theta, rect, key, argmin and ntiles (0 = culled)."""
    f = cuda.grid(1)
    if f < faces.shape[0]:
        xc = cuda.local.array((3, 3), np.float64)
        uv = cuda.local.array((3, 2), np.float64)
        lens = cuda.local.array(3, np.float64)
        ntiles[f] = km.setup_face(f, pos, faces, w2c, K, rgb, opac, opacity_min, near, far, min_area, grazing_cos,
                                  width, height, tile, theta, rect, key, argmin, xc, uv, lens)


@cuda.jit(device=True)
def _sat_overlap_closed(th, x0, x1, y0, y1):
    """kernel_math.sat_overlap for the closed triangle (a point on an edge is inside): the z-buffer's test."""
    for k in range(3):
        nx, ny, d = th[3 * k], th[3 * k + 1], th[3 * k + 2]
        mx = x0 if nx > 0 else x1
        my = y0 if ny > 0 else y1
        if nx * mx + ny * my + d > 0.0:
            return False
    return True


@cuda.jit(device=True)
def _tile_overlap(th, ix0, iy0, ix1, iy1, tile, tx, ty, closed):
    if closed:
        return _sat_overlap_closed(th, max(tx * tile, ix0) + 0.5, min(tx * tile + tile - 1, ix1) + 0.5,
                                   max(ty * tile, iy0) + 0.5, min(ty * tile + tile - 1, iy1) + 0.5)
    return km.tile_overlap(th, ix0, iy0, ix1, iy1, tile, tx, ty)


@cuda.jit(cache=_CACHE)
def emit_pairs(rows, rect, ntiles, offsets, depth_bits, tile, ntx, closed, keys, vals):
    """One thread per face: for every tile it overlaps (edge lines rows[f, 0:9]; open triangle, or closed for the
    z-buffer), the key (tile << 32 | depth_bits[f]) and the face id, at offsets[f] - ntiles[f] (offsets: the
    inclusive prefix sum of ntiles). Sorting the keys orders each tile's faces front to back."""
    f = cuda.grid(1)
    if f >= ntiles.shape[0] or ntiles[f] == 0:
        return
    j = offsets[f] - ntiles[f]
    ix0, iy0, ix1, iy1 = rect[f, 0], rect[f, 1], rect[f, 2], rect[f, 3]
    d = np.int64(depth_bits[f])
    th = rows[f]
    for ty in range(iy0 // tile, iy1 // tile + 1):
        for tx in range(ix0 // tile, ix1 // tile + 1):
            if _tile_overlap(th, ix0, iy0, ix1, iy1, tile, tx, ty, closed):
                keys[j] = (np.int64(ty * ntx + tx) << 32) | d
                vals[j] = f
                j += 1


@cuda.jit(device=True)
def _tile_pixel(ntx, tile, width, height):
    """This thread's pixel (one block per tile, tile^2 threads): the tile, x, y, whether it lies in the image, and
    the pixel centre x + 0.5, y + 0.5 in float32."""
    t = cuda.blockIdx.x
    tid = cuda.threadIdx.x
    ix = (t % ntx) * tile + tid % tile
    iy = (t // ntx) * tile + tid // tile
    half = np.float32(0.5)
    return t, ix, iy, ix < width and iy < height, np.float32(ix) + half, np.float32(iy) + half


@cuda.jit(device=True)
def _next_batch(done, rows, rect, tile_faces, b0, a1, sh_rows, sh_rect, sh_f):
    """The tile's faces tile_faces[b0:a1], up to BATCH of them, copied into shared memory (ids and boxes one per
    thread, then the rows of `rows` as one flat, coalesced copy); returns how many, or 0 when no thread of the block
    needs more (none is still not `done`). Every thread of the block must call it (it synchronises)."""
    if cuda.syncthreads_count(0 if done else 1) == 0:
        return 0
    n = min(BATCH, a1 - b0)
    tid = cuda.threadIdx.x
    nthr = cuda.blockDim.x
    ncol = sh_rows.shape[1]
    for i in range(tid, n, nthr):
        f = tile_faces[b0 + i]
        sh_f[i] = f
        for k in range(4):
            sh_rect[i, k] = rect[f, k]
    cuda.syncthreads()
    for e in range(tid, n * ncol, nthr):
        i = e // ncol
        k = e - i * ncol
        sh_rows[i, k] = rows[sh_f[i], k]
    cuda.syncthreads()
    return n


@cuda.jit(fastmath=True, cache=_CACHE)
def raster_forward(theta, rect, tile_faces, tile_start, width, height, tile, ntx, sigma, alpha_min, alpha_max, t_min,
                   perspective, bg, rgb, alpha, depth, normal, face_id, max_weight, evals):
    """One block per tile, one thread per pixel: composite the tile's faces front to back. Writes the images,
    face_id (first face where the accumulated weight passes 0.5, -1 if none), the per-face max weight (atomic max of
    the warp's largest) and, per pixel, the faces whose pixel box held it while it was not yet opaque."""
    sh_th = cuda.shared.array((BATCH, N_THETA), np.float32)
    sh_rect = cuda.shared.array((BATCH, 4), np.int32)
    sh_f = cuda.shared.array(BATCH, np.int32)
    t, ix, iy, inside, px, py = _tile_pixel(ntx, tile, width, height)
    sig = np.float32(sigma)
    a_min, a_max, tmin = np.float32(alpha_min), np.float32(alpha_max), np.float32(t_min)
    zero = np.float32(0.0)
    T = np.float32(1.0)
    acc_r = acc_g = acc_b = acc_d = acc_n0 = acc_n1 = acc_n2 = zero
    fid = -1
    ne = 0
    done = not inside
    a0, a1 = tile_start[t], tile_start[t + 1]
    for b0 in range(a0, a1, BATCH):
        n = _next_batch(done, theta, rect, tile_faces, b0, a1, sh_th, sh_rect, sh_f)
        if n == 0:  # no thread of the tile needs more faces
            break
        for i in range(n):
            w = zero
            if not done and sh_rect[i, 0] <= ix <= sh_rect[i, 2] and sh_rect[i, 1] <= iy <= sh_rect[i, 3]:
                ne += 1
                L0 = sh_th[i, 0] * px + (sh_th[i, 1] * py + sh_th[i, 2])
                L1 = sh_th[i, 3] * px + (sh_th[i, 4] * py + sh_th[i, 5])
                L2 = sh_th[i, 6] * px + (sh_th[i, 7] * py + sh_th[i, 8])
                phi = max(L0, max(L1, L2))
                if phi < 0.0:
                    _, _, a, _ = km.alpha_at(phi, sh_th[i, T_INVR], sh_th[i, T_OP], sig, a_max)
                    if a >= a_min:
                        _, _, _, dep, w0, w1, w2 = km.barycentric(
                            L0, L1, L2, sh_th[i, T_S], sh_th[i, T_S + 1], sh_th[i, T_S + 2], sh_th[i, T_ZI],
                            sh_th[i, T_ZI + 1], sh_th[i, T_ZI + 2], perspective)
                        w, Tn = km.composite(a, T)
                        acc_r += w * km.interpolate(w0, w1, w2, sh_th[i, T_COL], sh_th[i, T_COL + 3], sh_th[i, T_COL + 6])
                        acc_g += w * km.interpolate(w0, w1, w2, sh_th[i, T_COL + 1], sh_th[i, T_COL + 4],
                                                    sh_th[i, T_COL + 7])
                        acc_b += w * km.interpolate(w0, w1, w2, sh_th[i, T_COL + 2], sh_th[i, T_COL + 5],
                                                    sh_th[i, T_COL + 8])
                        acc_d += w * dep
                        acc_n0 += w * sh_th[i, T_NRM]
                        acc_n1 += w * sh_th[i, T_NRM + 1]
                        acc_n2 += w * sh_th[i, T_NRM + 2]
                        if fid < 0 and Tn < 0.5:
                            fid = sh_f[i]
                        T = Tn
                        if T < tmin:
                            done = True
            if _warp_any(w > zero):
                m = _warp_max(w)
                if _leader():
                    cuda.atomic.max(max_weight, sh_f[i], m)
    if inside:
        rgb[iy, ix, 0] = acc_r + T * bg[0]
        rgb[iy, ix, 1] = acc_g + T * bg[1]
        rgb[iy, ix, 2] = acc_b + T * bg[2]
        normal[iy, ix, 0] = acc_n0
        normal[iy, ix, 1] = acc_n1
        normal[iy, ix, 2] = acc_n2
        alpha[iy, ix] = np.float32(1.0) - T
        depth[iy, ix] = acc_d
        face_id[iy, ix] = fid
        evals[iy, ix] = ne


@cuda.jit(fastmath=True, cache=_CACHE)
def raster_backward(theta, rect, tile_faces, tile_start, width, height, tile, ntx, sigma, alpha_min, alpha_max, t_min,
                    perspective, rgb, alpha, depth, normal, g_rgb, g_alpha, g_depth, g_normal, g_theta):
    """One block per tile, one thread per pixel: the gradient of sum(g_rgb*rgb + g_alpha*alpha + g_depth*depth +
    g_normal*normal) w.r.t. THETA of every face the pixel composites, walking its faces front to back again
    (kernel_math.composite_backward, barycentric_backward, window_backward). Per face, the warp's sum of each THETA
    entry goes to g_theta with one atomic add."""
    sh_th = cuda.shared.array((BATCH, N_THETA), np.float32)
    sh_rect = cuda.shared.array((BATCH, 4), np.int32)
    sh_f = cuda.shared.array(BATCH, np.int32)
    t, ix, iy, inside, px, py = _tile_pixel(ntx, tile, width, height)
    sig = np.float32(sigma)
    a_min, a_max, tmin = np.float32(alpha_min), np.float32(alpha_max), np.float32(t_min)
    zero = np.float32(0.0)
    gr = gg = gb = gA = gD = gn0 = gn1 = gn2 = total = zero
    if inside:
        gr, gg, gb = g_rgb[iy, ix, 0], g_rgb[iy, ix, 1], g_rgb[iy, ix, 2]
        gA, gD = g_alpha[iy, ix], g_depth[iy, ix]
        gn0, gn1, gn2 = g_normal[iy, ix, 0], g_normal[iy, ix, 1], g_normal[iy, ix, 2]
        total = gA * alpha[iy, ix] + gD * depth[iy, ix]
        for c in range(3):
            total += g_rgb[iy, ix, c] * rgb[iy, ix, c] + g_normal[iy, ix, c] * normal[iy, ix, c]
    T = np.float32(1.0)
    prefix = zero
    done = not inside
    a0, a1 = tile_start[t], tile_start[t + 1]
    for b0 in range(a0, a1, BATCH):
        n = _next_batch(done, theta, rect, tile_faces, b0, a1, sh_th, sh_rect, sh_f)
        if n == 0:  # no thread of the tile needs more faces
            break
        for i in range(n):
            valid = False
            e0x = e0y = e0d = e1x = e1y = e1d = e2x = e2y = e2d = ginv = gs0 = gs1 = gs2 = zero
            dr0 = dg0 = db0 = dr1 = dg1 = db1 = dr2 = dg2 = db2 = gz0 = gz1 = gz2 = gm0 = gm1 = gm2 = gop = zero
            if not done and sh_rect[i, 0] <= ix <= sh_rect[i, 2] and sh_rect[i, 1] <= iy <= sh_rect[i, 3]:
                L0 = sh_th[i, 0] * px + (sh_th[i, 1] * py + sh_th[i, 2])
                L1 = sh_th[i, 3] * px + (sh_th[i, 4] * py + sh_th[i, 5])
                L2 = sh_th[i, 6] * px + (sh_th[i, 7] * py + sh_th[i, 8])
                phi = max(L0, max(L1, L2))
                if phi < 0.0:
                    inv_r, o = sh_th[i, T_INVR], sh_th[i, T_OP]
                    ratio, I, a, clamped = km.alpha_at(phi, inv_r, o, sig, a_max)
                    if a >= a_min:
                        valid = True
                        s0, s1, s2 = sh_th[i, T_S], sh_th[i, T_S + 1], sh_th[i, T_S + 2]
                        z0, z1, z2 = sh_th[i, T_ZI], sh_th[i, T_ZI + 1], sh_th[i, T_ZI + 2]
                        b0_, b1_, b2_, dep, w0, w1, w2 = km.barycentric(L0, L1, L2, s0, s1, s2, z0, z1, z2, perspective)
                        (prefix, g_a, w, gw0, gw1, gw2, dr0, dg0, db0, dr1, dg1, db1, dr2, dg2, db2, gm0, gm1,
                         gm2) = km.composite_backward(
                            T, a, dep, w0, w1, w2, sh_th[i, T_COL], sh_th[i, T_COL + 1], sh_th[i, T_COL + 2],
                            sh_th[i, T_COL + 3], sh_th[i, T_COL + 4], sh_th[i, T_COL + 5], sh_th[i, T_COL + 6],
                            sh_th[i, T_COL + 7], sh_th[i, T_COL + 8], sh_th[i, T_NRM], sh_th[i, T_NRM + 1],
                            sh_th[i, T_NRM + 2], total, prefix, gr, gg, gb, gA, gD, gn0, gn1, gn2)
                        gL0, gL1, gL2, gs0, gs1, gs2, gz0, gz1, gz2 = km.barycentric_backward(
                            gw0, gw1, gw2, w * gD, dep, b0_, b1_, b2_, z0, z1, z2, w0, w1, w2, L0, L1, L2, s0, s1, s2,
                            perspective)
                        gop, ginv, gp0, gp1, gp2 = km.window_backward(g_a, L0, L1, L2, phi, ratio, I, o, sig, inv_r,
                                                                      clamped)
                        gL0 += gp0
                        gL1 += gp1
                        gL2 += gp2
                        e0x, e0y, e0d = gL0 * px, gL0 * py, gL0
                        e1x, e1y, e1d = gL1 * px, gL1 * py, gL1
                        e2x, e2y, e2d = gL2 * px, gL2 * py, gL2
                        _, T = km.composite(a, T)
                        if T < tmin:
                            done = True
            if _warp_any(valid):
                f = sh_f[i]
                _add(g_theta, f, 0, e0x)
                _add(g_theta, f, 1, e0y)
                _add(g_theta, f, 2, e0d)
                _add(g_theta, f, 3, e1x)
                _add(g_theta, f, 4, e1y)
                _add(g_theta, f, 5, e1d)
                _add(g_theta, f, 6, e2x)
                _add(g_theta, f, 7, e2y)
                _add(g_theta, f, 8, e2d)
                _add(g_theta, f, T_INVR, ginv)
                _add(g_theta, f, T_S, gs0)
                _add(g_theta, f, T_S + 1, gs1)
                _add(g_theta, f, T_S + 2, gs2)
                _add(g_theta, f, T_COL, dr0)
                _add(g_theta, f, T_COL + 1, dg0)
                _add(g_theta, f, T_COL + 2, db0)
                _add(g_theta, f, T_COL + 3, dr1)
                _add(g_theta, f, T_COL + 4, dg1)
                _add(g_theta, f, T_COL + 5, db1)
                _add(g_theta, f, T_COL + 6, dr2)
                _add(g_theta, f, T_COL + 7, dg2)
                _add(g_theta, f, T_COL + 8, db2)
                _add(g_theta, f, T_ZI, gz0)
                _add(g_theta, f, T_ZI + 1, gz1)
                _add(g_theta, f, T_ZI + 2, gz2)
                _add(g_theta, f, T_NRM, gm0)
                _add(g_theta, f, T_NRM + 1, gm1)
                _add(g_theta, f, T_NRM + 2, gm2)
                _add(g_theta, f, T_OP, gop)


@cuda.jit(cache=_CACHE)
def setup_backward(pos, faces, w2c, K, argmin, ntiles, g_theta, g_pos, g_rgb, g_op):
    """One thread per drawn face: its THETA gradient -> its vertices' gradients (kernel_math.face_backward, float64),
    atomically added onto the shared vertices."""
    f = cuda.grid(1)
    if f >= faces.shape[0] or ntiles[f] == 0:
        return
    g = cuda.local.array(N_THETA, np.float64)
    for j in range(N_THETA):
        g[j] = g_theta[f, j]
    xc = cuda.local.array((3, 3), np.float64)
    uv = cuda.local.array((3, 2), np.float64)
    g_uv = cuda.local.array((3, 2), np.float64)
    g_xc = cuda.local.array((3, 3), np.float64)
    lens = cuda.local.array(3, np.float64)
    ex = cuda.local.array(3, np.float64)
    ey = cuda.local.array(3, np.float64)
    g_len = cuda.local.array(3, np.float64)
    gp = cuda.local.array((3, 3), np.float64)
    gc = cuda.local.array((3, 3), np.float64)
    go = cuda.local.array(3, np.float64)
    km.face_backward(g, f, pos, faces, w2c, K, argmin, xc, uv, g_uv, g_xc, lens, ex, ey, g_len, gp, gc, go)
    for k in range(3):
        v = faces[f, k]
        for c in range(3):
            cuda.atomic.add(g_pos, (v, c), np.float32(gp[k, c]))
            cuda.atomic.add(g_rgb, (v, c), np.float32(gc[k, c]))
        cuda.atomic.add(g_op, v, np.float32(go[k]))


# ---- hard (z-buffer) renderer -----------------------------------------------------------------------------------

@cuda.jit(cache=_CACHE)
def hard_setup(pos, faces, w2c, K, near, width, height, tile, uvz, box, znear, rows, rect, zkey, ntiles):
    """One thread per face: kernel_math.hard_setup_face (uvz, box, znear), then the edge functions and 1/z plane
    (rows [F,12], kernel_math.hard_lines), the box in the binning's layout (rect: ix0, iy0, ix1, iy1), the nearest
    vertex's view depth (zkey, the sort key) and the number of tiles the closed triangle touches (0 = culled)."""
    f = cuda.grid(1)
    if f >= faces.shape[0]:
        return
    ntiles[f] = 0
    if not km.hard_setup_face(f, pos, faces, w2c, K, near, width, height, uvz, box, znear):
        return
    n0x, n0y, d0, n1x, n1y, d1, n2x, n2y, d2, A, B, C = km.hard_lines(
        uvz[f, 0], uvz[f, 1], uvz[f, 2], uvz[f, 3], uvz[f, 4], uvz[f, 5], uvz[f, 6], uvz[f, 7], uvz[f, 8])
    rows[f, 0], rows[f, 1], rows[f, 2] = n0x, n0y, d0
    rows[f, 3], rows[f, 4], rows[f, 5] = n1x, n1y, d1
    rows[f, 6], rows[f, 7], rows[f, 8] = n2x, n2y, d2
    rows[f, 9], rows[f, 10], rows[f, 11] = A, B, C
    ix0, iy0, ix1, iy1 = box[f, 2], box[f, 0], box[f, 3], box[f, 1]
    rect[f, 0], rect[f, 1], rect[f, 2], rect[f, 3] = ix0, iy0, ix1, iy1
    zkey[f] = np.float32(1.0) / znear[f]
    n = 0
    th = rows[f]
    for ty in range(iy0 // tile, iy1 // tile + 1):
        for tx in range(ix0 // tile, ix1 // tile + 1):
            if _tile_overlap(th, ix0, iy0, ix1, iy1, tile, tx, ty, True):
                n += 1
    ntiles[f] = n


@cuda.jit(fastmath=True, cache=_CACHE)
def hard_pixels(rows, rect, znear, tile_faces, tile_start, width, height, tile, ntx, fid, evals):
    """One block per tile, one thread per pixel: the nearest face (largest 1/z on its plane) whose closed triangle
    holds the pixel centre, -1 if none. The tile's faces come nearest vertex first, so a pixel is done at the first
    face whose nearest vertex lies behind what it shows."""
    sh_rows = cuda.shared.array((BATCH, N_HARD), np.float32)
    sh_rect = cuda.shared.array((BATCH, 4), np.int32)
    sh_f = cuda.shared.array(BATCH, np.int32)
    t, ix, iy, inside, px, py = _tile_pixel(ntx, tile, width, height)
    best = np.float32(0.0)
    bf = -1
    ne = 0
    done = not inside
    a0, a1 = tile_start[t], tile_start[t + 1]
    for b0 in range(a0, a1, BATCH):
        n = _next_batch(done, rows, rect, tile_faces, b0, a1, sh_rows, sh_rect, sh_f)
        if n == 0:  # no thread of the tile needs more faces
            break
        for i in range(n):
            if done:
                break
            f = sh_f[i]
            if bf >= 0 and znear[f] <= best:
                done = True  # this face and every later one lie behind what the pixel shows
                break
            if sh_rect[i, 0] <= ix <= sh_rect[i, 2] and sh_rect[i, 1] <= iy <= sh_rect[i, 3]:
                ne += 1
                if (sh_rows[i, 0] * px + (sh_rows[i, 1] * py + sh_rows[i, 2]) <= 0.0
                        and sh_rows[i, 3] * px + (sh_rows[i, 4] * py + sh_rows[i, 5]) <= 0.0
                        and sh_rows[i, 6] * px + (sh_rows[i, 7] * py + sh_rows[i, 8]) <= 0.0):
                    zi = sh_rows[i, 9] * px + (sh_rows[i, 10] * py + sh_rows[i, 11])
                    if zi > best:
                        best = zi
                        bf = f
    if inside:
        fid[iy, ix] = bf
        evals[iy, ix] = ne


@cuda.jit(cache=_CACHE)
def hard_resolve(uvz, pos, faces, w2c, colors, fid, perspective, bg, rgb, depth, normal, face_id, won):
    """One thread per pixel: the winning face's interpolated vertex colour, view depth and camera-facing normal
    (kernel_math.hard_pixel, hard_face_normal); won[f] = 1 for every face that wins a pixel."""
    iy, ix = cuda.grid(2)
    if iy >= fid.shape[0] or ix >= fid.shape[1]:
        return
    f = fid[iy, ix]
    face_id[iy, ix] = f
    if f < 0:
        for c in range(3):
            rgb[iy, ix, c] = bg[c]
            normal[iy, ix, c] = 0.0
        depth[iy, ix] = 0.0
        return
    won[f] = 1.0
    u0, v0, z0 = uvz[f, 0], uvz[f, 1], uvz[f, 2]
    u1, v1, z1 = uvz[f, 3], uvz[f, 4], uvz[f, 5]
    u2, v2, z2 = uvz[f, 6], uvz[f, 7], uvz[f, 8]
    ia = 1.0 / ((u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0))
    b0, b1, b2, dep = km.hard_pixel(u0, v0, z0, u1, v1, z1, u2, v2, z2, ia, ix + 0.5, iy + 0.5, perspective)
    i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
    for c in range(3):
        rgb[iy, ix, c] = b0 * colors[i0, c] + b1 * colors[i1, c] + b2 * colors[i2, c]
    depth[iy, ix] = dep
    nx, ny, nz = km.hard_face_normal(pos, faces, f, w2c)
    normal[iy, ix, 0], normal[iy, ix, 1], normal[iy, ix, 2] = nx, ny, nz
