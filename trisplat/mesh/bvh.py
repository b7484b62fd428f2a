"""Bounding-volume hierarchy over triangles and a parallel segment/triangle any-hit query (Numba, Moller-Trumbore).

The tree is a linear BVH: triangles are sorted by the Morton code of their centroid and the sorted range is split
in half recursively down to leaves of at most `LEAF_SIZE` triangles; node boxes are computed bottom-up. Queries run
one segment per Numba task (`prange`) and write one slot each, so no atomics are needed.

`segment_any_hit_reference` is the readable pure-numpy twin of the compiled query (same inputs, same answers up to
ties between several hit triangles); tests compare the two.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

LEAF_SIZE = 4  # triangles per BVH leaf
_CHUNK = 1024  # segments per parallel task
_STACK_DEPTH = 128  # traversal stack entries; a median-split tree over 2^60 triangles would still fit
# A triangle counts as parallel to a segment when |det| <= PARALLEL_EPS * |d| * |e1| * |e2| (dimensionless: the
# sine of the angle between the segment and the triangle's plane, times the sine of the triangle's corner angle).
PARALLEL_EPS = 1e-12


@dataclass(frozen=True)
class TriangleBVH:
    """A BVH over T triangles (float64 corners), built by `build_bvh`.

    tri: float64 [T,3,3] triangle corners (in the caller's order). tri_vertex_ids: int64 [T,3] the vertex ids of each
    triangle (used to skip triangles that share a vertex with a query). order: int64 [T] triangle ids in leaf order.
    node_min/node_max: float64 [N,3] node boxes. node_left/node_right: int64 [N] children (-1 for leaves).
    node_start/node_count: int64 [N] range of a leaf in `order`.
    """

    tri: np.ndarray
    tri_vertex_ids: np.ndarray
    order: np.ndarray
    node_min: np.ndarray
    node_max: np.ndarray
    node_left: np.ndarray
    node_right: np.ndarray
    node_start: np.ndarray
    node_count: np.ndarray

    @property
    def num_triangles(self) -> int:
        return int(self.tri.shape[0])


def _morton_order(centroids: np.ndarray) -> np.ndarray:
    """Indices sorting points [T,3] along a 30-bit Morton (Z-order) curve."""
    lo = centroids.min(axis=0)
    span = np.maximum(centroids.max(axis=0) - lo, 1e-300)
    q = np.clip(((centroids - lo) / span * 1023.0).astype(np.int64), 0, 1023)

    def spread(x: np.ndarray) -> np.ndarray:  # insert two zero bits between each of 10 bits
        x = (x | (x << 16)) & 0x030000FF
        x = (x | (x << 8)) & 0x0300F00F
        x = (x | (x << 4)) & 0x030C30C3
        x = (x | (x << 2)) & 0x09249249
        return x

    code = spread(q[:, 0]) | (spread(q[:, 1]) << 1) | (spread(q[:, 2]) << 2)
    return np.argsort(code, kind="stable")


@nb.njit(cache=True)
def _build_nodes(tri_sorted, leaf_size):
    T = tri_sorted.shape[0]
    max_nodes = 2 * T + 1  # a binary tree with at most T leaves
    node_min = np.empty((max_nodes, 3))
    node_max = np.empty((max_nodes, 3))
    left = np.full(max_nodes, -1, np.int64)
    right = np.full(max_nodes, -1, np.int64)
    start = np.zeros(max_nodes, np.int64)
    count = np.zeros(max_nodes, np.int64)
    stack = np.empty((256, 2), np.int64)  # (node id, unused) ranges are kept in start/count
    n_nodes = 1
    start[0] = 0
    count[0] = T
    sp = 0
    stack[0, 0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp, 0]
        s = start[node]
        c = count[node]
        if c > leaf_size:
            half = c // 2
            l_id = n_nodes
            r_id = n_nodes + 1
            n_nodes += 2
            start[l_id] = s
            count[l_id] = half
            start[r_id] = s + half
            count[r_id] = c - half
            left[node] = l_id
            right[node] = r_id
            stack[sp, 0] = r_id
            sp += 1
            stack[sp, 0] = l_id
            sp += 1
    # children always have larger ids than their parent: fill boxes in reverse id order
    for node in range(n_nodes - 1, -1, -1):
        if left[node] < 0:
            for k in range(3):
                node_min[node, k] = np.inf
                node_max[node, k] = -np.inf
            for t in range(start[node], start[node] + count[node]):
                for j in range(3):
                    for k in range(3):
                        v = tri_sorted[t, j, k]
                        node_min[node, k] = min(node_min[node, k], v)
                        node_max[node, k] = max(node_max[node, k], v)
        else:
            a = left[node]
            b = right[node]
            for k in range(3):
                node_min[node, k] = min(node_min[a, k], node_min[b, k])
                node_max[node, k] = max(node_max[a, k], node_max[b, k])
    return node_min[:n_nodes], node_max[:n_nodes], left[:n_nodes], right[:n_nodes], start[:n_nodes], count[:n_nodes]


def build_bvh(vertices: np.ndarray, faces: np.ndarray) -> TriangleBVH:
    """BVH over the triangles `faces` [T,3] (int indices into `vertices` [V,3]). T may be 0."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    tri = vertices[faces] if len(faces) else np.zeros((0, 3, 3))
    if len(faces) == 0:
        empty_f = np.zeros((0, 3))
        empty_i = np.zeros(0, np.int64)
        return TriangleBVH(tri, faces, empty_i, empty_f, empty_f, empty_i, empty_i, empty_i, empty_i)
    order = _morton_order(tri.mean(axis=1)).astype(np.int64)
    nmin, nmax, left, right, start, count = _build_nodes(np.ascontiguousarray(tri[order]), LEAF_SIZE)
    return TriangleBVH(np.ascontiguousarray(tri), faces, order, nmin, nmax, left, right, start, count)


@nb.njit(cache=True, inline="always")
def _segment_triangle(p0, d, tri, t_id):
    """Moller-Trumbore: True when p0 + s*d, s in [0,1], meets triangle tri[t_id] (closed triangle)."""
    ax, ay, az = tri[t_id, 0, 0], tri[t_id, 0, 1], tri[t_id, 0, 2]
    e1x, e1y, e1z = tri[t_id, 1, 0] - ax, tri[t_id, 1, 1] - ay, tri[t_id, 1, 2] - az
    e2x, e2y, e2z = tri[t_id, 2, 0] - ax, tri[t_id, 2, 1] - ay, tri[t_id, 2, 2] - az
    px = d[1] * e2z - d[2] * e2y
    py = d[2] * e2x - d[0] * e2z
    pz = d[0] * e2y - d[1] * e2x
    det = e1x * px + e1y * py + e1z * pz
    scale = np.sqrt((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) * (e1x * e1x + e1y * e1y + e1z * e1z)
                    * (e2x * e2x + e2y * e2y + e2z * e2z))
    if abs(det) <= PARALLEL_EPS * scale or scale == 0.0:
        return False
    inv = 1.0 / det
    tx, ty, tz = p0[0] - ax, p0[1] - ay, p0[2] - az
    u = (tx * px + ty * py + tz * pz) * inv
    if u < 0.0 or u > 1.0:
        return False
    qx = ty * e1z - tz * e1y
    qy = tz * e1x - tx * e1z
    qz = tx * e1y - ty * e1x
    v = (d[0] * qx + d[1] * qy + d[2] * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return False
    s = (e2x * qx + e2y * qy + e2z * qz) * inv
    return 0.0 <= s <= 1.0


@nb.njit(cache=True, inline="always")
def _first_hit(p0, d, inv, stack, ea, eb, tri, tri_ids, order, nmin, nmax, left, right, start, count):
    """Depth-first any-hit traversal for one segment p0 + s*d (s in [0,1]); inv = 1/d (inf where d is 0)."""
    sp = 0
    stack[sp] = 0
    sp += 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        # slab test of the segment against the node box
        t0 = 0.0
        t1 = 1.0
        miss = False
        for k in range(3):
            if d[k] == 0.0:
                if p0[k] < nmin[node, k] or p0[k] > nmax[node, k]:
                    miss = True
                    break
            else:
                ta = (nmin[node, k] - p0[k]) * inv[k]
                tb = (nmax[node, k] - p0[k]) * inv[k]
                if ta > tb:
                    ta, tb = tb, ta
                t0 = max(t0, ta)
                t1 = min(t1, tb)
                if t0 > t1:
                    miss = True
                    break
        if miss:
            continue
        if left[node] < 0:
            for j in range(start[node], start[node] + count[node]):
                t_id = order[j]
                if ea >= 0 and (tri_ids[t_id, 0] == ea or tri_ids[t_id, 1] == ea or tri_ids[t_id, 2] == ea):
                    continue
                if eb >= 0 and (tri_ids[t_id, 0] == eb or tri_ids[t_id, 1] == eb or tri_ids[t_id, 2] == eb):
                    continue
                if _segment_triangle(p0, d, tri, t_id):
                    return t_id
        else:
            stack[sp] = left[node]
            sp += 1
            stack[sp] = right[node]
            sp += 1
    return -1


@nb.njit(parallel=True, cache=True)
def _any_hit_kernel(p0s, p1s, excl_a, excl_b, tri, tri_ids, order, nmin, nmax, left, right, start, count):
    n = p0s.shape[0]
    out = np.full(n, -1, np.int64)
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    for chunk in nb.prange(n_chunks):  # scratch arrays allocated once per chunk of segments, not per segment
        d = np.empty(3)
        inv = np.empty(3)
        stack = np.empty(_STACK_DEPTH, np.int64)
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            p0 = p0s[i]
            for k in range(3):
                d[k] = p1s[i, k] - p0[k]
                inv[k] = 1.0 / d[k] if d[k] != 0.0 else np.inf
            out[i] = _first_hit(p0, d, inv, stack, excl_a[i], excl_b[i], tri, tri_ids, order, nmin, nmax, left,
                                right, start, count)
    return out


def _check_segments(p0: np.ndarray, p1: np.ndarray, exclude):
    p0 = np.ascontiguousarray(p0, dtype=np.float64).reshape(-1, 3)
    p1 = np.ascontiguousarray(p1, dtype=np.float64).reshape(-1, 3)
    if p0.shape != p1.shape:
        raise ValueError(f"segment start and end points differ in shape: {p0.shape} vs {p1.shape}")
    n = len(p0)
    if exclude is None:
        ea = np.full(n, -1, np.int64)
        eb = np.full(n, -1, np.int64)
    else:
        ex = np.ascontiguousarray(exclude, dtype=np.int64).reshape(n, 2)
        ea, eb = np.ascontiguousarray(ex[:, 0]), np.ascontiguousarray(ex[:, 1])
    return p0, p1, ea, eb


def segment_any_hit(bvh: TriangleBVH, p0: np.ndarray, p1: np.ndarray, exclude: np.ndarray | None = None) -> np.ndarray:
    """For each segment p0[i] -> p1[i] ([N,3] each), the id of one triangle it meets (closed segment, closed
    triangle), or -1. `exclude` [N,2] int (optional, -1 = none): vertex ids; triangles using either are skipped.
    Segments of zero length and segments lying in a triangle's plane meet nothing."""
    p0, p1, ea, eb = _check_segments(p0, p1, exclude)
    if bvh.num_triangles == 0 or len(p0) == 0:
        return np.full(len(p0), -1, np.int64)
    return _any_hit_kernel(p0, p1, ea, eb, bvh.tri, bvh.tri_vertex_ids, bvh.order, bvh.node_min, bvh.node_max,
                           bvh.node_left, bvh.node_right, bvh.node_start, bvh.node_count)


def segment_any_hit_reference(vertices: np.ndarray, faces: np.ndarray, p0: np.ndarray, p1: np.ndarray,
                              exclude: np.ndarray | None = None) -> np.ndarray:
    """Readable twin of `segment_any_hit`: brute force over all (segment, triangle) pairs in numpy, returning for
    each segment the smallest id of a triangle it meets, or -1. O(N*T) memory: for tests on small inputs."""
    p0, p1, ea, eb = _check_segments(p0, p1, exclude)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    tri = np.asarray(vertices, dtype=np.float64)[faces]  # [T,3,3]
    if len(faces) == 0 or len(p0) == 0:
        return np.full(len(p0), -1, np.int64)
    a, e1, e2 = tri[None, :, 0], tri[None, :, 1] - tri[None, :, 0], tri[None, :, 2] - tri[None, :, 0]
    d = (p1 - p0)[:, None, :]
    pvec = np.cross(d, e2)
    det = np.sum(e1 * pvec, axis=-1)
    scale = np.sqrt(np.sum(d * d, -1) * np.sum(e1 * e1, -1) * np.sum(e2 * e2, -1))
    ok = (np.abs(det) > PARALLEL_EPS * scale) & (scale > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        tvec = p0[:, None, :] - a
        u = np.sum(tvec * pvec, -1) * inv
        qvec = np.cross(tvec, e1)
        v = np.sum(d * qvec, -1) * inv
        s = np.sum(e2 * qvec, -1) * inv
    hit = ok & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1) & (s >= 0) & (s <= 1)
    uses = lambda e: (faces[None, :, :] == e[:, None, None]).any(-1) & (e[:, None] >= 0)
    hit &= ~uses(ea) & ~uses(eb)
    first = np.where(hit.any(axis=1), hit.argmax(axis=1), -1)
    return first.astype(np.int64)


@nb.njit(cache=True, inline="always")
def _closest_on_triangle(px, py, pz, tri, t):
    """The point of triangle `tri[t]` nearest to (px, py, pz) (Ericson, Real-Time Collision Detection, 5.1.5; the
    readable twin is trisplat.mesh.cleanup.closest_points_on_triangles)."""
    ax, ay, az = tri[t, 0, 0], tri[t, 0, 1], tri[t, 0, 2]
    abx, aby, abz = tri[t, 1, 0] - ax, tri[t, 1, 1] - ay, tri[t, 1, 2] - az
    acx, acy, acz = tri[t, 2, 0] - ax, tri[t, 2, 1] - ay, tri[t, 2, 2] - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az
    bpx, bpy, bpz = px - tri[t, 1, 0], py - tri[t, 1, 1], pz - tri[t, 1, 2]
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2]
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return ax + v * abx, ay + v * aby, az + v * abz
    cpx, cpy, cpz = px - tri[t, 2, 0], py - tri[t, 2, 1], pz - tri[t, 2, 2]
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return tri[t, 2, 0], tri[t, 2, 1], tri[t, 2, 2]
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return ax + w * acx, ay + w * acy, az + w * acz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        bx, by, bz = tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2]
        return bx + w * (tri[t, 2, 0] - bx), by + w * (tri[t, 2, 1] - by), bz + w * (tri[t, 2, 2] - bz)
    den = va + vb + vc
    if den == 0.0:
        return ax, ay, az  # a degenerate triangle: its first corner
    v = vb / den
    w = vc / den
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w


@nb.njit(parallel=True, cache=True)
def _nearest_kernel(points, point_group, tri_group, max_d, tri, order, nmin, nmax, left, right, start, count,
                    out_t, out_d, out_q):
    n = points.shape[0]
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    for chunk in nb.prange(n_chunks):
        stack = np.empty(_STACK_DEPTH, np.int64)
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            best = max_d * max_d
            bt = -1
            sp = 1
            stack[0] = 0
            while sp > 0:
                sp -= 1
                node = stack[sp]
                dd = 0.0
                for k in range(3):
                    c = points[i, k]
                    if c < nmin[node, k]:
                        dd += (nmin[node, k] - c) ** 2
                    elif c > nmax[node, k]:
                        dd += (c - nmax[node, k]) ** 2
                if dd > best:
                    continue
                if left[node] < 0:
                    for j in range(start[node], start[node] + count[node]):
                        t = order[j]
                        if tri_group[t] == point_group[i]:
                            continue
                        qx, qy, qz = _closest_on_triangle(px, py, pz, tri, t)
                        d2 = (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2
                        if d2 <= best:
                            best = d2
                            bt = t
                            out_q[i, 0], out_q[i, 1], out_q[i, 2] = qx, qy, qz
                else:
                    stack[sp] = left[node]
                    sp += 1
                    stack[sp] = right[node]
                    sp += 1
            out_t[i] = bt
            out_d[i] = np.sqrt(best) if bt >= 0 else np.inf


def nearest_other_triangle(bvh: TriangleBVH, points: np.ndarray, point_group: np.ndarray, tri_group: np.ndarray,
                           max_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point [N,3], the nearest triangle of another group (tri_group [T] per triangle, point_group [N] per
    point: a triangle of the point's own group is skipped) within max_distance: (triangle id [N] or -1, distance
    [N] or inf, the nearest point on it [N,3])."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    out_t = np.full(n, -1, np.int64)
    out_d = np.full(n, np.inf)
    out_q = np.zeros((n, 3))
    if bvh.num_triangles == 0 or n == 0:
        return out_t, out_d, out_q
    _nearest_kernel(points, np.ascontiguousarray(point_group, np.int64), np.ascontiguousarray(tri_group, np.int64),
                    float(max_distance), bvh.tri, bvh.order, bvh.node_min, bvh.node_max, bvh.node_left,
                    bvh.node_right, bvh.node_start, bvh.node_count, out_t, out_d, out_q)
    return out_t, out_d, out_q
