"""The dense tracker's normal equations in one Numba pass (trisplat.slam.track): for every map point, its move by T,
projection, bilinear lookups, depth and photometric residuals, their closed-form SE(3) Jacobians, Huber weights,
and their sums into J^T W J, J^T W r and the robust cost, without the per-point arrays of the numpy reference
(`track._residuals`, which the tests compare this with).
"""
from __future__ import annotations

import numba as nb
import numpy as np

CHUNK = 4096  # points per parallel work item (each its own partial sums)
NOISE_A, NOISE_B, NOISE_Z0 = 0.0012, 0.0019, 0.4  # Kinect v1's axial depth noise (track.depth_scale)


@nb.njit(inline="always")
def _bilinear(img, x, y, x0, y0):  # pragma: no cover (compiled)
    ax = x - x0
    ay = y - y0
    return ((1 - ay) * ((1 - ax) * img[y0, x0] + ax * img[y0, x0 + 1])
            + ay * ((1 - ax) * img[y0 + 1, x0] + ax * img[y0 + 1, x0 + 1]))


@nb.njit(inline="always")
def _huber(a, k):  # pragma: no cover (compiled)
    """(cost, weight) of a scaled residual a."""
    m = abs(a)
    if m <= k:
        return 0.5 * m * m, 1.0
    return k * (m - 0.5 * k), k / m


@nb.njit(inline="always")
def _add(H, g, J, r, w):  # pragma: no cover (compiled)
    for a in range(6):
        wa = w * J[a]
        g[a] += wa * r
        for b in range(a, 6):
            H[a, b] += wa * J[b]


@nb.njit(parallel=True, cache=True)
def normal_equations(X, Ir, Io, gIx, gIy, Do, gDx, gDy, Dbad, K, T, outlier, depth_sigma, photo_sigma, huber,
                     w_photo, photo, depth_noise, No, p2p):  # pragma: no cover (compiled)
    """(robust cost sum, points kept, H [6,6], g [6]) of the level's map points X [N,3] (guess camera frame) moved by
    T [4,4] into the observation: see track._residuals for which points are kept and the residuals' definitions; a
    depth residual at depth z is scaled by track.depth_scale (TrackConfig.depth_noise); p2p: the
    point-to-plane depth term with the observation's normals No [h,w,3] (TrackConfig.depth_residual)."""
    n_pts = X.shape[0]
    h, w = Do.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    n_chunks = (n_pts + CHUNK - 1) // CHUNK
    Hs = np.zeros((n_chunks, 6, 6))
    gs = np.zeros((n_chunks, 6))
    costs = np.zeros(n_chunks)
    counts = np.zeros(n_chunks, np.int64)
    for c in nb.prange(n_chunks):
        Hc = Hs[c]
        gc = gs[c]
        Ju = np.empty(6)
        Jv = np.empty(6)
        J = np.empty(6)
        cost = 0.0
        cnt = 0
        for i in range(c * CHUNK, min(n_pts, (c + 1) * CHUNK)):
            Xx, Xy, Xz = X[i, 0], X[i, 1], X[i, 2]
            qx = T[0, 0] * Xx + T[0, 1] * Xy + T[0, 2] * Xz + T[0, 3]
            qy = T[1, 0] * Xx + T[1, 1] * Xy + T[1, 2] * Xz + T[1, 3]
            z = T[2, 0] * Xx + T[2, 1] * Xy + T[2, 2] * Xz + T[2, 3]
            if not z > 1e-3:
                continue
            x = fx * qx / z + cx - 0.5
            y = fy * qy / z + cy - 0.5
            if not (x >= 0 and x < w - 1 and y >= 0 and y < h - 1):
                continue
            x0 = int(np.floor(x))
            y0 = int(np.floor(y))
            rD = _bilinear(Do, x, y, x0, y0) - z
            if Dbad[y0, x0] or Dbad[y0, x0 + 1] or Dbad[y0 + 1, x0] or Dbad[y0 + 1, x0 + 1]:
                continue
            if not abs(rD) < outlier:
                continue
            cnt += 1
            iz = 1.0 / z
            Ju[0] = fx * iz
            Ju[1] = 0.0
            Ju[2] = -fx * qx * iz * iz
            Ju[3] = -fx * qx * qy * iz * iz
            Ju[4] = fx * (1 + qx * qx * iz * iz)
            Ju[5] = -fx * qy * iz
            Jv[0] = 0.0
            Jv[1] = fy * iz
            Jv[2] = -fy * qy * iz * iz
            Jv[3] = -fy * (1 + qy * qy * iz * iz)
            Jv[4] = fy * qx * qy * iz * iz
            Jv[5] = fy * qx * iz
            ds = depth_sigma * (1.0 - depth_noise + depth_noise * (NOISE_A + NOISE_B * (z - NOISE_Z0) ** 2)
                                / (NOISE_A + NOISE_B * (1.0 - NOISE_Z0) ** 2))
            if p2p:
                xn = int(np.floor(x + 0.5))
                yn = int(np.floor(y + 0.5))
                nx, ny, nz = No[yn, xn, 0], No[yn, xn, 1], No[yn, xn, 2]
                if nx == 0.0 and ny == 0.0 and nz == 0.0:
                    cnt -= 1
                    continue
                # n . (P_obs - Q), P_obs = Q D_obs / Q_z; its Jacobian -[n, Q x n] (the correspondence held)
                r = (nx * qx + ny * qy + nz * z) * rD / z / ds
                J[0] = -nx / ds
                J[1] = -ny / ds
                J[2] = -nz / ds
                J[3] = -(qy * nz - z * ny) / ds
                J[4] = -(z * nx - qx * nz) / ds
                J[5] = -(qx * ny - qy * nx) / ds
            else:
                gx = _bilinear(gDx, x, y, x0, y0)
                gy = _bilinear(gDy, x, y, x0, y0)
                for a in range(6):
                    J[a] = (gx * Ju[a] + gy * Jv[a]) / ds
                # minus d z / d xi = e_z . [I | -Q^] = (0, 0, 1, qy, -qx, 0)
                J[2] -= 1.0 / ds
                J[3] -= qy / ds
                J[4] += qx / ds
                r = rD / ds
            cst, wt = _huber(r, huber)
            cost += cst
            _add(Hc, gc, J, r, wt)
            if photo:
                rI = (_bilinear(Io, x, y, x0, y0) - Ir[i]) / photo_sigma
                gx = _bilinear(gIx, x, y, x0, y0)
                gy = _bilinear(gIy, x, y, x0, y0)
                for a in range(6):
                    J[a] = (gx * Ju[a] + gy * Jv[a]) / photo_sigma
                cst, wt = _huber(rI, huber)
                cost += w_photo * cst
                _add(Hc, gc, J, rI, w_photo * wt)
        costs[c] = cost
        counts[c] = cnt
    H = np.zeros((6, 6))
    g = np.zeros(6)
    for c in range(n_chunks):
        H += Hs[c]
        g += gs[c]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return costs.sum(), counts.sum(), H, g


# The same pass on one thread, for the coarse levels: a few thousand points are done before a parallel region's
# threads have all started (on a shared machine, one waits for a core), and the chunk sums are added in the same
# order, so both give the same numbers.
normal_equations_serial = nb.njit(cache=True)(normal_equations.py_func)
SERIAL_BELOW = 8 * CHUNK  # points: fewer go through normal_equations_serial


@nb.njit(cache=True)
def coverage(X, Do, K, T, outlier):  # pragma: no cover (compiled)
    """(distinct observation pixels landed on, hits, sum of |depth residual| over the hits) of the map points X [M,3]
    moved by T [4,4] and projected (floor of the pixel coordinate, centres at +0.5) into the observed depth Do: a hit
    lands on a valid observed depth within `outlier` metres. One serial pass (the landed mask is shared): what
    track._coverage_reference computes with numpy arrays of every point."""
    h, w = Do.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    landed = np.zeros(h * w, np.bool_)
    distinct = 0
    hits = 0
    total = 0.0
    for i in range(X.shape[0]):
        x, y, z0 = X[i, 0], X[i, 1], X[i, 2]
        z = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z0 + T[2, 3]
        if not z > 1e-3:
            continue
        qx = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z0 + T[0, 3]
        qy = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z0 + T[1, 3]
        fu = np.floor(fx * qx / z + cx)
        fv = np.floor(fy * qy / z + cy)
        if not (fu >= 0 and fu < w and fv >= 0 and fv < h):
            continue
        u = int(fu)
        v = int(fv)
        d = Do[v, u]
        if d > 0 and abs(d - z) < outlier:
            hits += 1
            total += abs(d - z)
            k = v * w + u
            if not landed[k]:
                landed[k] = True
                distinct += 1
    return distinct, hits, total
