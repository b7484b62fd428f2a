"""The rasterizers' kernel maths, written once for the CPU and the CUDA kernels: per-face setup, tile overlap, the
window, barycentrics, compositing, the per-pixel gradient and the setup's chain rule, and the z-buffer's per-face
and per-pixel maths.

Plain Python functions on scalars and arrays (no allocation: scratch arrays come from the caller), compiled twice by
`compiled(decorator)`: numba.njit(inline="always") for the CPU kernels (kernels.py, hard.py) and
numba.cuda.jit(device=True) for the CUDA kernels (cuda_kernels.py), each compiled function calling the others'
compiled versions. The launch layers differ (a task per tile with per-row spans and no atomics on the CPU; a thread
per pixel, shared-memory batches and atomics on the GPU); what a pixel computes from a face does not.

Numba's cache does not follow a kernel into this file: a kernel that inlines these functions is recompiled only when
its own file changes. So each launch layer keeps `KERNEL_MATH_STAMP`, the stamp of this file it was last checked
against, and uses the cache only while it matches `source_stamp()`; tests/render/test_render_cuda.py fails (and names
the new stamp) when it does not.
"""
from __future__ import annotations

import hashlib
import math
import types
from pathlib import Path

import numpy as np

# THETA layout (per face, float32): edge k is L_k(p) = n_k . p + d_k (outward unit normal, < 0 inside); the window is
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


def source_stamp() -> str:
    """The first 16 hex digits of this file's SHA-256: what the launch layers' KERNEL_MATH_STAMP must equal."""
    return hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:16]


# ---- soft rasterizer: per-face setup and binning ----------------------------------------------------------------

def sat_overlap(th, x0, x1, y0, y1):
    """Does the open triangle (edge lines in th[0:9]) touch the rectangle [x0,x1]x[y0,y1] (pixel-centre range)?"""
    for k in range(3):
        nx, ny, d = th[3 * k], th[3 * k + 1], th[3 * k + 2]
        mx = x0 if nx > 0 else x1
        my = y0 if ny > 0 else y1
        if nx * mx + ny * my + d >= 0.0:
            return False
    return True


def tile_overlap(th, ix0, iy0, ix1, iy1, tile, tx, ty):
    """Does the face (edge lines th, pixel-centre box ix0..ix1 x iy0..iy1) touch the pixel centres of tile (tx, ty)
    that lie in its box?"""
    return sat_overlap(th, max(tx * tile, ix0) + 0.5, min(tx * tile + tile - 1, ix1) + 0.5,
                       max(ty * tile, iy0) + 0.5, min(ty * tile + tile - 1, iy1) + 0.5)


def count_tiles(th, ix0, iy0, ix1, iy1, tile):
    """Tiles whose pixel centres (within the face's pixel-centre bounding box) the triangle touches."""
    n = 0
    for ty in range(iy0 // tile, iy1 // tile + 1):
        for tx in range(ix0 // tile, ix1 // tile + 1):
            if tile_overlap(th, ix0, iy0, ix1, iy1, tile, tx, ty):
                n += 1
    return n


def setup_face(f, pos, faces, w2c, K, rgb, opac, opacity_min, near, far, min_area, grazing_cos, width, height, tile,
               theta, rect, key, argmin, xc, uv, lens):
    """Face f: projection, culling (near/far, degenerate, grazing), edge lines, 1/inradius, barycentric scales,
    colours, 1/z, camera-facing normal and opacity into theta[f] (float64 maths, float32 storage), the pixel-centre
    bounding box rect[f] (ix0, iy0, ix1, iy1), the sort key key[f] (centroid view depth) and the opacity arg-min
    vertex argmin[f] (-1 for the mean). Returns the number of tiles the face overlaps exactly (0 = culled or
    off-screen). Scratch: xc [3,3], uv [3,2], lens [3] float64."""
    for k in range(3):
        v = faces[f, k]
        for r in range(3):
            xc[k, r] = w2c[r, 0] * pos[v, 0] + w2c[r, 1] * pos[v, 1] + w2c[r, 2] * pos[v, 2] + w2c[r, 3]
    z0, z1, z2 = xc[0, 2], xc[1, 2], xc[2, 2]
    if min(z0, min(z1, z2)) < near or min(z0, min(z1, z2)) > far:
        return 0
    for k in range(3):
        uv[k, 0] = (K[0, 0] * xc[k, 0] + K[0, 1] * xc[k, 1]) / xc[k, 2] + K[0, 2]
        uv[k, 1] = (K[1, 0] * xc[k, 0] + K[1, 1] * xc[k, 1]) / xc[k, 2] + K[1, 2]
    # Pixel-centre bounding box first: most faces in front of a camera inside a scene are off to its sides, and
    # they need nothing more (the tile rectangle and the exact overlap count come at the end).
    umin = min(uv[0, 0], min(uv[1, 0], uv[2, 0]))
    umax = max(uv[0, 0], max(uv[1, 0], uv[2, 0]))
    vmin = min(uv[0, 1], min(uv[1, 1], uv[2, 1]))
    vmax = max(uv[0, 1], max(uv[1, 1], uv[2, 1]))
    ix0 = max(0, int(math.ceil(umin - 0.5)))
    ix1 = min(width - 1, int(math.floor(umax - 0.5)))
    iy0 = max(0, int(math.ceil(vmin - 0.5)))
    iy1 = min(height - 1, int(math.floor(vmax - 0.5)))
    if ix0 > ix1 or iy0 > iy1:
        return 0
    ax, ay, az = xc[1, 0] - xc[0, 0], xc[1, 1] - xc[0, 1], xc[1, 2] - xc[0, 2]
    bx, by, bz = xc[2, 0] - xc[0, 0], xc[2, 1] - xc[0, 1], xc[2, 2] - xc[0, 2]
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    clen = math.sqrt(cx * cx + cy * cy + cz * cz)
    if clen == 0.0:
        return 0
    cx, cy, cz = cx / clen, cy / clen, cz / clen
    if cx * xc[0, 0] + cy * xc[0, 1] + cz * xc[0, 2] > 0:
        cx, cy, cz = -cx, -cy, -cz
    mx = (xc[0, 0] + xc[1, 0] + xc[2, 0]) / 3.0
    my = (xc[0, 1] + xc[1, 1] + xc[2, 1]) / 3.0
    mz = (z0 + z1 + z2) / 3.0
    if abs(cx * mx + cy * my + cz * mz) < grazing_cos * math.sqrt(mx * mx + my * my + mz * mz):
        return 0
    area2 = (uv[1, 0] - uv[0, 0]) * (uv[2, 1] - uv[0, 1]) - (uv[1, 1] - uv[0, 1]) * (uv[2, 0] - uv[0, 0])
    aa = abs(area2)
    if aa * 0.5 < min_area or aa == 0.0:
        return 0
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
    # the tile rectangle, then the exact overlap count
    rect[f, 0], rect[f, 1], rect[f, 2], rect[f, 3] = ix0, iy0, ix1, iy1
    key[f] = mz  # centroid view depth; ties keep the face order (stable sort)
    return count_tiles(theta[f], ix0, iy0, ix1, iy1, tile)


# ---- soft rasterizer: one (pixel, face) pair --------------------------------------------------------------------

def alpha_at(phi, inv_r, o, sig, alpha_max):
    """Inside a face (phi = max_k L_k < 0): the window's ratio -phi/r and value I = ratio^sigma, and alpha =
    min(o I, alpha_max) with whether the cap applied (then alpha has no gradient)."""
    ratio = -phi * inv_r
    I = math.exp(sig * math.log(ratio))
    a = o * I
    clamped = a > alpha_max
    if clamped:
        a = alpha_max
    return ratio, I, a, clamped


def barycentric(L0, L1, L2, s0, s1, s2, z0, z1, z2, perspective):
    """Screen-space barycentrics b_k = -L_{k+1} s_k, the view depth 1 / sum_k b_k / z_k and the interpolation weights
    (b, or the perspective-correct b_k z_k / sum b z with z_k holding 1/z)."""
    b0, b1, b2 = -L1 * s0, -L2 * s1, -L0 * s2
    zinv = b0 * z0 + b1 * z1 + b2 * z2
    dep = np.float32(1.0) / zinv
    if perspective:
        w0, w1, w2 = b0 * z0 * dep, b1 * z1 * dep, b2 * z2 * dep
    else:
        w0, w1, w2 = b0, b1, b2
    return b0, b1, b2, dep, w0, w1, w2


def interpolate(w0, w1, w2, c0, c1, c2):
    """One channel of the vertex colours c0, c1, c2 at interpolation weights w0, w1, w2."""
    return w0 * c0 + w1 * c1 + w2 * c2


def composite(a, T):
    """Front-to-back compositing of alpha a in front of transmittance T: the blending weight a T and the
    transmittance behind the face."""
    return a * T, T * (np.float32(1.0) - a)


def composite_backward(T, a, dep, w0, w1, w2, cr0, cg0, cb0, cr1, cg1, cb1, cr2, cg2, cb2, nn0, nn1, nn2, total,
                       prefix, gr, gg, gb, gA, gD, gn0, gn1, gn2):
    """The compositing's gradient at one pixel for one face, its faces walked front to back.

    Loss = sum(g . outputs) at this pixel, with upstream gradients gr, gg, gb (rgb), gA (alpha), gD (depth), gn0..2
    (normal); total = that sum at the pixel (background included); prefix = the part of it from the faces before
    this one. The light still to come behind the face is total - prefix - w G, so dL/da = T G - (that) / (1 - a)
    needs no division to recover T. Returns (prefix with this face, dL/da, the weight w = a T, dL/dw_k for the three
    interpolation weights, the 9 vertex-colour gradients (vertex-major rgb), the 3 normal gradients)."""
    c_r = interpolate(w0, w1, w2, cr0, cr1, cr2)
    c_g = interpolate(w0, w1, w2, cg0, cg1, cg2)
    c_b = interpolate(w0, w1, w2, cb0, cb1, cb2)
    w = a * T
    G = gr * c_r + gg * c_g + gb * c_b + gA + gD * dep + gn0 * nn0 + gn1 * nn1 + gn2 * nn2
    pre = prefix + w * G
    g_a = T * G - (total - pre) / (np.float32(1.0) - a)
    gcr, gcg, gcb = w * gr, w * gg, w * gb
    gw0 = gcr * cr0 + gcg * cg0 + gcb * cb0
    gw1 = gcr * cr1 + gcg * cg1 + gcb * cb1
    gw2 = gcr * cr2 + gcg * cg2 + gcb * cb2
    return (pre, g_a, w, gw0, gw1, gw2, w0 * gcr, w0 * gcg, w0 * gcb, w1 * gcr, w1 * gcg, w1 * gcb, w2 * gcr,
            w2 * gcg, w2 * gcb, w * gn0, w * gn1, w * gn2)


def barycentric_backward(gw0, gw1, gw2, g_dep, dep, b0, b1, b2, z0, z1, z2, w0, w1, w2, L0, L1, L2, s0, s1, s2,
                         perspective):
    """barycentric's gradient: from dL/dw_k (the interpolation weights) and dL/d(depth) to dL/dL_k (the edge
    functions at the pixel), dL/ds_k (the barycentric scales) and dL/dz_k (z_k holding 1/z of vertex k)."""
    g_zinv = -g_dep * dep * dep
    if perspective:
        # w_k = b_k z_k / zinv  ->  d/d(b_k z_k) = gw_k / zinv, d/dzinv = -sum_k gw_k w_k / zinv
        g_zinv -= (gw0 * w0 + gw1 * w1 + gw2 * w2) * dep
        gbz0, gbz1, gbz2 = gw0 * dep, gw1 * dep, gw2 * dep
        gb0, gb1, gb2 = gbz0 * z0, gbz1 * z1, gbz2 * z2
        gz0, gz1, gz2 = gbz0 * b0 + g_zinv * b0, gbz1 * b1 + g_zinv * b1, gbz2 * b2 + g_zinv * b2
    else:
        gb0, gb1, gb2 = gw0, gw1, gw2
        gz0, gz1, gz2 = g_zinv * b0, g_zinv * b1, g_zinv * b2
    gb0 += g_zinv * z0
    gb1 += g_zinv * z1
    gb2 += g_zinv * z2
    # b0 = -L1 s0, b1 = -L2 s1, b2 = -L0 s2
    return -gb2 * s2, -gb0 * s0, -gb1 * s1, -(gb0 * L1), -(gb1 * L2), -(gb2 * L0), gz0, gz1, gz2


def window_backward(g_a, L0, L1, L2, phi, ratio, I, o, sig, inv_r, clamped):
    """alpha_at's gradient: from dL/dalpha to dL/d(opacity), dL/d(inv_r) and dL/dL_k (only the arg-max edge of
    phi = max_k L_k gets it); all zero where the alpha cap applied."""
    zero = np.float32(0.0)
    if clamped:
        return zero, zero, zero, zero, zero
    g_ratio = g_a * o * sig * I / ratio
    g_phi = -g_ratio * inv_r
    if L0 >= L1 and L0 >= L2:
        return g_a * I, -(g_ratio * phi), g_phi, zero, zero
    if L1 >= L2:
        return g_a * I, -(g_ratio * phi), zero, g_phi, zero
    return g_a * I, -(g_ratio * phi), zero, zero, g_phi


# ---- soft rasterizer: the setup's chain rule --------------------------------------------------------------------

def face_backward(g, f, pos, faces, w2c, K, argmin, xc, uv, g_uv, g_xc, lens, ex, ey, g_len, g_pos, g_rgb, g_op):
    """Face f's THETA gradient g [29] (float64) -> the gradients of its three vertices: g_pos [3,3] (world
    positions), g_rgb [3,3] (colours), g_op [3] (opacities). The exact chain rule through the edge lines, 1/inradius
    (perimeter / (2 area)), the barycentric scales, 1/z, the camera-facing normal and the projection, with the forward
    quantities recomputed in float64. Scratch (float64): xc [3,3], uv [3,2], g_uv [3,2], g_xc [3,3], lens, ex, ey,
    g_len [3]."""
    for k in range(3):
        g_len[k] = 0.0
        for c in range(2):
            g_uv[k, c] = 0.0
        for c in range(3):
            g_xc[k, c] = 0.0
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
            g_pos[k, c] = w2c[0, c] * g_xc[k, 0] + w2c[1, c] * g_xc[k, 1] + w2c[2, c] * g_xc[k, 2]
            g_rgb[k, c] = g[T_COL + 3 * k + c]
        g_op[k] = 0.0
    if argmin[f] >= 0:
        g_op[argmin[f]] = g[T_OP]
    else:
        for k in range(3):
            g_op[k] = g[T_OP] / 3.0


# ---- hard (z-buffer) renderer -----------------------------------------------------------------------------------

def hard_setup_face(f, pos, faces, w2c, K, near, width, height, uvz, box, znear):
    """Face f of the z-buffer: screen vertices and 1/z into uvz[f] (u, v, 1/z per vertex), the pixel-centre box into
    box[f] (first row, last row, first column, last column; left (1, 0, ...) when culled: a vertex nearer than `near`,
    degenerate or off-screen) and its largest 1/z (nearest vertex) into znear[f] (0 when culled). Returns whether
    the face is drawn."""
    box[f, 0], box[f, 1] = 1, 0
    znear[f] = 0.0
    ok = True
    for k in range(3):
        v = faces[f, k]
        X = w2c[0, 0] * pos[v, 0] + w2c[0, 1] * pos[v, 1] + w2c[0, 2] * pos[v, 2] + w2c[0, 3]
        Y = w2c[1, 0] * pos[v, 0] + w2c[1, 1] * pos[v, 1] + w2c[1, 2] * pos[v, 2] + w2c[1, 3]
        Z = w2c[2, 0] * pos[v, 0] + w2c[2, 1] * pos[v, 1] + w2c[2, 2] * pos[v, 2] + w2c[2, 3]
        if Z < near:
            ok = False
        zi = 1.0 / Z
        uvz[f, 3 * k] = (K[0, 0] * X + K[0, 1] * Y) * zi + K[0, 2]
        uvz[f, 3 * k + 1] = (K[1, 0] * X + K[1, 1] * Y) * zi + K[1, 2]
        uvz[f, 3 * k + 2] = zi
    if not ok:
        return False
    u0, v0, u1, v1, u2, v2 = uvz[f, 0], uvz[f, 1], uvz[f, 3], uvz[f, 4], uvz[f, 6], uvz[f, 7]
    if (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0) == 0.0:
        return False
    ix0 = max(0, int(math.ceil(min(u0, min(u1, u2)) - 0.5)))
    ix1 = min(width - 1, int(math.floor(max(u0, max(u1, u2)) - 0.5)))
    iy0 = max(0, int(math.ceil(min(v0, min(v1, v2)) - 0.5)))
    iy1 = min(height - 1, int(math.floor(max(v0, max(v1, v2)) - 0.5)))
    if ix0 > ix1 or iy0 > iy1:
        return False
    box[f, 0], box[f, 1], box[f, 2], box[f, 3] = iy0, iy1, ix0, ix1
    znear[f] = max(uvz[f, 2], max(uvz[f, 5], uvz[f, 8]))
    return True


def hard_lines(u0, v0, z0, u1, v1, z1, u2, v2, z2):
    """The z-buffer's float32 edge functions of a screen triangle (unnormalised, n_k . p + d_k <= 0 inside the
    closed triangle; only signs matter) and its screen-space plane of 1/z, 1/z(p) = A u + B v + C. Returns
    (n0x, n0y, d0, n1x, n1y, d1, n2x, n2y, d2, A, B, C)."""
    one = np.float32(1.0)
    area2 = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
    sg = one if area2 > 0 else -one
    n0x, n0y = sg * (v1 - v0), -sg * (u1 - u0)
    n1x, n1y = sg * (v2 - v1), -sg * (u2 - u1)
    n2x, n2y = sg * (v0 - v2), -sg * (u0 - u2)
    d0, d1, d2 = -(n0x * u0 + n0y * v0), -(n1x * u1 + n1y * v1), -(n2x * u2 + n2y * v2)
    ia = one / area2
    A = ((z1 - z0) * (v2 - v0) - (z2 - z0) * (v1 - v0)) * ia
    B = ((z2 - z0) * (u1 - u0) - (z1 - z0) * (u2 - u0)) * ia
    C = z0 - A * u0 - B * v0
    return n0x, n0y, d0, n1x, n1y, d1, n2x, n2y, d2, A, B, C


def hard_face_normal(pos, faces, f, w2c):
    """Face f's unit normal in the camera frame (from the world positions, rotation only), turned towards the
    camera; (0, 0, 0) for a degenerate face."""
    i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
    ax, ay, az = pos[i1, 0] - pos[i0, 0], pos[i1, 1] - pos[i0, 1], pos[i1, 2] - pos[i0, 2]
    bx, by, bz = pos[i2, 0] - pos[i0, 0], pos[i2, 1] - pos[i0, 1], pos[i2, 2] - pos[i0, 2]
    wx, wy, wz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    cx = w2c[0, 0] * wx + w2c[0, 1] * wy + w2c[0, 2] * wz
    cy = w2c[1, 0] * wx + w2c[1, 1] * wy + w2c[1, 2] * wz
    cz = w2c[2, 0] * wx + w2c[2, 1] * wy + w2c[2, 2] * wz
    X0 = w2c[0, 0] * pos[i0, 0] + w2c[0, 1] * pos[i0, 1] + w2c[0, 2] * pos[i0, 2] + w2c[0, 3]
    Y0 = w2c[1, 0] * pos[i0, 0] + w2c[1, 1] * pos[i0, 1] + w2c[1, 2] * pos[i0, 2] + w2c[1, 3]
    Z0 = w2c[2, 0] * pos[i0, 0] + w2c[2, 1] * pos[i0, 1] + w2c[2, 2] * pos[i0, 2] + w2c[2, 3]
    ln = math.sqrt(cx * cx + cy * cy + cz * cz)
    if cx * X0 + cy * Y0 + cz * Z0 > 0:
        ln = -ln
    if ln != 0.0:
        return cx / ln, cy / ln, cz / ln
    return 0.0, 0.0, 0.0


def hard_pixel(u0, v0, z0, u1, v1, z1, u2, v2, z2, ia, px, py, perspective):
    """The z-buffer's interpolation at pixel centre (px, py) of a screen triangle (ia = 1 / twice its signed area,
    z_k = 1/z of vertex k): the colour weights (screen-space barycentrics, or perspective-correct ones) and the view
    depth."""
    b0 = ((u1 - px) * (v2 - py) - (v1 - py) * (u2 - px)) * ia
    b1 = ((u2 - px) * (v0 - py) - (v2 - py) * (u0 - px)) * ia
    b2 = 1.0 - b0 - b1
    zinv = b0 * z0 + b1 * z1 + b2 * z2
    if perspective:
        b0, b1, b2 = b0 * z0 / zinv, b1 * z1 / zinv, b2 * z2 / zinv
    return b0, b1, b2, 1.0 / zinv


SHARED = ("sat_overlap", "tile_overlap", "count_tiles", "setup_face", "alpha_at", "barycentric", "interpolate",
          "composite", "composite_backward", "barycentric_backward", "window_backward", "face_backward",
          "hard_setup_face", "hard_lines", "hard_face_normal", "hard_pixel")


def compiled(decorator, name: str) -> types.ModuleType:
    """The functions of SHARED compiled with `decorator` (e.g. numba.njit(inline="always") or
    numba.cuda.jit(device=True)), as a module object named `name` (Numba resolves a module's attributes in compiled
    code): copies of them whose calls to each other reach the compiled copies."""
    namespace = dict(globals())
    module = types.ModuleType(name, f"kernel_math's functions compiled with {decorator!r}")
    for fname in SHARED:
        fn = globals()[fname]
        clone = types.FunctionType(fn.__code__, namespace, fname, fn.__defaults__, fn.__closure__)
        clone.__doc__, clone.__qualname__ = fn.__doc__, fn.__qualname__
        namespace[fname] = decorator(clone)
        setattr(module, fname, namespace[fname])
    return module
