"""Numba CPU kernels of the soft rasterizer: per-face setup, tile binning, per-tile forward and exact backward.

Stages (all compiled, parallel, no atomics):
  setup_faces      per face: projection, culling, edge lines, incentre normaliser, colours -> THETA [F,29]
  bin_faces        exact triangle/tile overlap (separating axes), per-tile lists sorted by centroid depth
  raster_forward   one task per tile: front-to-back compositing over per-row spans
  raster_backward  one task per tile: the exact gradient of the loss w.r.t. THETA per (tile, face) pair
  setup_backward   pair gradients -> per face -> per face-vertex (positions, colours, opacity), exact chain
                   rule through the edge lines, the incentre normaliser 1/r = perimeter / (2 area), the
                   barycentric scales, 1/z, the camera-facing normal and the projection
  scatter_vertices face-vertex gradients -> shared vertices (serial, so no atomics)
The per-face parameter vector THETA (float32) is the narrow boundary between the stages; its layout is below.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# THETA layout (per face): edge k is L_k(p) = n_k . p + d_k (outward unit normal, < 0 inside); the window is
# ((-max_k L_k) * inv_r) ** sigma (inv_r = 1/inradius = -1/phi(s)); barycentric b_k = -L_{k+1} * s_k with
# s_k = |edge k+1| / (2 area); per-vertex colours; 1/z per vertex; camera-facing unit normal; face opacity.
T_EDGE = 0  # 9 values: n0x n0y d0 n1x n1y d1 n2x n2y d2
T_INVR = 9
T_S = 10  # 3
T_COL = 13  # 9: c0 rgb, c1 rgb, c2 rgb
T_ZI = 22  # 3
T_NRM = 25  # 3
T_OP = 28
N_THETA = 29
SETUP_CHUNKS = 256  # parallel chunks of the per-face setup loops
SPAN_EPS_PX = 1e-3  # per-row spans are widened by this much; the exact inside test runs on every pixel anyway


@njit(cache=True, inline="always")
def _sat_overlap(th, x0, x1, y0, y1):
    """Does the open triangle (edge lines in th) touch the rectangle [x0,x1]x[y0,y1] (pixel-centre range)?"""
    for k in range(3):
        nx, ny, d = th[3 * k], th[3 * k + 1], th[3 * k + 2]
        mx = x0 if nx > 0 else x1
        my = y0 if ny > 0 else y1
        if nx * mx + ny * my + d >= 0.0:
            return False
    return True


@njit(cache=True)
def _count_tiles(th, ix0, iy0, ix1, iy1, tile):
    """Tiles whose pixel centres (within the face's pixel-centre bounding box) the triangle touches."""
    n = 0
    for ty in range(iy0 // tile, iy1 // tile + 1):
        for tx in range(ix0 // tile, ix1 // tile + 1):
            if _sat_overlap(th, max(tx * tile, ix0) + 0.5, min(tx * tile + tile - 1, ix1) + 0.5,
                            max(ty * tile, iy0) + 0.5, min(ty * tile + tile - 1, iy1) + 0.5):
                n += 1
    return n


@njit(parallel=True, cache=True, fastmath=True)
def setup_faces(pos, faces, w2c, K, rgb, opac, opacity_min, near, far, min_area, grazing_cos, width, height, tile,
                theta, rect, key, argmin, ntiles):
    """Per face: THETA, pixel-centre bounding box rect [F,4] (ix0, iy0, ix1, iy1), sort key (centroid view depth),
    opacity arg-min vertex, and the number of tiles the face overlaps exactly (0 = culled or off-screen)."""
    F = faces.shape[0]
    for ch in prange(SETUP_CHUNKS):  # per-chunk scratch arrays: no allocation per face
        xc = np.empty((3, 3))
        uv = np.empty((3, 2))
        lens = np.empty(3)
        for f in range(ch * F // SETUP_CHUNKS, (ch + 1) * F // SETUP_CHUNKS):
            ntiles[f] = 0
            for k in range(3):
                v = faces[f, k]
                for r in range(3):
                    xc[k, r] = w2c[r, 0] * pos[v, 0] + w2c[r, 1] * pos[v, 1] + w2c[r, 2] * pos[v, 2] + w2c[r, 3]
            z0, z1, z2 = xc[0, 2], xc[1, 2], xc[2, 2]
            if min(z0, min(z1, z2)) < near or min(z0, min(z1, z2)) > far:
                continue
            for k in range(3):
                uv[k, 0] = (K[0, 0] * xc[k, 0] + K[0, 1] * xc[k, 1]) / xc[k, 2] + K[0, 2]
                uv[k, 1] = (K[1, 0] * xc[k, 0] + K[1, 1] * xc[k, 1]) / xc[k, 2] + K[1, 2]
            ax, ay, az = xc[1, 0] - xc[0, 0], xc[1, 1] - xc[0, 1], xc[1, 2] - xc[0, 2]
            bx, by, bz = xc[2, 0] - xc[0, 0], xc[2, 1] - xc[0, 1], xc[2, 2] - xc[0, 2]
            cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            clen = math.sqrt(cx * cx + cy * cy + cz * cz)
            if clen == 0.0:
                continue
            cx, cy, cz = cx / clen, cy / clen, cz / clen
            if cx * xc[0, 0] + cy * xc[0, 1] + cz * xc[0, 2] > 0:
                cx, cy, cz = -cx, -cy, -cz
            mx = (xc[0, 0] + xc[1, 0] + xc[2, 0]) / 3.0
            my = (xc[0, 1] + xc[1, 1] + xc[2, 1]) / 3.0
            mz = (z0 + z1 + z2) / 3.0
            if abs(cx * mx + cy * my + cz * mz) < grazing_cos * math.sqrt(mx * mx + my * my + mz * mz):
                continue
            area2 = (uv[1, 0] - uv[0, 0]) * (uv[2, 1] - uv[0, 1]) - (uv[1, 1] - uv[0, 1]) * (uv[2, 0] - uv[0, 0])
            aa = abs(area2)
            if aa * 0.5 < min_area or aa == 0.0:
                continue
            sg = 1.0 if area2 >= 0 else -1.0
            per = 0.0
            for k in range(3):
                k1 = (k + 1) % 3
                ex, ey = uv[k1, 0] - uv[k, 0], uv[k1, 1] - uv[k, 1]
                ln = math.sqrt(ex * ex + ey * ey)
                lens[k] = ln
                per += ln
                nx, ny = sg * ey / ln, -sg * ex / ln
                theta[f, 3 * k] = nx
                theta[f, 3 * k + 1] = ny
                theta[f, 3 * k + 2] = -(nx * uv[k, 0] + ny * uv[k, 1])
            theta[f, T_INVR] = per / aa
            for k in range(3):
                theta[f, T_S + k] = lens[(k + 1) % 3] / aa
                v = faces[f, k]
                for c in range(3):
                    theta[f, T_COL + 3 * k + c] = rgb[v, c]
                theta[f, T_ZI + k] = 1.0 / xc[k, 2]
            theta[f, T_NRM] = cx
            theta[f, T_NRM + 1] = cy
            theta[f, T_NRM + 2] = cz
            o0, o1, o2 = opac[faces[f, 0]], opac[faces[f, 1]], opac[faces[f, 2]]
            if opacity_min:
                am = 0
                om = o0
                if o1 < om:
                    am, om = 1, o1
                if o2 < om:
                    am, om = 2, o2
                theta[f, T_OP] = om
                argmin[f] = am
            else:
                theta[f, T_OP] = (o0 + o1 + o2) / 3.0
                argmin[f] = -1
            # Pixel-centre bounding box -> tile rectangle, then the exact overlap count.
            umin = min(uv[0, 0], min(uv[1, 0], uv[2, 0]))
            umax = max(uv[0, 0], max(uv[1, 0], uv[2, 0]))
            vmin = min(uv[0, 1], min(uv[1, 1], uv[2, 1]))
            vmax = max(uv[0, 1], max(uv[1, 1], uv[2, 1]))
            ix0 = max(0, int(math.ceil(umin - 0.5)))
            ix1 = min(width - 1, int(math.floor(umax - 0.5)))
            iy0 = max(0, int(math.ceil(vmin - 0.5)))
            iy1 = min(height - 1, int(math.floor(vmax - 0.5)))
            if ix0 > ix1 or iy0 > iy1:
                continue
            rect[f, 0], rect[f, 1], rect[f, 2], rect[f, 3] = ix0, iy0, ix1, iy1
            ntiles[f] = _count_tiles(theta[f], ix0, iy0, ix1, iy1, tile)
            key[f] = mz  # centroid view depth; ties keep the face order (stable sort)


@njit(parallel=True, cache=True)
def bin_faces(theta, rect, ntiles, order, width, height, tile):
    """Pairs (face-major order) and per-tile lists of pair indices sorted front to back.

    order [F] lists the faces by increasing sort key (centroid depth), equal keys in face order (a stable sort):
    filling the tile lists in that order leaves each list sorted, with no per-tile sort.
    Returns face_start [F+1], pair_face [P], tile_start [NT+1], tile_pairs [P] (indices into the face-major
    pair arrays) and its inverse pos_of [P]."""
    F = ntiles.shape[0]
    ntx = (width + tile - 1) // tile
    nty = (height + tile - 1) // tile
    nt = ntx * nty
    face_start = np.zeros(F + 1, np.int64)
    for f in range(F):
        face_start[f + 1] = face_start[f] + ntiles[f]
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
                if _sat_overlap(th, max(tx * tile, ix0) + 0.5, min(tx * tile + tile - 1, ix1) + 0.5,
                                max(ty * tile, iy0) + 0.5, min(ty * tile + tile - 1, iy1) + 0.5):
                    pair_face[j] = f
                    pair_tile[j] = ty * ntx + tx
                    j += 1
    tile_start = np.zeros(nt + 1, np.int64)
    for p in range(P):
        tile_start[pair_tile[p] + 1] += 1
    for t in range(nt):
        tile_start[t + 1] += tile_start[t]
    fill = tile_start[:-1].copy()
    tile_pairs = np.empty(tile_start[nt], np.int32)
    pos_of = np.empty(P, np.int32)  # face-major pair index -> position in the tile-ordered lists
    for i in range(F):
        f = order[i]
        for p in range(face_start[f], face_start[f + 1]):
            t = pair_tile[p]
            tile_pairs[fill[t]] = p
            pos_of[p] = fill[t]
            fill[t] += 1
    return face_start, pair_face, tile_start, tile_pairs, pos_of


@njit(cache=True, inline="always")
def _span(nx, rnx, c, xlo, xhi):
    """Clip the x range [xlo, xhi] of one row to the half-plane nx * x + c < 0 (rnx = 1/nx, 0 if nx ~ 0)."""
    if rnx > 0:
        xhi = min(xhi, -c * rnx + SPAN_EPS_PX)
    elif rnx < 0:
        xlo = max(xlo, -c * rnx - SPAN_EPS_PX)
    elif c >= SPAN_EPS_PX:
        xlo = xhi + 1
    return xlo, xhi


@njit(cache=True)
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


@njit(cache=True, inline="always")
def _shrink(T, t_min, r, tw, row_lo, row_hi):
    """A pixel of tile row r just fell below t_min: move the row's active range past finished end pixels."""
    while row_lo[r] <= row_hi[r] and T[r * tw + row_lo[r]] < t_min:
        row_lo[r] += 1
    while row_hi[r] >= row_lo[r] and T[r * tw + row_hi[r]] < t_min:
        row_hi[r] -= 1


@njit(cache=True, inline="always")
def _recip(nx):
    return 1.0 / nx if abs(nx) > 1e-12 else 0.0


@njit(parallel=True, cache=True, fastmath=True)
def raster_forward(theta, rect, pair_face, tile_start, tile_pairs, width, height, tile, sigma, alpha_min, alpha_max,
                   t_min, perspective, bg, rgb, alpha, depth, normal, face_id, pair_weight, tile_evals):
    """Composite every tile front to back. Writes images, face_id (-1 = none), per-pair max weight."""
    half = np.float32(0.5)
    sig = np.float32(sigma)
    alpha_min, alpha_max, t_min = np.float32(alpha_min), np.float32(alpha_max), np.float32(t_min)
    ntx = (width + tile - 1) // tile
    nt = tile_start.shape[0] - 1
    for t in prange(nt):
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
                    ratio = -phi * inv_r
                    a = o * math.exp(sig * math.log(ratio))
                    if a < alpha_min:
                        continue
                    if a > alpha_max:
                        a = alpha_max
                    b0, b1, b2 = -L1 * s0, -L2 * s1, -L0 * s2
                    zinv = b0 * z0 + b1 * z1 + b2 * z2
                    dep = np.float32(1.0) / zinv
                    if perspective:
                        w0, w1, w2 = b0 * z0 * dep, b1 * z1 * dep, b2 * z2 * dep
                    else:
                        w0, w1, w2 = b0, b1, b2
                    w = a * Tq
                    aq = acc[q]
                    aq[0] += w * (w0 * cr0 + w1 * cr1 + w2 * cr2)
                    aq[1] += w * (w0 * cg0 + w1 * cg1 + w2 * cg2)
                    aq[2] += w * (w0 * cb0 + w1 * cb1 + w2 * cb2)
                    aq[3] += w * dep
                    aq[4] += w * nn0
                    aq[5] += w * nn1
                    aq[6] += w * nn2
                    Tn = Tq * (np.float32(1.0) - a)
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


@njit(parallel=True, cache=True)
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


@njit(parallel=True, cache=True, fastmath=True)
def raster_backward(theta, rect, pair_face, tile_start, tile_pairs, width, height, tile, sigma, alpha_min, alpha_max,
                    t_min, perspective, bg, rgb, alpha, depth, normal, g_rgb, g_alpha, g_depth, g_normal, pair_grad):
    """Gradient of sum(g_rgb*rgb + g_alpha*alpha + g_depth*depth + g_normal*normal) w.r.t. THETA, per pair.

    Walks each tile front to back again; the light still to come behind a face is the pixel total minus the
    running prefix, so no division by (1 - a) is needed to recover T. Per-pair sums live in scalars."""
    half = np.float32(0.5)
    one = np.float32(1.0)
    sig = np.float32(sigma)
    alpha_min, alpha_max, t_min = np.float32(alpha_min), np.float32(alpha_max), np.float32(t_min)
    ntx = (width + tile - 1) // tile
    nt = tile_start.shape[0] - 1
    for t in prange(nt):
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
        for j in range(lf.shape[0]):
            if active == 0:
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
                    ratio = -phi * inv_r
                    I = math.exp(sig * math.log(ratio))
                    a = o * I
                    if a < alpha_min:
                        continue
                    clamped = a > alpha_max
                    if clamped:
                        a = alpha_max
                    b0, b1, b2 = -L1 * s0, -L2 * s1, -L0 * s2
                    zinv = b0 * z0 + b1 * z1 + b2 * z2
                    dep = one / zinv
                    if perspective:
                        w0, w1, w2 = b0 * z0 * dep, b1 * z1 * dep, b2 * z2 * dep
                    else:
                        w0, w1, w2 = b0, b1, b2
                    c_r = w0 * cr0 + w1 * cr1 + w2 * cr2
                    c_g = w0 * cg0 + w1 * cg1 + w2 * cg2
                    c_b = w0 * cb0 + w1 * cb1 + w2 * cb2
                    w = a * Tq
                    gr, gg, gb = gup[q, 0], gup[q, 1], gup[q, 2]
                    gD = gup[q, 4]
                    gn0, gn1, gn2 = gup[q, 5], gup[q, 6], gup[q, 7]
                    G = gr * c_r + gg * c_g + gb * c_b + gup[q, 3] + gD * dep + gn0 * nn0 + gn1 * nn1 + gn2 * nn2
                    pre = prefix[q] + w * G
                    prefix[q] = pre
                    g_a = Tq * G - (total[q] - pre) / (one - a)
                    gcr, gcg, gcb = w * gr, w * gg, w * gb
                    gm0 += w * gn0
                    gm1 += w * gn1
                    gm2 += w * gn2
                    gr0 += w0 * gcr
                    gg0 += w0 * gcg
                    gb0_ += w0 * gcb
                    gr1 += w1 * gcr
                    gg1 += w1 * gcg
                    gb1_ += w1 * gcb
                    gr2 += w2 * gcr
                    gg2 += w2 * gcg
                    gb2_ += w2 * gcb
                    gw0 = gcr * cr0 + gcg * cg0 + gcb * cb0
                    gw1 = gcr * cr1 + gcg * cg1 + gcb * cb1
                    gw2 = gcr * cr2 + gcg * cg2 + gcb * cb2
                    g_zinv = -(w * gD) * dep * dep
                    if perspective:
                        # w_k = b_k z_k / zinv  ->  d/d(b_k z_k) = gw_k / zinv, d/dzinv = -sum_k gw_k w_k / zinv
                        g_zinv -= (gw0 * w0 + gw1 * w1 + gw2 * w2) * dep
                        gbz0, gbz1, gbz2 = gw0 * dep, gw1 * dep, gw2 * dep
                        gb0, gb1, gb2 = gbz0 * z0, gbz1 * z1, gbz2 * z2
                        gz0 += gbz0 * b0
                        gz1 += gbz1 * b1
                        gz2 += gbz2 * b2
                    else:
                        gb0, gb1, gb2 = gw0, gw1, gw2
                    gb0 += g_zinv * z0
                    gb1 += g_zinv * z1
                    gb2 += g_zinv * z2
                    gz0 += g_zinv * b0
                    gz1 += g_zinv * b1
                    gz2 += g_zinv * b2
                    # b0 = -L1 s0, b1 = -L2 s1, b2 = -L0 s2
                    gs0 -= gb0 * L1
                    gs1 -= gb1 * L2
                    gs2 -= gb2 * L0
                    gL0, gL1, gL2 = -gb2 * s2, -gb0 * s0, -gb1 * s1
                    if not clamped:
                        gop += g_a * I
                        g_ratio = g_a * o * sig * I / ratio
                        ginv -= g_ratio * phi
                        g_phi = -g_ratio * inv_r
                        if L0 >= L1 and L0 >= L2:
                            gL0 += g_phi
                        elif L1 >= L2:
                            gL1 += g_phi
                        else:
                            gL2 += g_phi
                    rP0 += gL0 * px
                    rP1 += gL1 * px
                    rP2 += gL2 * px
                    rL0 += gL0
                    rL1 += gL1
                    rL2 += gL2
                    Tn = Tq * (one - a)
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


@njit(parallel=True, cache=True, fastmath=True)
def setup_backward(pos, faces, w2c, K, argmin, pair_grad, pos_of, face_start, f0, g_pos_f, g_rgb_f, g_op_f):
    """Faces f0 .. f0 + len(g_pos_f) - 1: sum the pair gradients of THETA, then chain back through the setup to the
    face's vertices. Writes g_pos_f [n,3,3] (world positions), g_rgb_f [n,3,3] (vertex colours), g_op_f [n,3]
    (vertex opacities), row i for face f0 + i."""
    F = g_pos_f.shape[0]
    for ch in prange(SETUP_CHUNKS):  # per-chunk scratch arrays: no allocation per face
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
            for k in range(3):
                for c in range(3):
                    g_pos_f[i, k, c] = 0.0
                    g_rgb_f[i, k, c] = 0.0
                g_op_f[i, k] = 0.0
            if a_ == b_:
                continue
            g[:] = 0.0
            g_uv[:] = 0.0
            g_xc[:] = 0.0
            g_len[:] = 0.0
            for p in range(a_, b_):
                for j in range(N_THETA):
                    g[j] += pair_grad[pos_of[p], j]
            # Recompute the forward quantities in float64.
            for k in range(3):
                v = faces[f, k]
                for r in range(3):
                    xc[k, r] = w2c[r, 0] * pos[v, 0] + w2c[r, 1] * pos[v, 1] + w2c[r, 2] * pos[v, 2] + w2c[r, 3]
                uv[k, 0] = (K[0, 0] * xc[k, 0] + K[0, 1] * xc[k, 1]) / xc[k, 2] + K[0, 2]
                uv[k, 1] = (K[1, 0] * xc[k, 0] + K[1, 1] * xc[k, 1]) / xc[k, 2] + K[1, 2]
            area2 = (uv[1, 0] - uv[0, 0]) * (uv[2, 1] - uv[0, 1]) - (uv[1, 1] - uv[0, 1]) * (uv[2, 0] - uv[0, 0])
            sg = 1.0 if area2 >= 0 else -1.0
            aa = abs(area2)
            per = 0.0
            for k in range(3):
                k1 = (k + 1) % 3
                ex[k], ey[k] = uv[k1, 0] - uv[k, 0], uv[k1, 1] - uv[k, 1]
                lens[k] = math.sqrt(ex[k] * ex[k] + ey[k] * ey[k])
                per += lens[k]
            g_aa = 0.0
            # inv_r = per / aa ; s_k = len_{k+1} / aa
            g_invr = g[T_INVR]
            for k in range(3):
                g_len[k] += g_invr / aa
            g_aa -= g_invr * per / (aa * aa)
            for k in range(3):
                k1 = (k + 1) % 3
                g_len[k1] += g[T_S + k] / aa
                g_aa -= g[T_S + k] * lens[k1] / (aa * aa)
            # Edge lines: n_k = sg * (ey, -ex) / len, d_k = -n_k . uv_k
            for k in range(3):
                k1 = (k + 1) % 3
                ln = lens[k]
                nx, ny = sg * ey[k] / ln, -sg * ex[k] / ln
                gnx, gny, gd = g[3 * k], g[3 * k + 1], g[3 * k + 2]
                gnx -= gd * uv[k, 0]
                gny -= gd * uv[k, 1]
                g_uv[k, 0] -= gd * nx
                g_uv[k, 1] -= gd * ny
                # n = sg * qhat, q = (ey, -ex): g_q = (g_qhat - (g_qhat . qhat) qhat) / |q|, g_qhat = sg * g_n
                qx, qy = sg * nx, sg * ny
                gqx, gqy = sg * gnx, sg * gny
                dot = gqx * qx + gqy * qy
                gqx, gqy = (gqx - dot * qx) / ln, (gqy - dot * qy) / ln
                gex, gey = -gqy, gqx
                gex += g_len[k] * ex[k] / ln
                gey += g_len[k] * ey[k] / ln
                g_uv[k1, 0] += gex
                g_uv[k1, 1] += gey
                g_uv[k, 0] -= gex
                g_uv[k, 1] -= gey
            # |area2| = sg * ((u1-u0)(v2-v0) - (v1-v0)(u2-u0))
            g_a2 = sg * g_aa
            ax_, ay_ = uv[1, 0] - uv[0, 0], uv[1, 1] - uv[0, 1]
            bx_, by_ = uv[2, 0] - uv[0, 0], uv[2, 1] - uv[0, 1]
            g_uv[1, 0] += g_a2 * by_
            g_uv[1, 1] -= g_a2 * bx_
            g_uv[2, 0] -= g_a2 * ay_
            g_uv[2, 1] += g_a2 * ax_
            g_uv[0, 0] -= g_a2 * (by_ - ay_)
            g_uv[0, 1] -= g_a2 * (ax_ - bx_)
            # Projection u = (K00 x + K01 y)/z + K02, v = (K10 x + K11 y)/z + K12; and 1/z.
            for k in range(3):
                z = xc[k, 2]
                gu, gv = g_uv[k, 0], g_uv[k, 1]
                g_xc[k, 0] += (gu * K[0, 0] + gv * K[1, 0]) / z
                g_xc[k, 1] += (gu * K[0, 1] + gv * K[1, 1]) / z
                g_xc[k, 2] -= (gu * (uv[k, 0] - K[0, 2]) + gv * (uv[k, 1] - K[1, 2])) / z
                g_xc[k, 2] -= g[T_ZI + k] / (z * z)
            # Camera-facing unit normal: nrm = s * c / |c|, c = A x B, A = x1 - x0, B = x2 - x0.
            ax, ay, az = xc[1, 0] - xc[0, 0], xc[1, 1] - xc[0, 1], xc[1, 2] - xc[0, 2]
            bx, by, bz = xc[2, 0] - xc[0, 0], xc[2, 1] - xc[0, 1], xc[2, 2] - xc[0, 2]
            cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            clen = math.sqrt(cx * cx + cy * cy + cz * cz)
            chx, chy, chz = cx / clen, cy / clen, cz / clen
            s = -1.0 if chx * xc[0, 0] + chy * xc[0, 1] + chz * xc[0, 2] > 0 else 1.0
            gx, gy, gz = s * g[T_NRM], s * g[T_NRM + 1], s * g[T_NRM + 2]
            dot = gx * chx + gy * chy + gz * chz
            gcx, gcy, gcz = (gx - dot * chx) / clen, (gy - dot * chy) / clen, (gz - dot * chz) / clen
            # g_A = B x g_c, g_B = g_c x A
            gAx, gAy, gAz = by * gcz - bz * gcy, bz * gcx - bx * gcz, bx * gcy - by * gcx
            gBx, gBy, gBz = gcy * az - gcz * ay, gcz * ax - gcx * az, gcx * ay - gcy * ax
            g_xc[1, 0] += gAx
            g_xc[1, 1] += gAy
            g_xc[1, 2] += gAz
            g_xc[2, 0] += gBx
            g_xc[2, 1] += gBy
            g_xc[2, 2] += gBz
            g_xc[0, 0] -= gAx + gBx
            g_xc[0, 1] -= gAy + gBy
            g_xc[0, 2] -= gAz + gBz
            # World positions: x_c = R p + t  ->  g_p = R^T g_xc
            for k in range(3):
                for c in range(3):
                    g_pos_f[i, k, c] = w2c[0, c] * g_xc[k, 0] + w2c[1, c] * g_xc[k, 1] + w2c[2, c] * g_xc[k, 2]
                    g_rgb_f[i, k, c] = g[T_COL + 3 * k + c]
            if argmin[f] >= 0:
                g_op_f[i, argmin[f]] = g[T_OP]
            else:
                for k in range(3):
                    g_op_f[i, k] = g[T_OP] / 3.0


@njit(cache=True)
def scatter_vertices(faces, f0, g_pos_f, g_rgb_f, g_op_f, g_pos, g_rgb, g_op):
    """Accumulate the face-vertex gradients of faces f0.. on the shared vertices (serial: no atomics needed)."""
    for i in range(g_pos_f.shape[0]):
        for k in range(3):
            v = faces[f0 + i, k]
            for c in range(3):
                g_pos[v, c] += g_pos_f[i, k, c]
                g_rgb[v, c] += g_rgb_f[i, k, c]
            g_op[v] += g_op_f[i, k]
