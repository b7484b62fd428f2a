"""Numba CPU kernels of the soft rasterizer: per-face setup, tile binning, per-tile forward and exact backward.

Stages (all compiled, parallel, no atomics):
  setup_faces      per face: projection, culling, edge lines, incentre normaliser, colours -> THETA [F,29]
  depth_order      the shown faces by centroid depth (a parallel stable radix sort)
  bin_faces        exact triangle/tile overlap (separating axes), per-tile lists sorted by centroid depth (a parallel
                   stable counting sort of the pairs by tile, in the depth order)
  raster_forward   one task per tile: front-to-back compositing over per-row spans
  raster_backward  one task per tile: the exact gradient of the loss w.r.t. THETA per (tile, face) pair
  setup_backward   pair gradients -> per face -> per face-vertex (positions, colours, opacity), exact chain
                   rule through the edge lines, the incentre normaliser 1/r = perimeter / (2 area), the
                   barycentric scales, 1/z, the camera-facing normal and the projection
  scatter_vertices face-vertex gradients -> shared vertices (each thread owns a range of vertices: no atomics)
The per-face parameter vector THETA (float32) is the narrow boundary between the stages (layout: kernel_math.py).
What a pixel computes from a face, the per-face setup and its chain rule are kernel_math's functions, shared with
the CUDA kernels (cuda_kernels.py); this file is the CPU launch layer: tasks per tile, per-row spans, no atomics.
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from trisplat.render import kernel_math
from trisplat.render.kernel_math import N_THETA, T_COL, T_EDGE, T_INVR, T_NRM, T_OP, T_S, T_ZI  # noqa: F401 (re-exported)

KERNEL_MATH_STAMP = "f283f9c65ec7a742"  # kernel_math.source_stamp() last checked against (kernel_math docstring)
_CACHE = kernel_math.source_stamp() == KERNEL_MATH_STAMP
km = kernel_math.compiled(njit(inline="always"), "trisplat.render.kernel_math.cpu")  # inlined into the kernels below
SETUP_CHUNKS = 256  # parallel chunks of the per-face setup loops
SPAN_EPS_PX = 1e-3  # per-row spans are widened by this much; the exact inside test runs on every pixel anyway


@njit(parallel=True, cache=_CACHE, fastmath=True)
def setup_faces(pos, faces, w2c, K, rgb, opac, opacity_min, near, far, min_area, grazing_cos, width, height, tile,
                theta, rect, key, argmin, ntiles):
    """Per face (kernel_math.setup_face): THETA, pixel-centre bounding box rect [F,4] (ix0, iy0, ix1, iy1), sort key
    (centroid view depth), opacity arg-min vertex, and the number of tiles the face overlaps exactly (0 = culled or
    off-screen)."""
    F = faces.shape[0]
    stride = spread_stride(SETUP_CHUNKS)  # chunks in a spread order: the faces a view keeps cluster by index
    for kc in prange(SETUP_CHUNKS):  # per-chunk scratch arrays: no allocation per face
        ch = (kc * stride) % SETUP_CHUNKS
        xc = np.empty((3, 3))
        uv = np.empty((3, 2))
        lens = np.empty(3)
        for f in range(ch * F // SETUP_CHUNKS, (ch + 1) * F // SETUP_CHUNKS):
            ntiles[f] = km.setup_face(f, pos, faces, w2c, K, rgb, opac, opacity_min, near, far, min_area, grazing_cos,
                                      width, height, tile, theta, rect, key, argmin, xc, uv, lens)


VISIBLE_MARGIN_PX = 1.0  # vertices_in_view widens the image by this much on each side: a superset whatever the rounding


@njit(parallel=True, cache=_CACHE)
def vertices_in_view(pos, faces, w2c, K, near, far, width, height, mask):
    """mask[v] = 1 for the vertices of every face that setup_faces could keep (no vertex nearer than `near`, not
    all beyond `far`, its projected bounding box meeting the image widened by VISIBLE_MARGIN_PX), 0 elsewhere
    (mask [V] uint8). A superset of the vertices whose colours and opacities the render reads: the others get no
    gradient from it. One pass projects the vertices, one over the faces marks theirs (two faces marking one vertex
    write the same value)."""
    V, F = pos.shape[0], faces.shape[0]
    uvz = np.empty((V, 3))
    for v in prange(V):
        mask[v] = 0
        x = w2c[0, 0] * pos[v, 0] + w2c[0, 1] * pos[v, 1] + w2c[0, 2] * pos[v, 2] + w2c[0, 3]
        y = w2c[1, 0] * pos[v, 0] + w2c[1, 1] * pos[v, 1] + w2c[1, 2] * pos[v, 2] + w2c[1, 3]
        z = w2c[2, 0] * pos[v, 0] + w2c[2, 1] * pos[v, 1] + w2c[2, 2] * pos[v, 2] + w2c[2, 3]
        uvz[v, 2] = z
        if z > 0.0:
            uvz[v, 0] = (K[0, 0] * x + K[0, 1] * y) / z + K[0, 2]
            uvz[v, 1] = (K[1, 0] * x + K[1, 1] * y) / z + K[1, 2]
        else:
            uvz[v, 0] = uvz[v, 1] = 0.0
    lo_u, hi_u = -VISIBLE_MARGIN_PX, width + VISIBLE_MARGIN_PX
    lo_v, hi_v = -VISIBLE_MARGIN_PX, height + VISIBLE_MARGIN_PX
    for f in prange(F):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        zmin = min(uvz[a, 2], min(uvz[b, 2], uvz[c, 2]))
        if zmin < near or zmin > far:
            continue
        if max(uvz[a, 0], max(uvz[b, 0], uvz[c, 0])) < lo_u or min(uvz[a, 0], min(uvz[b, 0], uvz[c, 0])) > hi_u:
            continue
        if max(uvz[a, 1], max(uvz[b, 1], uvz[c, 1])) < lo_v or min(uvz[a, 1], min(uvz[b, 1], uvz[c, 1])) > hi_v:
            continue
        mask[a] = 1
        mask[b] = 1
        mask[c] = 1


BLOCKS_PER_THREAD = 4  # blocks of the parallel scans, counting sorts and radix passes, per numba thread (the
# results depend on neither the blocks nor the threads; fewer blocks, less serial work between the passes)
MAX_BLOCKS = 256


def _blocks() -> int:
    return min(MAX_BLOCKS, BLOCKS_PER_THREAD * numba.get_num_threads())


RADIX_BITS = 11  # digit of the depth sort: 3 passes over 32-bit keys
RADIX_BINS = 1 << RADIX_BITS


@njit(parallel=True, cache=_CACHE)
def _exclusive_scan(counts, out, B):
    """out[0] = 0, out[i + 1] = counts[0] + ... + counts[i]: per-block sums, their serial scan (a value per block),
    then each block's own scan from its offset."""
    n = counts.shape[0]
    sums = np.zeros(B + 1, np.int64)
    for b in prange(B):
        s = 0
        for i in range(b * n // B, (b + 1) * n // B):
            s += counts[i]
        sums[b + 1] = s
    for b in range(B):
        sums[b + 1] += sums[b]
    out[0] = 0
    for b in prange(B):
        s = sums[b]
        for i in range(b * n // B, (b + 1) * n // B):
            s += counts[i]
            out[i + 1] = s


def depth_order(ntiles, key):
    """The faces with tiles (ntiles > 0) in increasing order of their sort key, equal keys in face order: exactly
    numpy's stable argsort of the keys' int32 bits (positive float32 depths order like them), in parallel.

    A parallel compaction of the shown faces, then a least-significant-digit radix sort of their keys (RADIX_BITS a
    pass; a pass whose digit is the same for every key is skipped). Each pass is a stable counting sort in blocks
    (_blocks(): a few per thread): per-block digit counts, offsets in (digit, block) order, each block scattering
    its elements in order; so the whole sort is stable and its result depends on neither the blocks nor the
    threads."""
    return _depth_order(ntiles, key, _blocks())


@njit(parallel=True, cache=_CACHE)
def _depth_order(ntiles, key, B):
    F = ntiles.shape[0]
    cnt = np.zeros(B + 1, np.int64)
    for b in prange(B):
        c = 0
        for f in range(b * F // B, (b + 1) * F // B):
            if ntiles[f] > 0:
                c += 1
        cnt[b + 1] = c
    for b in range(B):
        cnt[b + 1] += cnt[b]
    n = cnt[B]
    ids = np.empty(n, np.int32)
    keys = np.empty(n, np.uint32)
    bits = key.view(np.int32)
    for b in prange(B):
        j = cnt[b]
        for f in range(b * F // B, (b + 1) * F // B):
            if ntiles[f] > 0:
                ids[j] = f
                keys[j] = np.uint32(np.int64(bits[f]) + 2147483648)  # signed order as unsigned order
                j += 1
    ids2 = np.empty(n, np.int32)
    keys2 = np.empty(n, np.uint32)
    hist = np.zeros((B, RADIX_BINS), np.int64)
    for shift in range(0, 32, RADIX_BITS):
        for b in prange(B):
            h = hist[b]
            h[:] = 0
            for i in range(b * n // B, (b + 1) * n // B):
                h[(keys[i] >> shift) & (RADIX_BINS - 1)] += 1
        if n == 0:
            break
        d0 = (keys[0] >> shift) & (RADIX_BINS - 1)
        c0 = 0
        for b in range(B):
            c0 += hist[b, d0]
        if c0 == n:
            continue  # every key has this digit: the pass would leave the order as it is
        s = 0
        for d in range(RADIX_BINS):  # exclusive offsets in (digit, block) order
            for b in range(B):
                c = hist[b, d]
                hist[b, d] = s
                s += c
        for b in prange(B):
            h = hist[b]
            for i in range(b * n // B, (b + 1) * n // B):
                d = (keys[i] >> shift) & (RADIX_BINS - 1)
                j = h[d]
                h[d] = j + 1
                ids2[j] = ids[i]
                keys2[j] = keys[i]
        ids, ids2 = ids2, ids
        keys, keys2 = keys2, keys
    return ids


def bin_faces(theta, rect, ntiles, order, width, height, tile):
    """Pairs (face-major order) and per-tile lists of pair indices sorted front to back.

    order lists the faces with tiles (ntiles > 0; faces without may be in it too) by increasing sort key (centroid
    depth), equal keys in face order (a stable sort): filling the tile lists in that order leaves each list sorted,
    with no per-tile sort. The fill is a stable counting sort of the pairs by tile in blocks of `order` (_blocks():
    a few per thread; per-block tile counts, offsets in (tile, block) order, each block writing its pairs in
    order): every list is in `order`'s order whatever the threads. The face offsets are a parallel block scan.
    Returns face_start [F+1], pair_face [P], tile_start [NT+1], tile_pairs [P] (indices into the face-major
    pair arrays) and its inverse pos_of [P]."""
    return _bin_faces(theta, rect, ntiles, order, width, height, tile, _blocks())


@njit(parallel=True, cache=_CACHE)
def _bin_faces(theta, rect, ntiles, order, width, height, tile, B):
    F = ntiles.shape[0]
    ntx = (width + tile - 1) // tile
    nty = (height + tile - 1) // tile
    nt = ntx * nty
    face_start = np.empty(F + 1, np.int64)
    _exclusive_scan(ntiles, face_start, B)
    P = face_start[F]
    pair_face = np.empty(P, np.int32)
    pair_tile = np.empty(P, np.int32)
    for f in prange(F):
        if ntiles[f] == 0:
            continue
        j = face_start[f]
        th = theta[f]
        ix0, iy0, ix1, iy1 = rect[f, 0], rect[f, 1], rect[f, 2], rect[f, 3]
        for ty in range(iy0 // tile, iy1 // tile + 1):
            for tx in range(ix0 // tile, ix1 // tile + 1):
                if km.tile_overlap(th, ix0, iy0, ix1, iy1, tile, tx, ty):
                    pair_face[j] = f
                    pair_tile[j] = ty * ntx + tx
                    j += 1
    n = order.shape[0]
    hist = np.zeros((B, nt), np.int64)
    for b in prange(B):
        h = hist[b]
        for i in range(b * n // B, (b + 1) * n // B):
            f = order[i]
            for p in range(face_start[f], face_start[f + 1]):
                h[pair_tile[p]] += 1
    tile_start = np.empty(nt + 1, np.int64)
    s = 0
    for t in range(nt):  # exclusive offsets in (tile, block) order
        tile_start[t] = s
        for b in range(B):
            c = hist[b, t]
            hist[b, t] = s
            s += c
    tile_start[nt] = s
    tile_pairs = np.empty(s, np.int32)
    pos_of = np.empty(P, np.int32)  # face-major pair index -> position in the tile-ordered lists
    for b in prange(B):
        h = hist[b]
        for i in range(b * n // B, (b + 1) * n // B):
            f = order[i]
            for p in range(face_start[f], face_start[f + 1]):
                t = pair_tile[p]
                j = h[t]
                h[t] = j + 1
                tile_pairs[j] = p
                pos_of[p] = j
    return face_start, pair_face, tile_start, tile_pairs, pos_of


@njit(cache=_CACHE, inline="always")
def _span(nx, rnx, c, xlo, xhi):
    """Clip the x range [xlo, xhi] of one row to the half-plane nx * x + c < 0 (rnx = 1/nx, 0 if nx ~ 0)."""
    if rnx > 0:
        xhi = min(xhi, -c * rnx + SPAN_EPS_PX)
    elif rnx < 0:
        xlo = max(xlo, -c * rnx - SPAN_EPS_PX)
    elif c >= SPAN_EPS_PX:
        xlo = xhi + 1
    return xlo, xhi


@njit(cache=_CACHE)
def _gather_tile(theta, rect, pair_face, tile_pairs, a, b):
    """Copy the THETA rows, pixel boxes and face ids of one tile's pairs into contiguous local arrays (the
    independent loads overlap; the tile loop then reads memory in order instead of chasing face indices)."""
    n = b - a
    loc = np.empty((n, N_THETA), np.float32)
    lrect = np.empty((n, 4), np.int32)
    lf = np.empty(n, np.int64)
    for j in range(n):
        f = pair_face[tile_pairs[a + j]]
        lf[j] = f
        for k in range(N_THETA):
            loc[j, k] = theta[f, k]
        for k in range(4):
            lrect[j, k] = rect[f, k]
    return loc, lrect, lf


@njit(cache=_CACHE, inline="always")
def _shrink(T, t_min, r, tw, row_lo, row_hi):
    """A pixel of tile row r just fell below t_min: move the row's active range past finished end pixels."""
    while row_lo[r] <= row_hi[r] and T[r * tw + row_lo[r]] < t_min:
        row_lo[r] += 1
    while row_hi[r] >= row_lo[r] and T[r * tw + row_hi[r]] < t_min:
        row_hi[r] -= 1


@njit(cache=_CACHE, inline="always")
def _recip(nx):
    return 1.0 / nx if abs(nx) > 1e-12 else 0.0


@njit(cache=_CACHE)
def spread_stride(nt):
    """The step of a spread order over nt work items (tiles, chunks of faces): item (k * stride) mod nt at
    iteration k, with stride near 0.618 nt and coprime to it, so each thread's contiguous block of iterations
    (numba's parallel loops split them statically on the OpenMP layer; its chunk-size setting does not make them
    dynamic) is spread evenly over the items. In row order, the bottom half of a photo of a room (floor,
    furniture) held 58-68% of a bonsai step's pixel-face work early in training, and its thread set the pace; the
    faces a view keeps cluster by index the same way. Every item is still visited once and writes only its own
    outputs: the results do not depend on the order."""
    if nt <= 2:
        return 1
    s = int(nt * 0.6180339887) | 1
    while True:
        a, b = s, nt
        while b:
            a, b = b, a % b
        if a == 1:
            return s
        s += 1


@njit(parallel=True, cache=_CACHE, fastmath=True)
def raster_forward(theta, rect, pair_face, tile_start, tile_pairs, width, height, tile, sigma, alpha_min, alpha_max,
                   t_min, perspective, bg, rgb, alpha, depth, normal, face_id, pair_weight, tile_evals):
    """Composite every tile front to back. Writes images, face_id (-1 = none), per-pair max weight."""
    half = np.float32(0.5)
    sig = np.float32(sigma)
    alpha_min, alpha_max, t_min = np.float32(alpha_min), np.float32(alpha_max), np.float32(t_min)
    ntx = (width + tile - 1) // tile
    nt = tile_start.shape[0] - 1
    stride = spread_stride(nt)
    for kt in prange(nt):
        t = (kt * stride) % nt
        tx, ty = t % ntx, t // ntx
        x0, y0 = tx * tile, ty * tile
        x1, y1 = min(x0 + tile, width), min(y0 + tile, height)
        tw, th_ = x1 - x0, y1 - y0
        npx = tw * th_
        T = np.ones(npx, np.float32)
        acc = np.zeros((npx, 7), np.float32)  # rgb, depth, normal
        fid = np.full(npx, -1, np.int64)
        row_lo = np.zeros(th_, np.int64)  # per tile row, the first and last pixel still above transmittance_min
        row_hi = np.full(th_, tw - 1, np.int64)
        active = npx
        evals = 0
        ta = tile_start[t]
        loc, lrect, lf = _gather_tile(theta, rect, pair_face, tile_pairs, ta, tile_start[t + 1])
        for j in range(lf.shape[0]):
            if active == 0:
                break
            f = lf[j]
            th = loc[j]
            inv_r, o = th[T_INVR], th[T_OP]
            s0, s1, s2 = th[T_S], th[T_S + 1], th[T_S + 2]
            z0, z1, z2 = th[T_ZI], th[T_ZI + 1], th[T_ZI + 2]
            cr0, cg0, cb0 = th[T_COL], th[T_COL + 1], th[T_COL + 2]
            cr1, cg1, cb1 = th[T_COL + 3], th[T_COL + 4], th[T_COL + 5]
            cr2, cg2, cb2 = th[T_COL + 6], th[T_COL + 7], th[T_COL + 8]
            nn0, nn1, nn2 = th[T_NRM], th[T_NRM + 1], th[T_NRM + 2]
            maxw = np.float32(0.0)
            n0x, n0y, d0, n1x, n1y, d1, n2x, n2y, d2 = th[0], th[1], th[2], th[3], th[4], th[5], th[6], th[7], th[8]
            r0, r1, r2 = _recip(n0x), _recip(n1x), _recip(n2x)
            xa, xb = max(x0, lrect[j, 0]), min(x1 - 1, lrect[j, 2])
            for iy in range(max(y0, lrect[j, 1]), min(y1 - 1, lrect[j, 3]) + 1):
                r = iy - y0
                if row_lo[r] > row_hi[r]:
                    continue
                py = np.float32(iy) + half
                c0, c1, c2 = n0y * py + d0, n1y * py + d1, n2y * py + d2
                xlo, xhi = xa + 0.5, xb + 0.5
                xlo, xhi = _span(n0x, r0, c0, xlo, xhi)
                xlo, xhi = _span(n1x, r1, c1, xlo, xhi)
                xlo, xhi = _span(n2x, r2, c2, xlo, xhi)
                if xlo > xhi:
                    continue
                ixa = max(max(xa, x0 + row_lo[r]), int(math.ceil(xlo - 0.5)))
                ixb = min(min(xb, x0 + row_hi[r]), int(math.floor(xhi - 0.5)))
                for ix in range(ixa, ixb + 1):
                    q = (iy - y0) * tw + (ix - x0)
                    Tq = T[q]
                    if Tq < t_min:
                        continue
                    evals += 1
                    px = np.float32(ix) + half
                    L0 = n0x * px + c0
                    L1 = n1x * px + c1
                    L2 = n2x * px + c2
                    phi = max(L0, max(L1, L2))
                    if phi >= 0.0:
                        continue
                    _, _, a, _ = km.alpha_at(phi, inv_r, o, sig, alpha_max)
                    if a < alpha_min:
                        continue
                    _, _, _, dep, w0, w1, w2 = km.barycentric(L0, L1, L2, s0, s1, s2, z0, z1, z2, perspective)
                    w, Tn = km.composite(a, Tq)
                    aq = acc[q]
                    aq[0] += w * km.interpolate(w0, w1, w2, cr0, cr1, cr2)
                    aq[1] += w * km.interpolate(w0, w1, w2, cg0, cg1, cg2)
                    aq[2] += w * km.interpolate(w0, w1, w2, cb0, cb1, cb2)
                    aq[3] += w * dep
                    aq[4] += w * nn0
                    aq[5] += w * nn1
                    aq[6] += w * nn2
                    T[q] = Tn
                    if w > maxw:
                        maxw = w
                    if fid[q] < 0 and Tn < 0.5:
                        fid[q] = f
                    if Tn < t_min:
                        active -= 1
                        _shrink(T, t_min, r, tw, row_lo, row_hi)
            pair_weight[ta + j] = maxw
        tile_evals[t] = evals
        for q in range(npx):
            iy, ix = y0 + q // tw, x0 + q % tw
            for c in range(3):
                rgb[iy, ix, c] = acc[q, c] + T[q] * bg[c]
                normal[iy, ix, c] = acc[q, 4 + c]
            alpha[iy, ix] = 1.0 - T[q]
            depth[iy, ix] = acc[q, 3]
            face_id[iy, ix] = fid[q]


@njit(parallel=True, cache=_CACHE)
def reduce_max_weight(pair_weight, face_start, pos_of):
    """Per-face maximum of the per-pair weights (stored in tile order; pos_of maps face-major -> tile order)."""
    F = face_start.shape[0] - 1
    out = np.zeros(F, np.float32)
    for f in prange(F):
        m = np.float32(0.0)
        for p in range(face_start[f], face_start[f + 1]):
            m = max(m, pair_weight[pos_of[p]])
        out[f] = m
    return out


@njit(parallel=True, cache=_CACHE, fastmath=True)
def raster_backward(theta, rect, pair_face, tile_start, tile_pairs, width, height, tile, sigma, alpha_min, alpha_max,
                    t_min, perspective, bg, rgb, alpha, depth, normal, g_rgb, g_alpha, g_depth, g_normal, pair_grad):
    """Gradient of sum(g_rgb*rgb + g_alpha*alpha + g_depth*depth + g_normal*normal) w.r.t. THETA, per pair.

    Walks each tile front to back again; the light still to come behind a face is the pixel total minus the
    running prefix, so no division by (1 - a) is needed to recover T. Per-pair sums live in scalars. Every row of
    pair_grad [P,N_THETA] is written (zeros behind a saturated tile): it needs no zero fill."""
    half = np.float32(0.5)
    sig = np.float32(sigma)
    alpha_min, alpha_max, t_min = np.float32(alpha_min), np.float32(alpha_max), np.float32(t_min)
    ntx = (width + tile - 1) // tile
    nt = tile_start.shape[0] - 1
    stride = spread_stride(nt)
    for kt in prange(nt):
        t = (kt * stride) % nt
        tx, ty = t % ntx, t // ntx
        x0, y0 = tx * tile, ty * tile
        x1, y1 = min(x0 + tile, width), min(y0 + tile, height)
        tw, th_ = x1 - x0, y1 - y0
        npx = tw * th_
        T = np.ones(npx, np.float32)
        prefix = np.zeros(npx, np.float32)
        total = np.empty(npx, np.float32)
        gup = np.empty((npx, 8), np.float32)  # dC rgb, dA, dD, dN
        for q in range(npx):
            iy, ix = y0 + q // tw, x0 + q % tw
            s = g_alpha[iy, ix] * alpha[iy, ix] + g_depth[iy, ix] * depth[iy, ix]
            for c in range(3):
                s += g_rgb[iy, ix, c] * rgb[iy, ix, c] + g_normal[iy, ix, c] * normal[iy, ix, c]
                gup[q, c] = g_rgb[iy, ix, c]
                gup[q, 5 + c] = g_normal[iy, ix, c]
            gup[q, 3] = g_alpha[iy, ix]
            gup[q, 4] = g_depth[iy, ix]
            total[q] = s
        active = npx
        row_lo = np.zeros(th_, np.int64)
        row_hi = np.full(th_, tw - 1, np.int64)
        ta = tile_start[t]
        loc, lrect, lf = _gather_tile(theta, rect, pair_face, tile_pairs, ta, tile_start[t + 1])
        n_tile = lf.shape[0]
        for j in range(n_tile):
            if active == 0:
                # every pixel saturated: the faces behind get no gradient (pair_grad is not zero-filled beforehand)
                for jj in range(j, n_tile):
                    for k in range(N_THETA):
                        pair_grad[ta + jj, k] = 0.0
                break
            th = loc[j]
            inv_r, o = th[T_INVR], th[T_OP]
            s0, s1, s2 = th[T_S], th[T_S + 1], th[T_S + 2]
            z0, z1, z2 = th[T_ZI], th[T_ZI + 1], th[T_ZI + 2]
            cr0, cg0, cb0 = th[T_COL], th[T_COL + 1], th[T_COL + 2]
            cr1, cg1, cb1 = th[T_COL + 3], th[T_COL + 4], th[T_COL + 5]
            cr2, cg2, cb2 = th[T_COL + 6], th[T_COL + 7], th[T_COL + 8]
            nn0, nn1, nn2 = th[T_NRM], th[T_NRM + 1], th[T_NRM + 2]
            n0x, n0y, d0, n1x, n1y, d1, n2x, n2y, d2 = th[0], th[1], th[2], th[3], th[4], th[5], th[6], th[7], th[8]
            r0, r1, r2 = _recip(n0x), _recip(n1x), _recip(n2x)
            # Per-pair gradient sums (float32 scalars, kept in registers).
            zero = np.float32(0.0)
            e0x = e0y = e0d = e1x = e1y = e1d = e2x = e2y = e2d = zero
            ginv = gs0 = gs1 = gs2 = zero
            gr0 = gg0 = gb0_ = gr1 = gg1 = gb1_ = gr2 = gg2 = gb2_ = zero
            gz0 = gz1 = gz2 = gm0 = gm1 = gm2 = gop = zero
            xa, xb = max(x0, lrect[j, 0]), min(x1 - 1, lrect[j, 2])
            for iy in range(max(y0, lrect[j, 1]), min(y1 - 1, lrect[j, 3]) + 1):
                r = iy - y0
                if row_lo[r] > row_hi[r]:
                    continue
                py = np.float32(iy) + half
                c0, c1, c2 = n0y * py + d0, n1y * py + d1, n2y * py + d2
                xlo, xhi = xa + 0.5, xb + 0.5
                xlo, xhi = _span(n0x, r0, c0, xlo, xhi)
                xlo, xhi = _span(n1x, r1, c1, xlo, xhi)
                xlo, xhi = _span(n2x, r2, c2, xlo, xhi)
                if xlo > xhi:
                    continue
                ixa = max(max(xa, x0 + row_lo[r]), int(math.ceil(xlo - 0.5)))
                ixb = min(min(xb, x0 + row_hi[r]), int(math.floor(xhi - 0.5)))
                rL0 = rL1 = rL2 = zero  # row sums of dL_k (times px, and plain)
                rP0 = rP1 = rP2 = zero
                for ix in range(ixa, ixb + 1):
                    q = (iy - y0) * tw + (ix - x0)
                    Tq = T[q]
                    if Tq < t_min:
                        continue
                    px = np.float32(ix) + half
                    L0 = n0x * px + c0
                    L1 = n1x * px + c1
                    L2 = n2x * px + c2
                    phi = max(L0, max(L1, L2))
                    if phi >= 0.0:
                        continue
                    ratio, I, a, clamped = km.alpha_at(phi, inv_r, o, sig, alpha_max)
                    if a < alpha_min:
                        continue
                    b0, b1, b2, dep, w0, w1, w2 = km.barycentric(L0, L1, L2, s0, s1, s2, z0, z1, z2, perspective)
                    gD = gup[q, 4]
                    (pre, g_a, w, gw0, gw1, gw2, dr0, dg0, db0, dr1, dg1, db1, dr2, dg2, db2, dm0, dm1,
                     dm2) = km.composite_backward(Tq, a, dep, w0, w1, w2, cr0, cg0, cb0, cr1, cg1, cb1, cr2, cg2, cb2,
                                                  nn0, nn1, nn2, total[q], prefix[q], gup[q, 0], gup[q, 1], gup[q, 2],
                                                  gup[q, 3], gD, gup[q, 5], gup[q, 6], gup[q, 7])
                    prefix[q] = pre
                    gr0 += dr0
                    gg0 += dg0
                    gb0_ += db0
                    gr1 += dr1
                    gg1 += dg1
                    gb1_ += db1
                    gr2 += dr2
                    gg2 += dg2
                    gb2_ += db2
                    gm0 += dm0
                    gm1 += dm1
                    gm2 += dm2
                    gL0, gL1, gL2, ds0, ds1, ds2, dz0, dz1, dz2 = km.barycentric_backward(
                        gw0, gw1, gw2, w * gD, dep, b0, b1, b2, z0, z1, z2, w0, w1, w2, L0, L1, L2, s0, s1, s2,
                        perspective)
                    gs0 += ds0
                    gs1 += ds1
                    gs2 += ds2
                    gz0 += dz0
                    gz1 += dz1
                    gz2 += dz2
                    dop, dinv, gp0, gp1, gp2 = km.window_backward(g_a, L0, L1, L2, phi, ratio, I, o, sig, inv_r,
                                                                  clamped)
                    gop += dop
                    ginv += dinv
                    gL0 += gp0
                    gL1 += gp1
                    gL2 += gp2
                    rP0 += gL0 * px
                    rP1 += gL1 * px
                    rP2 += gL2 * px
                    rL0 += gL0
                    rL1 += gL1
                    rL2 += gL2
                    _, Tn = km.composite(a, Tq)
                    T[q] = Tn
                    if Tn < t_min:
                        active -= 1
                        _shrink(T, t_min, r, tw, row_lo, row_hi)
                e0x += rP0
                e1x += rP1
                e2x += rP2
                e0y += rL0 * py
                e1y += rL1 * py
                e2y += rL2 * py
                e0d += rL0
                e1d += rL1
                e2d += rL2
            out = pair_grad[ta + j]
            out[0], out[1], out[2], out[3], out[4], out[5], out[6], out[7], out[8] = (
                e0x, e0y, e0d, e1x, e1y, e1d, e2x, e2y, e2d)
            out[T_INVR] = ginv
            out[T_S], out[T_S + 1], out[T_S + 2] = gs0, gs1, gs2
            out[T_COL], out[T_COL + 1], out[T_COL + 2] = gr0, gg0, gb0_
            out[T_COL + 3], out[T_COL + 4], out[T_COL + 5] = gr1, gg1, gb1_
            out[T_COL + 6], out[T_COL + 7], out[T_COL + 8] = gr2, gg2, gb2_
            out[T_ZI], out[T_ZI + 1], out[T_ZI + 2] = gz0, gz1, gz2
            out[T_NRM], out[T_NRM + 1], out[T_NRM + 2] = gm0, gm1, gm2
            out[T_OP] = gop


@njit(parallel=True, cache=_CACHE, fastmath=True)
def setup_backward(pos, faces, w2c, K, argmin, pair_grad, pos_of, face_start, f0, g_pos_f, g_rgb_f, g_op_f):
    """Faces f0 .. f0 + len(g_pos_f) - 1: sum the pair gradients of THETA, then chain back through the setup to the
    face's vertices (kernel_math.face_backward). Writes g_pos_f [n,3,3] (world positions), g_rgb_f [n,3,3] (vertex
    colours), g_op_f [n,3] (vertex opacities), row i for face f0 + i, for the faces with pairs (face_start[f] <
    face_start[f + 1]) only: the others have no gradient, and scatter_vertices given face_start skips them."""
    F = g_pos_f.shape[0]
    stride = spread_stride(SETUP_CHUNKS)  # chunks in a spread order: the faces a view keeps cluster by index
    for kc in prange(SETUP_CHUNKS):  # per-chunk scratch arrays: no allocation per face
        ch = (kc * stride) % SETUP_CHUNKS
        g = np.zeros(N_THETA)
        xc = np.empty((3, 3))
        uv = np.empty((3, 2))
        g_uv = np.zeros((3, 2))
        g_xc = np.zeros((3, 3))
        lens = np.empty(3)
        ex = np.empty(3)
        ey = np.empty(3)
        g_len = np.zeros(3)
        for i in range(ch * F // SETUP_CHUNKS, (ch + 1) * F // SETUP_CHUNKS):
            f = f0 + i
            a_, b_ = face_start[f], face_start[f + 1]
            if a_ == b_:  # not shown: no gradient, and its rows are left as they are (scatter_vertices skips it)
                continue
            g[:] = 0.0
            for p in range(a_, b_):
                for j in range(N_THETA):
                    g[j] += pair_grad[pos_of[p], j]
            km.face_backward(g, f, pos, faces, w2c, K, argmin, xc, uv, g_uv, g_xc, lens, ex, ey, g_len, g_pos_f[i],
                             g_rgb_f[i], g_op_f[i])


SCATTER_SERIAL_BELOW = 20_000  # faces: fewer are scattered in one serial pass (the private copies cost more)


@njit(parallel=True, cache=_CACHE)
def _scatter_vertices(faces, f0, g_pos_f, g_rgb_f, g_op_f, g_pos, g_rgb, g_op, T, face_start):
    """Accumulate the face-vertex gradients of faces f0.. on the shared vertices. No atomics, no copies: with T
    threads, thread t reads every face corner and adds those whose vertex lies in its t-th of the vertex range (each
    vertex's sum keeps the serial order of its corners: the result is the serial pass's, bit for bit)."""
    n = g_pos_f.shape[0]
    V = g_pos.shape[0]
    skip = face_start.shape[0] > 0
    for t in prange(T):
        lo, hi = t * V // T, (t + 1) * V // T
        for i in range(n):
            if skip and face_start[f0 + i] == face_start[f0 + i + 1]:
                continue
            for k in range(3):
                v = faces[f0 + i, k]
                if v < lo or v >= hi:
                    continue
                for c in range(3):
                    g_pos[v, c] += g_pos_f[i, k, c]
                    g_rgb[v, c] += g_rgb_f[i, k, c]
                g_op[v] += g_op_f[i, k]


_EVERY_FACE = np.empty(0, np.int64)


def scatter_vertices(faces, f0, g_pos_f, g_rgb_f, g_op_f, g_pos, g_rgb, g_op, face_start=None):
    """_scatter_vertices on numba's threads (one below SCATTER_SERIAL_BELOW faces). face_start (bin_faces'): the
    faces without pairs are skipped (setup_backward leaves their rows unwritten); None: every face is added."""
    T = 1 if len(g_pos_f) < SCATTER_SERIAL_BELOW else numba.get_num_threads()
    _scatter_vertices(faces, f0, g_pos_f, g_rgb_f, g_op_f, g_pos, g_rgb, g_op, T,
                      _EVERY_FACE if face_start is None else face_start)
