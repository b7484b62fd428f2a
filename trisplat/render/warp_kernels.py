# ruff: noqa: UP018 - Warp treats a variable assigned a bare literal as a constant: int(0) / float(0.0) declare
# the local variables that loops and branches modify.
"""NVIDIA Warp kernels of the soft and hard rasterizers: one source, compiled for CUDA or for Warp's CPU device.

The GPU design of gsplat / 3DGS, with the maths of the Numba kernels (kernels.py, same THETA layout):
  setup_faces        one thread per face: projection, culling, edge lines, incentre normaliser, colours -> THETA
                     [F,29], pixel-centre box, centroid depth, and the exact number of tiles the face overlaps
  emit_pairs         one thread per face: a (tile, depth rank) int64 key and the face id per overlapped tile
                     (the keys are then sorted on the device: per-tile face lists, front to back)
  tile_ranges        one thread per sorted pair: where each tile's list starts and ends
  raster_forward     one thread per pixel (threads of a tile adjacent): front-to-back compositing over its tile's
                     list, early stop at T < transmittance_min; remembers where it stopped and its final T
  raster_backward    one thread per pixel: the same list in reverse from where the forward stopped, T recovered by
                     division by (1 - a); per-face THETA gradients accumulated with atomics
  setup_backward     one thread per face: THETA gradient -> face-vertex gradients (exact chain rule through the
                     edge lines, 1/inradius, barycentric scales, 1/z, the camera-facing normal and the
                     projection), atomically added to the shared vertices
  hard_setup / hard_pixels / hard_resolve   the opaque z-buffer renderer on the same binning (nearest face per
                     pixel centre; a tile's faces sorted by nearest-vertex depth, so a pixel stops early)
As in the Numba kernels, the per-face setup and its backward run in float64 (few operations per face) and the
per-pixel work in float32; the hard mode is float32 throughout.
"""
from __future__ import annotations

import warp as wp

from trisplat.render.kernels import N_THETA, T_COL, T_INVR, T_NRM, T_OP, T_S, T_ZI

if wp.config.log_level < wp.LOG_WARNING:  # no greeting or per-module load lines from the library
    wp.config.log_level = wp.LOG_WARNING
wp.set_module_options({"enable_backward": False})  # gradients are written by hand below (about half the build time)

# Re-exported as Warp constants so the kernels can index THETA by name.
_T_INVR = wp.constant(T_INVR)
_T_S = wp.constant(T_S)
_T_COL = wp.constant(T_COL)
_T_ZI = wp.constant(T_ZI)
_T_NRM = wp.constant(T_NRM)
_T_OP = wp.constant(T_OP)
_N_THETA = wp.constant(N_THETA)
mat32 = wp.types.matrix(shape=(3, 2), dtype=wp.float32)  # three screen points, one per row
mat32d = wp.types.matrix(shape=(3, 2), dtype=wp.float64)


@wp.func
def to_cam(w2c: wp.array2d(dtype=wp.float32), pos: wp.array2d(dtype=wp.float32), v: int):
    """Camera-frame position of vertex v (x_cam = R x + t)."""
    x = pos[v, 0]
    y = pos[v, 1]
    z = pos[v, 2]
    return wp.vec3(
        w2c[0, 0] * x + w2c[0, 1] * y + w2c[0, 2] * z + w2c[0, 3],
        w2c[1, 0] * x + w2c[1, 1] * y + w2c[1, 2] * z + w2c[1, 3],
        w2c[2, 0] * x + w2c[2, 1] * y + w2c[2, 2] * z + w2c[2, 3],
    )


@wp.func
def project(K: wp.array2d(dtype=wp.float32), c: wp.vec3):
    return wp.vec2((K[0, 0] * c[0] + K[0, 1] * c[1]) / c[2] + K[0, 2], (K[1, 0] * c[0] + K[1, 1] * c[1]) / c[2] + K[1, 2])


@wp.func
def sat_overlap(theta: wp.array2d(dtype=wp.float32), f: int, x0: float, x1: float, y0: float, y1: float,
                closed: int):
    """Does the triangle (edge lines n_k . p + d_k < 0 inside, THETA rows 0..8) touch the rectangle
    [x0,x1]x[y0,y1]? Open triangle (closed=0: a point on an edge is outside) or closed (closed=1)."""
    ok = int(1)
    for k in range(3):
        nx = theta[f, 3 * k]
        ny = theta[f, 3 * k + 1]
        d = theta[f, 3 * k + 2]
        mx = x1
        if nx > 0.0:
            mx = x0
        my = y1
        if ny > 0.0:
            my = y0
        m = nx * mx + ny * my + d
        if closed == 0:
            if m >= 0.0:
                ok = 0
        else:
            if m > 0.0:
                ok = 0
    return ok


@wp.func
def tile_overlap(theta: wp.array2d(dtype=wp.float32), rect: wp.array2d(dtype=wp.int32), f: int, tile: int, tx: int,
                 ty: int, closed: int):
    """Does face f touch the pixel centres of tile (tx, ty) that lie in its pixel-centre box?"""
    xa = float(wp.max(tx * tile, rect[f, 0])) + 0.5
    xb = float(wp.min(tx * tile + tile - 1, rect[f, 2])) + 0.5
    ya = float(wp.max(ty * tile, rect[f, 1])) + 0.5
    yb = float(wp.min(ty * tile + tile - 1, rect[f, 3])) + 0.5
    return sat_overlap(theta, f, xa, xb, ya, yb, closed)


@wp.func
def count_tiles(theta: wp.array2d(dtype=wp.float32), rect: wp.array2d(dtype=wp.int32), f: int, tile: int, closed: int):
    """Number of tiles whose pixel centres (within the face's pixel-centre box) the triangle touches."""
    n = int(0)
    for ty in range(rect[f, 1] // tile, rect[f, 3] // tile + 1):
        for tx in range(rect[f, 0] // tile, rect[f, 2] // tile + 1):
            n += tile_overlap(theta, rect, f, tile, tx, ty, closed)
    return n


@wp.func
def pixel_box(u: wp.vec3, v: wp.vec3, width: int, height: int):
    """Pixel-centre bounding box (ix0, iy0, ix1, iy1) of a screen triangle, clipped to the image."""
    ix0 = wp.max(0, int(wp.ceil(wp.min(u[0], wp.min(u[1], u[2])) - 0.5)))
    ix1 = wp.min(width - 1, int(wp.floor(wp.max(u[0], wp.max(u[1], u[2])) - 0.5)))
    iy0 = wp.max(0, int(wp.ceil(wp.min(v[0], wp.min(v[1], v[2])) - 0.5)))
    iy1 = wp.min(height - 1, int(wp.floor(wp.max(v[0], wp.max(v[1], v[2])) - 0.5)))
    return wp.vec4i(ix0, iy0, ix1, iy1)


@wp.func
def to_cam64(w2c: wp.array2d(dtype=wp.float64), pos: wp.array2d(dtype=wp.float32), v: int):
    """Camera-frame position of vertex v in float64 (x_cam = R x + t)."""
    x = wp.float64(pos[v, 0])
    y = wp.float64(pos[v, 1])
    z = wp.float64(pos[v, 2])
    return wp.vec3d(
        w2c[0, 0] * x + w2c[0, 1] * y + w2c[0, 2] * z + w2c[0, 3],
        w2c[1, 0] * x + w2c[1, 1] * y + w2c[1, 2] * z + w2c[1, 3],
        w2c[2, 0] * x + w2c[2, 1] * y + w2c[2, 2] * z + w2c[2, 3],
    )


@wp.func
def project64(K: wp.array2d(dtype=wp.float64), c: wp.vec3d):
    return wp.vec2d((K[0, 0] * c[0] + K[0, 1] * c[1]) / c[2] + K[0, 2], (K[1, 0] * c[0] + K[1, 1] * c[1]) / c[2] + K[1, 2])


@wp.kernel
def setup_faces(pos: wp.array2d(dtype=wp.float32), faces: wp.array2d(dtype=wp.int32), w2c: wp.array2d(dtype=wp.float64),
                K: wp.array2d(dtype=wp.float64), rgb: wp.array2d(dtype=wp.float32), opac: wp.array(dtype=wp.float32),
                opacity_min: int, near: wp.float64, far: wp.float64, min_area: wp.float64, grazing_cos: wp.float64,
                width: int, height: int, tile: int, theta: wp.array2d(dtype=wp.float32), rect: wp.array2d(dtype=wp.int32),
                depth: wp.array(dtype=wp.float32), argmin: wp.array(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32)):
    """Per face: THETA, pixel-centre box rect [F,4] (ix0, iy0, ix1, iy1), centroid view depth (the sort key),
    opacity arg-min vertex (-1 in mean mode) and the number of tiles overlapped exactly (0 = culled/off-screen).
    Computed in float64 and stored in float32, as the Numba setup (edge offsets near the far side of a large image
    would otherwise carry ~1e-5 px of rounding, which moves pixels across the alpha_min threshold at sigma < 1)."""
    f = wp.tid()
    ntiles[f] = 0
    depth[f] = 0.0
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    c0 = to_cam64(w2c, pos, faces[f, 0])
    c1 = to_cam64(w2c, pos, faces[f, 1])
    c2 = to_cam64(w2c, pos, faces[f, 2])
    zmin = wp.min(c0[2], wp.min(c1[2], c2[2]))
    if zmin < near or zmin > far:
        return
    p0 = project64(K, c0)
    p1 = project64(K, c1)
    p2 = project64(K, c2)
    cr = wp.cross(c1 - c0, c2 - c0)
    clen = wp.length(cr)
    if clen == zero:
        return
    nrm = cr / clen
    if wp.dot(nrm, c0) > zero:
        nrm = -nrm
    cen = (c0 + c1 + c2) / wp.float64(3.0)
    if wp.abs(wp.dot(nrm, cen)) < grazing_cos * wp.length(cen):
        return
    area2 = (p1[0] - p0[0]) * (p2[1] - p0[1]) - (p1[1] - p0[1]) * (p2[0] - p0[0])
    aa = wp.abs(area2)
    if aa * wp.float64(0.5) < min_area or aa == zero:
        return
    sg = one
    if area2 < zero:
        sg = -one
    uv = mat32d(p0[0], p0[1], p1[0], p1[1], p2[0], p2[1])
    lens = wp.vec3d(zero)
    per = zero
    for k in range(3):
        k1 = (k + 1) % 3
        ex = uv[k1, 0] - uv[k, 0]
        ey = uv[k1, 1] - uv[k, 1]
        ln = wp.sqrt(ex * ex + ey * ey)
        lens[k] = ln
        per += ln
        nx = sg * ey / ln
        ny = -sg * ex / ln
        theta[f, 3 * k] = wp.float32(nx)
        theta[f, 3 * k + 1] = wp.float32(ny)
        theta[f, 3 * k + 2] = wp.float32(-(nx * uv[k, 0] + ny * uv[k, 1]))
    theta[f, _T_INVR] = wp.float32(per / aa)
    zs = wp.vec3d(c0[2], c1[2], c2[2])
    for k in range(3):
        theta[f, _T_S + k] = wp.float32(lens[(k + 1) % 3] / aa)
        v = faces[f, k]
        for c in range(3):
            theta[f, _T_COL + 3 * k + c] = rgb[v, c]
        theta[f, _T_ZI + k] = wp.float32(one / zs[k])
    for c in range(3):
        theta[f, _T_NRM + c] = wp.float32(nrm[c])
    o0 = opac[faces[f, 0]]
    o1 = opac[faces[f, 1]]
    o2 = opac[faces[f, 2]]
    if opacity_min == 1:
        am = int(0)
        om = o0
        if o1 < om:
            am = 1
            om = o1
        if o2 < om:
            am = 2
            om = o2
        theta[f, _T_OP] = om
        argmin[f] = am
    else:
        theta[f, _T_OP] = (o0 + o1 + o2) / 3.0
        argmin[f] = -1
    half = wp.float64(0.5)
    ix0 = wp.max(0, int(wp.ceil(wp.min(p0[0], wp.min(p1[0], p2[0])) - half)))
    ix1 = wp.min(width - 1, int(wp.floor(wp.max(p0[0], wp.max(p1[0], p2[0])) - half)))
    iy0 = wp.max(0, int(wp.ceil(wp.min(p0[1], wp.min(p1[1], p2[1])) - half)))
    iy1 = wp.min(height - 1, int(wp.floor(wp.max(p0[1], wp.max(p1[1], p2[1])) - half)))
    if ix0 > ix1 or iy0 > iy1:
        return
    rect[f, 0] = ix0
    rect[f, 1] = iy0
    rect[f, 2] = ix1
    rect[f, 3] = iy1
    ntiles[f] = count_tiles(theta, rect, f, tile, 0)
    depth[f] = wp.float32(cen[2])


@wp.kernel
def invert_order(order: wp.array(dtype=wp.int32), rank: wp.array(dtype=wp.int32)):
    """rank[order[i]] = i: each face's position in the front-to-back order."""
    i = wp.tid()
    rank[order[i]] = i


@wp.kernel
def emit_pairs(theta: wp.array2d(dtype=wp.float32), rect: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32),
               offsets: wp.array(dtype=wp.int32), rank: wp.array(dtype=wp.int32), tile: int, ntx: int, closed: int,
               keys: wp.array(dtype=wp.int64), vals: wp.array(dtype=wp.int32)):
    """One (tile << 32 | depth rank) key and the face id per overlapped tile; offsets = inclusive scan of ntiles."""
    f = wp.tid()
    n = ntiles[f]
    if n == 0:
        return
    j = offsets[f] - n
    r = wp.int64(rank[f])
    for ty in range(rect[f, 1] // tile, rect[f, 3] // tile + 1):
        for tx in range(rect[f, 0] // tile, rect[f, 2] // tile + 1):
            if tile_overlap(theta, rect, f, tile, tx, ty, closed) == 1:
                keys[j] = (wp.int64(ty * ntx + tx) << wp.int64(32)) | r
                vals[j] = f
                j += 1


@wp.kernel
def tile_ranges(keys: wp.array(dtype=wp.int64), npairs: int, tile_start: wp.array(dtype=wp.int32),
                tile_end: wp.array(dtype=wp.int32)):
    """Each tile's [start, end) in the sorted pair list (tiles without pairs keep 0, 0)."""
    i = wp.tid()
    t = wp.int32(keys[i] >> wp.int64(32))
    if i == 0:
        tile_start[t] = 0
    else:
        tp = wp.int32(keys[i - 1] >> wp.int64(32))
        if tp != t:
            tile_start[t] = i
            tile_end[tp] = i
    if i == npairs - 1:
        tile_end[t] = npairs


@wp.func
def pixel_of(tid: int, tile: int, ntx: int):
    """Thread -> (tile, x, y): the tile*tile threads of one tile are consecutive (one CUDA block per 16x16 tile)."""
    per = tile * tile
    t = tid // per
    loc = tid - t * per
    return wp.vec3i(t, (t % ntx) * tile + loc % tile, (t // ntx) * tile + loc // tile)


@wp.kernel
def raster_forward(theta: wp.array2d(dtype=wp.float32), rect: wp.array2d(dtype=wp.int32), vals: wp.array(dtype=wp.int32),
                   tile_start: wp.array(dtype=wp.int32), tile_end: wp.array(dtype=wp.int32), width: int, height: int,
                   tile: int, ntx: int, sigma: float, alpha_min: float, alpha_max: float, t_min: float, perspective: int,
                   bg: wp.array(dtype=wp.float32), rgb: wp.array3d(dtype=wp.float32),
                   alpha: wp.array2d(dtype=wp.float32), depth: wp.array2d(dtype=wp.float32),
                   normal: wp.array3d(dtype=wp.float32), face_id: wp.array2d(dtype=wp.int64),
                   max_weight: wp.array(dtype=wp.float32), t_final: wp.array2d(dtype=wp.float32),
                   last: wp.array2d(dtype=wp.int32), evals: wp.array2d(dtype=wp.int32)):
    """One pixel: composite its tile's faces front to back; writes the images, face_id (first face where the
    accumulated weight passes 0.5, -1 if none), the per-face max weight (atomic max), the final transmittance and
    `last` (one past the last list entry the pixel used) for the backward pass."""
    pt = pixel_of(wp.tid(), tile, ntx)
    t = pt[0]
    ix = pt[1]
    iy = pt[2]
    if ix >= width or iy >= height:
        return
    px = float(ix) + 0.5
    py = float(iy) + 0.5
    T = float(1.0)
    acc = wp.vec3(0.0)
    accn = wp.vec3(0.0)
    accd = float(0.0)
    fid = int(-1)
    a_ = tile_start[t]
    stop = a_
    ne = int(0)
    for j in range(a_, tile_end[t]):
        f = vals[j]
        if ix < rect[f, 0] or ix > rect[f, 2] or iy < rect[f, 1] or iy > rect[f, 3]:
            continue
        ne += 1
        L0 = theta[f, 0] * px + theta[f, 1] * py + theta[f, 2]
        L1 = theta[f, 3] * px + theta[f, 4] * py + theta[f, 5]
        L2 = theta[f, 6] * px + theta[f, 7] * py + theta[f, 8]
        phi = wp.max(L0, wp.max(L1, L2))
        if phi >= 0.0:
            continue
        ratio = -phi * theta[f, _T_INVR]
        a = theta[f, _T_OP] * wp.exp(sigma * wp.log(ratio))
        if a < alpha_min:
            continue
        a = wp.min(a, alpha_max)
        b0 = -L1 * theta[f, _T_S]
        b1 = -L2 * theta[f, _T_S + 1]
        b2 = -L0 * theta[f, _T_S + 2]
        z0 = theta[f, _T_ZI]
        z1 = theta[f, _T_ZI + 1]
        z2 = theta[f, _T_ZI + 2]
        dep = 1.0 / (b0 * z0 + b1 * z1 + b2 * z2)
        w0 = b0
        w1 = b1
        w2 = b2
        if perspective == 1:
            w0 = b0 * z0 * dep
            w1 = b1 * z1 * dep
            w2 = b2 * z2 * dep
        w = a * T
        col = wp.vec3(
            w0 * theta[f, _T_COL] + w1 * theta[f, _T_COL + 3] + w2 * theta[f, _T_COL + 6],
            w0 * theta[f, _T_COL + 1] + w1 * theta[f, _T_COL + 4] + w2 * theta[f, _T_COL + 7],
            w0 * theta[f, _T_COL + 2] + w1 * theta[f, _T_COL + 5] + w2 * theta[f, _T_COL + 8],
        )
        acc += w * col
        accd += w * dep
        accn += w * wp.vec3(theta[f, _T_NRM], theta[f, _T_NRM + 1], theta[f, _T_NRM + 2])
        wp.atomic_max(max_weight, f, w)
        Tn = T * (1.0 - a)
        if fid < 0 and Tn < 0.5:
            fid = f
        T = Tn
        stop = j + 1
        if T < t_min:
            break
    for c in range(3):
        rgb[iy, ix, c] = acc[c] + T * bg[c]
        normal[iy, ix, c] = accn[c]
    alpha[iy, ix] = 1.0 - T
    depth[iy, ix] = accd
    face_id[iy, ix] = wp.int64(fid)
    t_final[iy, ix] = T
    last[iy, ix] = stop
    evals[iy, ix] = ne


@wp.kernel
def raster_backward(theta: wp.array2d(dtype=wp.float32), rect: wp.array2d(dtype=wp.int32), vals: wp.array(dtype=wp.int32),
                    tile_start: wp.array(dtype=wp.int32), width: int, height: int, tile: int, ntx: int, sigma: float,
                    alpha_min: float, alpha_max: float, perspective: int, bg: wp.array(dtype=wp.float32),
                    t_final: wp.array2d(dtype=wp.float32), last: wp.array2d(dtype=wp.int32),
                    g_rgb: wp.array3d(dtype=wp.float32), g_alpha: wp.array2d(dtype=wp.float32),
                    g_depth: wp.array2d(dtype=wp.float32), g_normal: wp.array3d(dtype=wp.float32),
                    grad_theta: wp.array2d(dtype=wp.float32)):
    """One pixel: gradient of sum(g_rgb*rgb + g_alpha*alpha + g_depth*depth + g_normal*normal) w.r.t. THETA of
    every face it composited, walking its list back to front from where the forward stopped. S = the light still to
    come behind the current face (starts with the background's share T_final * g_rgb . bg); T before a face is
    T after it / (1 - a). Per-face sums go to grad_theta with atomic adds."""
    pt = pixel_of(wp.tid(), tile, ntx)
    t = pt[0]
    ix = pt[1]
    iy = pt[2]
    if ix >= width or iy >= height:
        return
    px = float(ix) + 0.5
    py = float(iy) + 0.5
    gr = g_rgb[iy, ix, 0]
    gg = g_rgb[iy, ix, 1]
    gb = g_rgb[iy, ix, 2]
    gA = g_alpha[iy, ix]
    gD = g_depth[iy, ix]
    gn = wp.vec3(g_normal[iy, ix, 0], g_normal[iy, ix, 1], g_normal[iy, ix, 2])
    T = t_final[iy, ix]
    S = T * (gr * bg[0] + gg * bg[1] + gb * bg[2])
    a_ = tile_start[t]
    for jj in range(last[iy, ix] - a_):
        j = last[iy, ix] - 1 - jj
        f = vals[j]
        if ix < rect[f, 0] or ix > rect[f, 2] or iy < rect[f, 1] or iy > rect[f, 3]:
            continue
        L0 = theta[f, 0] * px + theta[f, 1] * py + theta[f, 2]
        L1 = theta[f, 3] * px + theta[f, 4] * py + theta[f, 5]
        L2 = theta[f, 6] * px + theta[f, 7] * py + theta[f, 8]
        phi = wp.max(L0, wp.max(L1, L2))
        if phi >= 0.0:
            continue
        inv_r = theta[f, _T_INVR]
        o = theta[f, _T_OP]
        ratio = -phi * inv_r
        I = wp.exp(sigma * wp.log(ratio))
        a = o * I
        if a < alpha_min:
            continue
        clamped = int(0)
        if a > alpha_max:
            a = alpha_max
            clamped = 1
        T = T / (1.0 - a)  # the transmittance in front of this face
        s0 = theta[f, _T_S]
        s1 = theta[f, _T_S + 1]
        s2 = theta[f, _T_S + 2]
        z0 = theta[f, _T_ZI]
        z1 = theta[f, _T_ZI + 1]
        z2 = theta[f, _T_ZI + 2]
        b0 = -L1 * s0
        b1 = -L2 * s1
        b2 = -L0 * s2
        dep = 1.0 / (b0 * z0 + b1 * z1 + b2 * z2)
        w0 = b0
        w1 = b1
        w2 = b2
        if perspective == 1:
            w0 = b0 * z0 * dep
            w1 = b1 * z1 * dep
            w2 = b2 * z2 * dep
        col0 = wp.vec3(theta[f, _T_COL], theta[f, _T_COL + 1], theta[f, _T_COL + 2])
        col1 = wp.vec3(theta[f, _T_COL + 3], theta[f, _T_COL + 4], theta[f, _T_COL + 5])
        col2 = wp.vec3(theta[f, _T_COL + 6], theta[f, _T_COL + 7], theta[f, _T_COL + 8])
        nn = wp.vec3(theta[f, _T_NRM], theta[f, _T_NRM + 1], theta[f, _T_NRM + 2])
        c = w0 * col0 + w1 * col1 + w2 * col2
        w = a * T
        gc = wp.vec3(gr, gg, gb)
        G = wp.dot(gc, c) + gA + gD * dep + wp.dot(gn, nn)
        g_a = T * G - S / (1.0 - a)
        S += w * G
        gcw = w * gc
        gm = w * gn
        gw0 = wp.dot(gcw, col0)
        gw1 = wp.dot(gcw, col1)
        gw2 = wp.dot(gcw, col2)
        g_zinv = -(w * gD) * dep * dep
        gz0 = float(0.0)
        gz1 = float(0.0)
        gz2 = float(0.0)
        gb0 = gw0
        gb1 = gw1
        gb2 = gw2
        if perspective == 1:
            g_zinv -= (gw0 * w0 + gw1 * w1 + gw2 * w2) * dep
            gb0 = gw0 * dep * z0
            gb1 = gw1 * dep * z1
            gb2 = gw2 * dep * z2
            gz0 = gw0 * dep * b0
            gz1 = gw1 * dep * b1
            gz2 = gw2 * dep * b2
        gb0 += g_zinv * z0
        gb1 += g_zinv * z1
        gb2 += g_zinv * z2
        gz0 += g_zinv * b0
        gz1 += g_zinv * b1
        gz2 += g_zinv * b2
        gL0 = -gb2 * s2
        gL1 = -gb0 * s0
        gL2 = -gb1 * s1
        if clamped == 0:
            wp.atomic_add(grad_theta, f, _T_OP, g_a * I)
            g_ratio = g_a * o * sigma * I / ratio
            wp.atomic_add(grad_theta, f, _T_INVR, -g_ratio * phi)
            g_phi = -g_ratio * inv_r
            if L0 >= L1 and L0 >= L2:
                gL0 += g_phi
            elif L1 >= L2:
                gL1 += g_phi
            else:
                gL2 += g_phi
        wp.atomic_add(grad_theta, f, 0, gL0 * px)
        wp.atomic_add(grad_theta, f, 1, gL0 * py)
        wp.atomic_add(grad_theta, f, 2, gL0)
        wp.atomic_add(grad_theta, f, 3, gL1 * px)
        wp.atomic_add(grad_theta, f, 4, gL1 * py)
        wp.atomic_add(grad_theta, f, 5, gL1)
        wp.atomic_add(grad_theta, f, 6, gL2 * px)
        wp.atomic_add(grad_theta, f, 7, gL2 * py)
        wp.atomic_add(grad_theta, f, 8, gL2)
        wp.atomic_add(grad_theta, f, _T_S, -gb0 * L1)
        wp.atomic_add(grad_theta, f, _T_S + 1, -gb1 * L2)
        wp.atomic_add(grad_theta, f, _T_S + 2, -gb2 * L0)
        for k in range(3):
            wp.atomic_add(grad_theta, f, _T_COL + k, w0 * gcw[k])
            wp.atomic_add(grad_theta, f, _T_COL + 3 + k, w1 * gcw[k])
            wp.atomic_add(grad_theta, f, _T_COL + 6 + k, w2 * gcw[k])
            wp.atomic_add(grad_theta, f, _T_NRM + k, gm[k])
        wp.atomic_add(grad_theta, f, _T_ZI, gz0)
        wp.atomic_add(grad_theta, f, _T_ZI + 1, gz1)
        wp.atomic_add(grad_theta, f, _T_ZI + 2, gz2)


@wp.kernel
def setup_backward(pos: wp.array2d(dtype=wp.float32), faces: wp.array2d(dtype=wp.int32),
                   w2c: wp.array2d(dtype=wp.float64), K: wp.array2d(dtype=wp.float64), argmin: wp.array(dtype=wp.int32),
                   ntiles: wp.array(dtype=wp.int32), gt: wp.array2d(dtype=wp.float32), g_pos: wp.array2d(dtype=wp.float32),
                   g_rgb: wp.array2d(dtype=wp.float32), g_op: wp.array(dtype=wp.float32)):
    """One face: its THETA gradient gt -> world positions, vertex colours and vertex opacities (atomic adds onto the
    shared vertices). The forward quantities are recomputed in float64, as in the Numba kernel."""
    f = wp.tid()
    if ntiles[f] == 0:
        return
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    c0 = to_cam64(w2c, pos, faces[f, 0])
    c1 = to_cam64(w2c, pos, faces[f, 1])
    c2 = to_cam64(w2c, pos, faces[f, 2])
    xc = wp.mat33d(c0[0], c0[1], c0[2], c1[0], c1[1], c1[2], c2[0], c2[1], c2[2])
    p0 = project64(K, c0)
    p1 = project64(K, c1)
    p2 = project64(K, c2)
    uv = mat32d(p0[0], p0[1], p1[0], p1[1], p2[0], p2[1])
    area2 = (p1[0] - p0[0]) * (p2[1] - p0[1]) - (p1[1] - p0[1]) * (p2[0] - p0[0])
    sg = one
    if area2 < zero:
        sg = -one
    aa = wp.abs(area2)
    ex = wp.vec3d(zero)
    ey = wp.vec3d(zero)
    lens = wp.vec3d(zero)
    per = zero
    for k in range(3):
        k1 = (k + 1) % 3
        ex[k] = uv[k1, 0] - uv[k, 0]
        ey[k] = uv[k1, 1] - uv[k, 1]
        lens[k] = wp.sqrt(ex[k] * ex[k] + ey[k] * ey[k])
        per += lens[k]
    g_len = wp.vec3d(zero)
    g_aa = zero
    g_invr = wp.float64(gt[f, _T_INVR])
    for k in range(3):  # inv_r = per / aa
        g_len[k] += g_invr / aa
    g_aa -= g_invr * per / (aa * aa)
    for k in range(3):  # s_k = len_{k+1} / aa
        k1 = (k + 1) % 3
        gs = wp.float64(gt[f, _T_S + k])
        g_len[k1] += gs / aa
        g_aa -= gs * lens[k1] / (aa * aa)
    g_uv = mat32d(zero)
    for k in range(3):  # edge lines: n_k = sg * (ey, -ex) / len, d_k = -n_k . uv_k
        k1 = (k + 1) % 3
        ln = lens[k]
        nx = sg * ey[k] / ln
        ny = -sg * ex[k] / ln
        gd = wp.float64(gt[f, 3 * k + 2])
        gnx = wp.float64(gt[f, 3 * k]) - gd * uv[k, 0]
        gny = wp.float64(gt[f, 3 * k + 1]) - gd * uv[k, 1]
        g_uv[k, 0] -= gd * nx
        g_uv[k, 1] -= gd * ny
        qx = sg * nx
        qy = sg * ny
        gqx = sg * gnx
        gqy = sg * gny
        dot = gqx * qx + gqy * qy
        gqx2 = (gqx - dot * qx) / ln
        gqy2 = (gqy - dot * qy) / ln
        gex = -gqy2 + g_len[k] * ex[k] / ln
        gey = gqx2 + g_len[k] * ey[k] / ln
        g_uv[k1, 0] += gex
        g_uv[k1, 1] += gey
        g_uv[k, 0] -= gex
        g_uv[k, 1] -= gey
    g_a2 = sg * g_aa  # |area2| = sg * ((u1-u0)(v2-v0) - (v1-v0)(u2-u0))
    ax_ = uv[1, 0] - uv[0, 0]
    ay_ = uv[1, 1] - uv[0, 1]
    bx_ = uv[2, 0] - uv[0, 0]
    by_ = uv[2, 1] - uv[0, 1]
    g_uv[1, 0] += g_a2 * by_
    g_uv[1, 1] -= g_a2 * bx_
    g_uv[2, 0] -= g_a2 * ay_
    g_uv[2, 1] += g_a2 * ax_
    g_uv[0, 0] -= g_a2 * (by_ - ay_)
    g_uv[0, 1] -= g_a2 * (ax_ - bx_)
    g_xc = wp.mat33d(zero)
    for k in range(3):  # projection and 1/z
        z = xc[k, 2]
        gu = g_uv[k, 0]
        gv = g_uv[k, 1]
        g_xc[k, 0] += (gu * K[0, 0] + gv * K[1, 0]) / z
        g_xc[k, 1] += (gu * K[0, 1] + gv * K[1, 1]) / z
        g_xc[k, 2] -= (gu * (uv[k, 0] - K[0, 2]) + gv * (uv[k, 1] - K[1, 2])) / z
        g_xc[k, 2] -= wp.float64(gt[f, _T_ZI + k]) / (z * z)
    # Camera-facing unit normal: nrm = s * c / |c|, c = A x B, A = x1 - x0, B = x2 - x0.
    A = c1 - c0
    B = c2 - c0
    cr = wp.cross(A, B)
    clen = wp.length(cr)
    ch = cr / clen
    s = one
    if wp.dot(ch, c0) > zero:
        s = -one
    gN = s * wp.vec3d(wp.float64(gt[f, _T_NRM]), wp.float64(gt[f, _T_NRM + 1]), wp.float64(gt[f, _T_NRM + 2]))
    gcv = (gN - wp.dot(gN, ch) * ch) / clen
    gA = wp.cross(B, gcv)
    gB = wp.cross(gcv, A)
    for c in range(3):
        g_xc[1, c] += gA[c]
        g_xc[2, c] += gB[c]
        g_xc[0, c] -= gA[c] + gB[c]
    am = argmin[f]
    for k in range(3):  # world positions: x_c = R p + t  ->  g_p = R^T g_xc
        v = faces[f, k]
        for c in range(3):
            wp.atomic_add(g_pos, v, c, wp.float32(w2c[0, c] * g_xc[k, 0] + w2c[1, c] * g_xc[k, 1] + w2c[2, c] * g_xc[k, 2]))
            wp.atomic_add(g_rgb, v, c, gt[f, _T_COL + 3 * k + c])
        if am < 0:
            wp.atomic_add(g_op, v, gt[f, _T_OP] / 3.0)
        elif am == k:
            wp.atomic_add(g_op, v, gt[f, _T_OP])


# ---- hard (opaque z-buffer) mode ----------------------------------------------------------------------------------
# Per-face rows of `hth` [F,12]: the unnormalised edge lines (9, same slots as THETA, n_k . p + d_k <= 0 inside),
# then 1/z of the three vertices (9..11). A tile's faces are ordered by the depth of their nearest vertex, so a pixel
# stops at the first face that cannot be nearer than what it already shows.
N_HARD = wp.constant(12)


@wp.kernel
def hard_setup(pos: wp.array2d(dtype=wp.float32), faces: wp.array2d(dtype=wp.int32), w2c: wp.array2d(dtype=wp.float32),
               K: wp.array2d(dtype=wp.float32), near: float, width: int, height: int, tile: int,
               hth: wp.array2d(dtype=wp.float32), rect: wp.array2d(dtype=wp.int32), znear: wp.array(dtype=wp.float32),
               ntiles: wp.array(dtype=wp.int32)):
    """Per face: edge lines and 1/z (hth), pixel-centre box, nearest-vertex view depth and the number of tiles the
    closed triangle touches (0 when culled: a vertex nearer than `near`, degenerate, or off-screen)."""
    f = wp.tid()
    ntiles[f] = 0
    znear[f] = 0.0
    c0 = to_cam(w2c, pos, faces[f, 0])
    c1 = to_cam(w2c, pos, faces[f, 1])
    c2 = to_cam(w2c, pos, faces[f, 2])
    zmin = wp.min(c0[2], wp.min(c1[2], c2[2]))
    if zmin < near:
        return
    p0 = project(K, c0)
    p1 = project(K, c1)
    p2 = project(K, c2)
    area2 = (p1[0] - p0[0]) * (p2[1] - p0[1]) - (p1[1] - p0[1]) * (p2[0] - p0[0])
    if area2 == 0.0:
        return
    sg = 1.0
    if area2 < 0.0:
        sg = -1.0
    uv = mat32(p0[0], p0[1], p1[0], p1[1], p2[0], p2[1])
    for k in range(3):
        k1 = (k + 1) % 3
        nx = sg * (uv[k1, 1] - uv[k, 1])
        ny = -sg * (uv[k1, 0] - uv[k, 0])
        hth[f, 3 * k] = nx
        hth[f, 3 * k + 1] = ny
        hth[f, 3 * k + 2] = -(nx * uv[k, 0] + ny * uv[k, 1])
    hth[f, 9] = 1.0 / c0[2]
    hth[f, 10] = 1.0 / c1[2]
    hth[f, 11] = 1.0 / c2[2]
    box = pixel_box(wp.vec3(p0[0], p1[0], p2[0]), wp.vec3(p0[1], p1[1], p2[1]), width, height)
    if box[0] > box[2] or box[1] > box[3]:
        return
    for k in range(4):
        rect[f, k] = box[k]
    ntiles[f] = count_tiles(hth, rect, f, tile, 1)
    znear[f] = zmin


@wp.kernel
def hard_pixels(hth: wp.array2d(dtype=wp.float32), rect: wp.array2d(dtype=wp.int32), vals: wp.array(dtype=wp.int32),
                tile_start: wp.array(dtype=wp.int32), tile_end: wp.array(dtype=wp.int32), znear: wp.array(dtype=wp.float32),
                width: int, height: int, tile: int, ntx: int, fid: wp.array2d(dtype=wp.int32),
                evals: wp.array2d(dtype=wp.int32)):
    """One pixel: the nearest face (largest 1/z) whose closed triangle holds the pixel centre, -1 if none."""
    pt = pixel_of(wp.tid(), tile, ntx)
    t = pt[0]
    ix = pt[1]
    iy = pt[2]
    if ix >= width or iy >= height:
        return
    px = float(ix) + 0.5
    py = float(iy) + 0.5
    best = float(0.0)
    bf = int(-1)
    ne = int(0)
    for j in range(tile_start[t], tile_end[t]):
        f = vals[j]
        if bf >= 0 and 1.0 / znear[f] <= best:
            break  # this face and every later one lie behind what the pixel shows
        if ix < rect[f, 0] or ix > rect[f, 2] or iy < rect[f, 1] or iy > rect[f, 3]:
            continue
        ne += 1
        L0 = hth[f, 0] * px + hth[f, 1] * py + hth[f, 2]
        L1 = hth[f, 3] * px + hth[f, 4] * py + hth[f, 5]
        L2 = hth[f, 6] * px + hth[f, 7] * py + hth[f, 8]
        if L0 > 0.0 or L1 > 0.0 or L2 > 0.0:
            continue
        tot = L0 + L1 + L2  # barycentrics are L_{k+1} / (L0 + L1 + L2) (unnormalised edge functions)
        zi = (L1 * hth[f, 9] + L2 * hth[f, 10] + L0 * hth[f, 11]) / tot
        if zi > best:
            best = zi
            bf = f
    fid[iy, ix] = bf
    evals[iy, ix] = ne


@wp.kernel
def hard_resolve(pos: wp.array2d(dtype=wp.float32), faces: wp.array2d(dtype=wp.int32), w2c: wp.array2d(dtype=wp.float32),
                 K: wp.array2d(dtype=wp.float32), colors: wp.array2d(dtype=wp.float32), fid: wp.array2d(dtype=wp.int32),
                 perspective: int, bg: wp.array(dtype=wp.float32), rgb: wp.array3d(dtype=wp.float32),
                 depth: wp.array2d(dtype=wp.float32), normal: wp.array3d(dtype=wp.float32),
                 face_id: wp.array2d(dtype=wp.int64), won: wp.array(dtype=wp.float32)):
    """One pixel: the winning face's interpolated vertex colour, view depth and camera-facing normal."""
    iy, ix = wp.tid()
    f = fid[iy, ix]
    face_id[iy, ix] = wp.int64(f)
    if f < 0:
        for c in range(3):
            rgb[iy, ix, c] = bg[c]
            normal[iy, ix, c] = 0.0
        depth[iy, ix] = 0.0
        return
    won[f] = 1.0
    i0 = faces[f, 0]
    i1 = faces[f, 1]
    i2 = faces[f, 2]
    c0 = to_cam(w2c, pos, i0)
    c1 = to_cam(w2c, pos, i1)
    c2 = to_cam(w2c, pos, i2)
    p0 = project(K, c0)
    p1 = project(K, c1)
    p2 = project(K, c2)
    px = float(ix) + 0.5
    py = float(iy) + 0.5
    ia = 1.0 / ((p1[0] - p0[0]) * (p2[1] - p0[1]) - (p1[1] - p0[1]) * (p2[0] - p0[0]))
    b0 = ((p1[0] - px) * (p2[1] - py) - (p1[1] - py) * (p2[0] - px)) * ia
    b1 = ((p2[0] - px) * (p0[1] - py) - (p2[1] - py) * (p0[0] - px)) * ia
    b2 = 1.0 - b0 - b1
    zinv = b0 / c0[2] + b1 / c1[2] + b2 / c2[2]
    if perspective == 1:
        b0 = b0 / c0[2] / zinv
        b1 = b1 / c1[2] / zinv
        b2 = b2 / c2[2] / zinv
    for c in range(3):
        rgb[iy, ix, c] = b0 * colors[i0, c] + b1 * colors[i1, c] + b2 * colors[i2, c]
    depth[iy, ix] = 1.0 / zinv
    n = wp.cross(c1 - c0, c2 - c0)
    ln = wp.length(n)
    if wp.dot(n, c0) > 0.0:
        ln = -ln
    if ln != 0.0:
        n = n / ln
    else:
        n = wp.vec3(0.0)
    for c in range(3):
        normal[iy, ix, c] = n[c]
