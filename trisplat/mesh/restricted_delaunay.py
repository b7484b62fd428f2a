"""Restricted Delaunay triangulation: the Delaunay faces of a vertex set whose dual Voronoi edge meets a triangle soup.

Spec (MeshSplatting, ALGORITHM.md section 4): tetrahedralise the vertices (scipy / Qhull); every interior face is
shared by two tetrahedra and its dual Voronoi edge is the segment between their circumcentres; a face on the convex
hull has one tetrahedron and its dual edge is the ray from that circumcentre along the face's outward normal (cut at
`HULL_RAY_LENGTH` bounding-box diagonals). A face is kept when its dual edge meets any soup triangle (BVH + Moller-
Trumbore, `trisplat.mesh.bvh`). Kept faces are then oriented consistently (`trisplat.mesh.orient`), using the normal
of the soup triangle each dual edge met as the hint for open pieces.

Degenerate input: exact duplicate points are left out (the first copy is used); the points are jittered by
`JITTER` bounding-box diagonals (fixed seed; the output keeps the exact positions) so that coplanar and co-spherical
groups get one consistent triangulation (as a symbolic perturbation would) instead of rounding noise; co-spherical
points are also handled by Qhull's point at infinity (`Qz`); a flat tetrahedron (coplanar points; |det| tiny or circumcentre beyond
`HULL_RAY_LENGTH` diagonals) gets its Voronoi vertex that far along its plane normal, above its circumcircle, so
exactly one of the two triangulations of its points is kept; coplanar input is triangulated in its plane (2D
Delaunay) with dual edges crossing the plane; collinear input and fewer than 4 points give no faces; if Qhull
still fails it is retried once with joggle (`QJ`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from scipy.spatial import Delaunay, QhullError

from trisplat.mesh.bvh import build_bvh, segment_any_hit
from trisplat.mesh.orient import orient_faces

QHULL_OPTIONS = "Qbb Qc Qz Q12"  # scipy's default for 3D (Qt is always on)
QHULL_JOGGLE_OPTIONS = "QJ Qbb"  # Qz (point at infinity) would leak into the simplices with QJ
HULL_RAY_LENGTH = 4.0  # bounding-box diagonals of (vertices + soup): length of the dual ray of a hull face
FLAT_RATIO = 1e-9  # smallest / largest singular value of the centred points below which the input counts as flat
JITTER = 1e-7  # bounding-box diagonals: amplitude of the uniform jitter applied (for the triangulation only)
JITTER_SEED = 0
FLAT_TET_EPS = 1e-12  # |det| / (|u| |v| |w|) below which a tetrahedron counts as flat (dimensionless)


@dataclass
class RDTReport:
    """What `restricted_delaunay` did, with timings (seconds)."""

    num_vertices: int = 0
    num_unused_vertices: int = 0  # vertices in no Delaunay simplex (duplicates) or in no kept face
    num_tets: int = 0
    num_interior_faces: int = 0
    num_hull_faces: int = 0
    num_kept_faces: int = 0
    num_flat_tets: int = 0
    mode: str = "3d"  # "3d", "planar", "collinear" or "too-few-points"
    qhull_options: str = ""
    joggled: bool = False
    num_flipped: int = 0
    num_conflicting_edges: int = 0
    qhull_s: float = 0.0
    qhull_cpu_s: float = 0.0  # process CPU time of the Qhull call (single-threaded: its wall time on an idle core)
    dual_s: float = 0.0
    bvh_build_s: float = 0.0
    bvh_test_s: float = 0.0
    orient_s: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def total_s(self) -> float:
        return self.qhull_s + self.dual_s + self.bvh_build_s + self.bvh_test_s + self.orient_s


@nb.njit(parallel=True, cache=True)
def _circumcentres(points, simplices, flat_eps, far):
    """Circumcentres [T,3] of tetrahedra and a flag for flat ones. A flat tetrahedron (|det| tiny, or circumcentre
    farther than `far` from it) has its Voronoi vertex at (or beyond) infinity along the normal of its plane, in a
    direction that rounding noise makes arbitrary: it is placed at `far` along that normal from the circumcentre
    of its largest face, on the side the raw computation pointed to (+normal when undetermined)."""
    n = simplices.shape[0]
    out = np.empty((n, 3))
    flat = np.zeros(n, np.bool_)
    for t in nb.prange(n):
        a = points[simplices[t, 0]]
        u = points[simplices[t, 1]] - a
        v = points[simplices[t, 2]] - a
        w = points[simplices[t, 3]] - a
        vw = np.cross(v, w)
        wu = np.cross(w, u)
        uv = np.cross(u, v)
        det = 2.0 * (u[0] * vw[0] + u[1] * vw[1] + u[2] * vw[2])
        lu, lv, lw = np.dot(u, u), np.dot(v, v), np.dot(w, w)
        is_flat = abs(det) <= 2.0 * flat_eps * np.sqrt(lu * lv * lw)
        raw = a.copy()
        if not is_flat:
            raw = a + (lu * vw + lv * wu + lw * uv) / det
            off = raw - a
            is_flat = np.dot(off, off) > far * far
        if not is_flat:
            out[t] = raw
            continue
        flat[t] = True
        # largest face of the tetrahedron: its plane and circumcircle stand for the flat tetrahedron's
        best = -1.0
        cc = a.copy()
        nrm = np.zeros(3)
        for k in range(4):
            p0 = points[simplices[t, (k + 1) % 4]]
            e1 = points[simplices[t, (k + 2) % 4]] - p0
            e2 = points[simplices[t, (k + 3) % 4]] - p0
            c = np.cross(e1, e2)
            cc2 = np.dot(c, c)
            if cc2 > best:
                best = cc2
                nrm = c
                if cc2 > 0.0:
                    cc = p0 + (np.dot(e1, e1) * np.cross(e2, c) + np.dot(e2, e2) * np.cross(c, e1)) / (2.0 * cc2)
                else:
                    cc = p0
        ln = np.sqrt(best)
        if ln == 0.0:
            out[t] = a + (u + v + w) / 4.0  # all four points collinear or coincident
            continue
        nrm = nrm / ln
        side = 1.0
        if not np.array_equal(raw, a) and np.dot(raw - cc, nrm) < 0.0:
            side = -1.0
        out[t] = cc + side * far * nrm
    return out, flat


def _validate(vertices, soup_vertices, soup_faces):
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be [V,3], got shape {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError(f"vertices contain {int((~np.isfinite(v)).any(axis=1).sum())} non-finite rows")
    sv = np.asarray(soup_vertices, dtype=np.float64)
    if sv.ndim != 2 or sv.shape[1] != 3:
        raise ValueError(f"soup_vertices must be [S,3], got shape {sv.shape}")
    sf = np.asarray(soup_faces)
    if sf.ndim != 2 or sf.shape[1] != 3 or (sf.size and not np.issubdtype(sf.dtype, np.integer)):
        raise ValueError(f"soup_faces must be integer [G,3], got shape {sf.shape} dtype {sf.dtype}")
    sf = sf.astype(np.int64)
    if sf.size and (sf.min() < 0 or sf.max() >= len(sv)):
        raise ValueError(f"soup_faces index out of range [0, {len(sv)}): min {sf.min()}, max {sf.max()}")
    return v, sv, sf


def _hint_normals(soup_tri: np.ndarray, hit: np.ndarray) -> np.ndarray:
    return np.cross(soup_tri[hit, 1] - soup_tri[hit, 0], soup_tri[hit, 2] - soup_tri[hit, 0])


def restricted_delaunay(
    vertices: np.ndarray, soup_vertices: np.ndarray, soup_faces: np.ndarray, report: RDTReport | None = None
) -> np.ndarray:
    """Faces int32 [F,3] (indices into `vertices` [V,3]) of the Delaunay triangulation of `vertices` restricted to the
    triangle soup (`soup_vertices` [S,3], `soup_faces` [G,3]); consistently oriented, outward on closed pieces.

    Pass an `RDTReport` to receive counts, timings and notes about degenerate input. Use `restricted_delaunay_report`
    to get both back.
    """
    rep = report if report is not None else RDTReport()
    v, sv, sf = _validate(vertices, soup_vertices, soup_faces)
    rep.num_vertices = len(v)
    empty = np.zeros((0, 3), np.int32)
    if len(v) < 4:
        rep.mode = "too-few-points"
        rep.num_unused_vertices = len(v)
        rep.notes.append(f"{len(v)} vertices: a 3D Delaunay triangulation needs at least 4; no faces")
        return empty
    all_pts = np.concatenate([v, sv]) if len(sv) else v
    diag = float(np.linalg.norm(all_pts.max(axis=0) - all_pts.min(axis=0)))
    ray_len = HULL_RAY_LENGTH * max(diag, 1e-30)

    centre = v.mean(axis=0)
    _, sing, basis = np.linalg.svd(v - centre, full_matrices=False)
    if sing[0] == 0 or sing[1] <= FLAT_RATIO * sing[0]:
        rep.mode = "collinear"
        rep.num_unused_vertices = len(v)
        rep.notes.append("all vertices are collinear or coincident: no faces")
        return empty

    t0 = time.perf_counter()
    if sing[2] <= FLAT_RATIO * sing[0]:
        faces, p0, p1 = _planar_dual(v, centre, basis, ray_len, rep)
    else:
        # exact duplicates out; a tiny fixed-seed jitter so that coplanar / co-spherical groups (points sampled on
        # the flat facets of a mesh, grids) get one consistent Delaunay triangulation instead of rounding noise
        uniq, first = np.unique(v, axis=0, return_index=True)
        n_dup = len(v) - len(uniq)
        if n_dup:
            rep.notes.append(f"{n_dup} duplicate vertices left out (their first copy is used)")
        jitter = JITTER * max(diag, 1e-30)
        uj = v[first] + np.random.default_rng(JITTER_SEED).uniform(-jitter, jitter, (len(first), 3))
        faces, p0, p1 = _spatial_dual(uj, ray_len, rep, t0)
        faces = first[faces]
    rep.dual_s = time.perf_counter() - t0 - rep.qhull_s

    t0 = time.perf_counter()
    bvh = build_bvh(sv, sf)
    rep.bvh_build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    hit = segment_any_hit(bvh, p0, p1)
    rep.bvh_test_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    keep = hit >= 0
    kept = faces[keep]
    oriented, orep = orient_faces(v, kept, hint_normals=_hint_normals(bvh.tri, hit[keep]))
    rep.orient_s = time.perf_counter() - t0
    rep.num_kept_faces = len(oriented)
    rep.num_flipped = orep.num_flipped
    rep.num_conflicting_edges = orep.num_conflicting_edges
    used = np.zeros(len(v), bool)
    used[oriented.reshape(-1)] = True
    rep.num_unused_vertices = len(v) - int(used.sum())
    return oriented


def restricted_delaunay_report(vertices, soup_vertices, soup_faces) -> tuple[np.ndarray, RDTReport]:
    """`restricted_delaunay` returning (faces, report)."""
    rep = RDTReport()
    faces = restricted_delaunay(vertices, soup_vertices, soup_faces, report=rep)
    return faces, rep


def _spatial_dual(v: np.ndarray, ray_len: float, rep: RDTReport, t_start: float):
    """Delaunay faces [N,3] and their dual edges (p0, p1 [N,3]) for a full-dimensional vertex set."""
    cpu0 = time.process_time()
    try:
        tri = Delaunay(v, qhull_options=QHULL_OPTIONS)
        rep.qhull_options = QHULL_OPTIONS
    except QhullError as exc:
        tri = Delaunay(v, qhull_options=QHULL_JOGGLE_OPTIONS)
        rep.qhull_options = QHULL_JOGGLE_OPTIONS
        rep.joggled = True
        rep.notes.append(f"Qhull failed with {QHULL_OPTIONS!r} ({str(exc).splitlines()[0]}); retried with joggle QJ")
    rep.qhull_s = time.perf_counter() - t_start
    rep.qhull_cpu_s = time.process_time() - cpu0
    simplices = np.ascontiguousarray(tri.simplices, dtype=np.int64)
    neighbors = tri.neighbors
    rep.num_tets = len(simplices)
    cc, flat = _circumcentres(v, simplices, FLAT_TET_EPS, ray_len)
    rep.num_flat_tets = int(flat.sum())
    if rep.num_flat_tets:
        rep.notes.append(
            f"{rep.num_flat_tets} flat tetrahedra (coplanar points): Voronoi vertex put "
            f"{HULL_RAY_LENGTH} bounding-box diagonals along their plane normal"
        )
    in_tet = np.zeros(len(v), bool)
    in_tet[simplices.reshape(-1)] = True
    n_unused = len(v) - int(in_tet.sum())
    if n_unused:
        rep.notes.append(f"{n_unused} vertices are in no tetrahedron (duplicates or coplanar with Qhull's tolerance)")

    neighbors = np.ascontiguousarray(neighbors, dtype=np.int64)
    n_int = _count_dual(neighbors, True)
    n_hull = _count_dual(neighbors, False)
    rep.num_interior_faces, rep.num_hull_faces = int(n_int.sum()), int(n_hull.sum())
    offsets = np.concatenate([[0], np.cumsum(n_int + n_hull)])
    return _dual_edges(v, simplices, neighbors, cc, ray_len, offsets)


@nb.njit(parallel=True, cache=True)
def _count_dual(neighbors, interior):
    """Per tetrahedron: its interior faces counted once (from the lower-numbered side), or its hull faces."""
    n = neighbors.shape[0]
    out = np.zeros(n, np.int64)
    for t in nb.prange(n):
        c = 0
        for i in range(4):
            nb_t = neighbors[t, i]
            if (interior and nb_t > t) or (not interior and nb_t < 0):
                c += 1
        out[t] = c
    return out


@nb.njit(parallel=True, cache=True)
def _dual_edges(points, simplices, neighbors, cc, ray_len, offsets):
    """Faces [N,3] (the face opposite local vertex i of tetrahedron t) and dual edges p0 -> p1: to the neighbour's
    circumcentre for interior faces; a ray of length `ray_len` along the outward normal for hull faces."""
    total = offsets[-1]
    faces = np.empty((total, 3), np.int64)
    p0 = np.empty((total, 3))
    p1 = np.empty((total, 3))
    for t in nb.prange(neighbors.shape[0]):
        k = offsets[t]
        for i in range(4):
            nb_t = neighbors[t, i]
            if nb_t >= 0 and nb_t < t:
                continue
            j = 0
            for m in range(4):
                if m != i:
                    faces[k, j] = simplices[t, m]
                    j += 1
            p0[k] = cc[t]
            if nb_t >= 0:
                p1[k] = cc[nb_t]
            else:
                a = points[faces[k, 0]]
                nrm = np.cross(points[faces[k, 1]] - a, points[faces[k, 2]] - a)
                if np.dot(nrm, points[simplices[t, i]] - a) > 0.0:
                    nrm = -nrm
                ln = np.sqrt(np.dot(nrm, nrm))
                if ln > 0.0:
                    nrm = nrm / ln
                p1[k] = cc[t] + ray_len * nrm
            k += 1
    return faces, p0, p1


def _planar_dual(v: np.ndarray, centre: np.ndarray, basis: np.ndarray, ray_len: float, rep: RDTReport):
    """All vertices in one plane: 2D Delaunay in the plane; each triangle's dual edge crosses the plane through its
    circumcentre along the plane normal."""
    rep.mode = "planar"
    rep.notes.append("vertices are coplanar: 2D Delaunay in their plane, dual edges along the plane normal")
    uv = (v - centre) @ basis[:2].T
    t0 = time.perf_counter()
    tri = Delaunay(uv, qhull_options="Qbb Qc Qz Q12")
    rep.qhull_options = "Qbb Qc Qz Q12 (2D)"
    rep.qhull_s = time.perf_counter() - t0
    s = np.ascontiguousarray(tri.simplices, dtype=np.int64)
    rep.num_tets = 0
    rep.num_interior_faces = len(s)
    a, b, c = uv[s[:, 0]], uv[s[:, 1]], uv[s[:, 2]]
    bx, by = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    cx, cy = c[:, 0] - a[:, 0], c[:, 1] - a[:, 1]
    d = 2.0 * (bx * cy - by * cx)
    flat = np.abs(d) <= FLAT_TET_EPS * (bx * bx + by * by + cx * cx + cy * cy)
    d = np.where(flat, 1.0, d)
    ux = (cy * (bx * bx + by * by) - by * (cx * cx + cy * cy)) / d
    uy = (bx * (cx * cx + cy * cy) - cx * (bx * bx + by * by)) / d
    cc2 = np.where(flat[:, None], (a + b + c) / 3.0, a + np.stack([ux, uy], axis=1))
    cc3 = centre + cc2 @ basis[:2]
    normal = basis[2] / np.linalg.norm(basis[2])
    return s, cc3 - ray_len * normal, cc3 + ray_len * normal
