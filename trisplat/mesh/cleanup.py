"""Mesh cleanup: weld coincident vertices, drop degenerate and duplicate faces, orient, remove small fragments.

Every step keeps index maps so a caller can carry per-vertex attributes (SH, opacity) along:
`new_attr = old_attr[result.vertex_source]` and per-face ones with `result.face_source`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from trisplat.mesh.arrays import mesh_arrays
from trisplat.mesh.orient import orient_faces


@dataclass(frozen=True)
class CleanupConfig:
    """Cleanup settings. Lengths in the mesh's units."""

    weld: bool = True
    """merge coincident vertices (see weld_tolerance); False leaves the vertex table as it is."""
    weld_tolerance: float = 0.0
    """vertices closer than this are merged into one (scene units); 0 merges only exactly equal positions."""
    min_face_area: float = 0.0
    """faces with area <= this are degenerate and dropped (scene units^2); faces repeating a vertex always are."""
    drop_duplicate_faces: bool = True
    """drop faces using the same three vertices as an earlier face (either winding)."""
    repair_non_manifold_edges: bool = False
    """at every edge with more than two faces keep the two best-shaped faces (aspect quality) and drop the rest."""
    repair_keeps_orientation: bool = False
    """with repair_non_manifold_edges, on a consistently oriented input: of the faces at an over-full edge keep the
    best-shaped one traversing it each way, so the kept faces stay consistently oriented."""
    orient: bool = True
    """flip faces so neighbours agree, then turn each piece (see orient_by)."""
    orient_by: Literal["volume", "winding"] = "volume"
    """'volume': closed pieces outward (positive signed volume), open ones outward about their centroid; 'winding':
    every piece, closed or open, towards the majority (by area) of its faces' winding as given. A surface fused from
    depth maps is wound towards the free space the cameras looked through, so its majority is right where the
    volume rule is not: a room seen from inside faces into the room, its outward side is the one nobody sees."""
    min_component_faces: int = 0
    """drop vertex-connected pieces with fewer faces than this (count); 0 keeps all."""
    min_component_area_fraction: float = 0.0
    """drop pieces whose area is below this fraction of the total area (dimensionless, 0..1); 0 keeps all."""
    drop_unreferenced_vertices: bool = True
    """compact the vertex table to the vertices some face uses; False keeps every (welded) vertex."""


@dataclass
class CleanupResult:
    """Output of `clean_mesh`.

    vertices: float [V',3]; faces: int32 [F',3].
    vertex_source: int64 [V'] input vertex each output vertex comes from (the lowest index of a welded group).
    vertex_map: int64 [V] output vertex of each input vertex, -1 when dropped.
    face_source: int64 [F'] input face each output face comes from.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_source: np.ndarray
    vertex_map: np.ndarray
    face_source: np.ndarray
    num_welded: int = 0  # input vertices merged into another
    num_degenerate_faces: int = 0
    num_duplicate_faces: int = 0
    num_non_manifold_faces: int = 0  # faces dropped to make every edge have at most two faces
    num_fragment_faces: int = 0  # faces removed with small pieces
    num_fragments: int = 0  # pieces removed
    num_flipped: int = 0
    num_unreferenced_vertices: int = 0  # dropped (or, when kept, present) vertices no face uses


def weld_vertices(vertices: np.ndarray, tolerance: float = 0.0) -> np.ndarray:
    """Representative (lowest index) of each vertex's group, int64 [V]: groups are the connected components of
    "closer than `tolerance`" (exactly equal positions when tolerance is 0)."""
    v = np.asarray(vertices, dtype=np.float64)
    V = len(v)
    if V == 0:
        return np.zeros(0, np.int64)
    if tolerance < 0:
        raise ValueError(f"weld_tolerance must be >= 0, got {tolerance}")
    if tolerance == 0:
        _, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
        return first[inverse.reshape(-1)].astype(np.int64)
    pairs = cKDTree(v).query_pairs(tolerance, output_type="ndarray")
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(V, V))
    _, labels = connected_components(graph, directed=False)
    rep = np.full(labels.max() + 1, V, np.int64)
    np.minimum.at(rep, labels, np.arange(V))
    return rep[labels]


def face_components(faces: np.ndarray, num_vertices: int) -> tuple[int, np.ndarray]:
    """Vertex-connected pieces: (count, label int64 [F] per face)."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return 0, np.zeros(0, np.int64)
    a = faces[:, [0, 1]].reshape(-1)
    b = faces[:, [1, 2]].reshape(-1)
    graph = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(num_vertices, num_vertices))
    _, labels = connected_components(graph, directed=False)
    used, lab = np.unique(labels[faces[:, 0]], return_inverse=True)
    return len(used), lab.reshape(-1).astype(np.int64)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64).reshape(-1, 3)]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def face_quality(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Aspect quality per face in [0,1]: 4*sqrt(3)*area / (sum of squared edge lengths); 1 = equilateral."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64).reshape(-1, 3)]
    e = tri[:, [1, 2, 0]] - tri
    sq = np.einsum("fkj,fkj->f", e, e)
    return np.where(sq > 0, 4.0 * np.sqrt(3.0) * face_areas(vertices, faces) / np.maximum(sq, 1e-300), 0.0)


def non_manifold_excess_faces(vertices: np.ndarray, faces: np.ndarray, max_rounds: int = 8,
                              oriented: bool = False) -> np.ndarray:
    """bool [F]: faces to drop so that no edge has more than two faces; at each over-full edge the two faces of best
    `face_quality` stay (repeated while dropping one face leaves another edge over-full, at most `max_rounds`).
    oriented: the faces are consistently oriented (as marching cubes and quadric decimation leave them), and stay so:
    at each over-full edge the best face traversing it in each direction stays (one face where all go one way)."""
    from trisplat.mesh.orient import edge_table

    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    drop = np.zeros(len(faces), bool)
    quality = face_quality(vertices, faces)
    for _ in range(max_rounds):
        alive = np.nonzero(~drop)[0]
        table = edge_table(faces[alive])
        slots = np.nonzero(table.edge_face_count[table.face_edges.reshape(-1)] > 2)[0]
        if len(slots) == 0:
            break
        edge = table.face_edges.reshape(-1)[slots]
        face = alive[slots // 3]
        if oriented:  # one group per (edge, direction): keep the best face of each
            a = faces[face, slots % 3]
            forward = a == table.edges[edge, 0]
            edge = 2 * edge + forward
        order = np.lexsort((-quality[face], edge))  # by edge, best quality first
        edge, face = edge[order], face[order]
        first = np.r_[True, edge[1:] != edge[:-1]]
        rank = np.arange(len(edge)) - np.maximum.accumulate(np.where(first, np.arange(len(edge)), 0))
        drop[face[rank >= (1 if oriented else 2)]] = True
    return drop


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, config: CleanupConfig = CleanupConfig()) -> CleanupResult:
    """Apply the cleanup steps of `config` in order: weld, drop degenerate, drop duplicates, remove fragments,
    orient, compact. vertices [V,3]; faces int [F,3]."""
    v, f = mesh_arrays(vertices, faces)
    V = len(v)
    if not 0.0 <= config.min_component_area_fraction <= 1.0:
        raise ValueError(f"min_component_area_fraction must be in [0, 1], got {config.min_component_area_fraction}")
    face_src = np.arange(len(f), dtype=np.int64)

    rep = weld_vertices(v, config.weld_tolerance) if config.weld else np.arange(V, dtype=np.int64)
    num_welded = int(np.count_nonzero(rep != np.arange(V)))
    f = rep[f]

    area = face_areas(v, f)
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2]) | (area <= config.min_face_area)
    f, face_src, area = f[~degenerate], face_src[~degenerate], area[~degenerate]

    num_dup = 0
    if config.drop_duplicate_faces and len(f):
        _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
        first = np.sort(first)
        num_dup = len(f) - len(first)
        f, face_src, area = f[first], face_src[first], area[first]

    num_nm = 0
    if config.repair_non_manifold_edges and len(f):
        drop = non_manifold_excess_faces(v, f, oriented=config.repair_keeps_orientation)
        num_nm = int(drop.sum())
        f, face_src, area = f[~drop], face_src[~drop], area[~drop]

    num_frag_faces = num_frags = 0
    if (config.min_component_faces > 0 or config.min_component_area_fraction > 0) and len(f):
        n_comp, label = face_components(f, V)
        comp_faces = np.bincount(label, minlength=n_comp)
        comp_area = np.bincount(label, weights=area, minlength=n_comp)
        small = (comp_faces < config.min_component_faces) | (
            comp_area < config.min_component_area_fraction * max(area.sum(), 0.0))
        drop = small[label]
        num_frags, num_frag_faces = int(small.sum()), int(drop.sum())
        f, face_src = f[~drop], face_src[~drop]

    num_flipped = 0
    if config.orient and len(f):
        hint = None
        if config.orient_by == "winding":
            t = v[f]
            hint = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        f, orep = orient_faces(v, f, hint_normals=hint, hint_closed=config.orient_by == "winding")
        f = f.astype(np.int64)
        num_flipped = orep.num_flipped

    used = np.zeros(V, bool)
    used[f.reshape(-1)] = True
    is_rep = rep == np.arange(V)
    keep_v = used if config.drop_unreferenced_vertices else is_rep
    vertex_source = np.nonzero(keep_v)[0].astype(np.int64)
    new_index = np.full(V, -1, np.int64)
    new_index[vertex_source] = np.arange(len(vertex_source))
    vertex_map = new_index[rep]
    return CleanupResult(
        vertices=v[vertex_source].astype(np.asarray(vertices).dtype if np.asarray(vertices).dtype.kind == "f"
                                         else np.float64),
        faces=new_index[f].astype(np.int32).reshape(-1, 3),
        vertex_source=vertex_source,
        vertex_map=vertex_map,
        face_source=face_src,
        num_welded=num_welded,
        num_degenerate_faces=int(degenerate.sum()),
        num_duplicate_faces=num_dup,
        num_non_manifold_faces=num_nm,
        num_fragment_faces=num_frag_faces,
        num_fragments=num_frags,
        num_flipped=num_flipped,
        num_unreferenced_vertices=int(np.count_nonzero(is_rep & ~used)),
    )


def weld_near_pieces(vertices: np.ndarray, faces: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Join the vertex-connected pieces of a mesh that come within `distance` of one another (mesh units): for each
    pair of nearly touching pieces, the vertex of one nearest to the surface of the other is welded onto that
    surface, onto its nearest point (the face is split there) or onto the face's vertex when the point is one.
    Pieces of a fused surface that nearly touch (a stool's cloth within a voxel of the floor it stands on, split by
    the field's sampling) are one object; a pinch at one vertex makes them one piece without moving anything
    visibly. Rounds repeat until no more pieces join, so chains of touching pieces end up one. Returns vertices
    [V',3] (split points appended), faces [F',3] and how many joins were made. Nearest faces from a BVH
    (trisplat.mesh.bvh.nearest_other_triangle)."""
    from trisplat.mesh.bvh import build_bvh, nearest_other_triangle

    v = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    joins = 0
    for _ in range(64):
        n, label = face_components(faces, len(v))
        if n < 2:
            break
        piece = np.full(len(v), -1, np.int64)
        piece[faces.reshape(-1)] = np.repeat(label, 3)
        used = np.unique(faces.reshape(-1))
        t, d, q = nearest_other_triangle(build_bvh(v, faces), v[used], piece[used], label, float(distance))
        hit = t >= 0
        if not hit.any():
            break
        sv, t, d, q = used[hit], t[hit], d[hit], q[hit]
        pa, pb = piece[sv], label[t]
        lo, hi = np.minimum(pa, pb), np.maximum(pa, pb)
        # per pair of pieces, their nearest vertex and face; joins of one round go through union-find (a pair already
        # joined through others is skipped), and a face is split, a vertex moved, once per round
        order = np.lexsort((d, hi, lo))
        first = np.ones(len(order), bool)
        first[1:] = (lo[order][1:] != lo[order][:-1]) | (hi[order][1:] != hi[order][:-1])
        sel = order[first][np.argsort(d[order[first]], kind="stable")]
        parent = np.arange(n)
        remap = np.arange(len(v))
        busy = np.zeros(len(v), bool)
        new_v, new_f, split = [], [], []
        for k in sel:
            a, b, fi = _root(parent, pa[k]), _root(parent, pb[k]), int(t[k])
            tri = faces[fi]
            if a == b or busy[sv[k]] or busy[tri].any():
                continue
            at = np.nonzero(np.linalg.norm(v[tri] - q[k], axis=1) <= 1e-12 + 1e-9 * float(distance))[0]
            if len(at):
                remap[sv[k]] = tri[at[0]]  # the nearest point is a vertex: weld onto it
            else:
                idx = len(v) + len(new_v)
                new_v.append(q[k])
                split.append(fi)
                new_f += [[tri[0], tri[1], idx], [tri[1], tri[2], idx], [tri[2], tri[0], idx]]
                remap[sv[k]] = idx
            busy[sv[k]] = True
            busy[tri] = True
            parent[a] = b
            joins += 1
        if new_v:
            v = np.concatenate([v, np.asarray(new_v)])
            remap = np.concatenate([remap, np.arange(len(remap), len(v))])
        keep_f = np.ones(len(faces), bool)
        keep_f[split] = False
        faces = remap[np.concatenate([faces[keep_f], np.asarray(new_f, np.int64).reshape(-1, 3)])]
        good = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
        faces = faces[good]
    return v, faces, joins


def _root(parent: np.ndarray, x: int) -> int:
    """Union-find: the root of x (path halving)."""
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


def closest_points_on_triangles(p: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For points p [N,3] and triangles tri [N,3,3]: each triangle's point nearest to its point [N,3] and the
    distance [N] (the Voronoi-region cases of Ericson, Real-Time Collision Detection, 5.1.5, vectorised)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c

    def dot(x, y):
        return np.einsum("ij,ij->i", x, y)

    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        q = a + ab * (vb / den)[:, None] + ac * (vc / den)[:, None]  # inside the face
        cases = [
            (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None] * (c - b),
            (vb <= 0) & (d2 >= 0) & (d6 <= 0), a + (d2 / (d2 - d6))[:, None] * ac,
            (d6 >= 0) & (d5 <= d6), c,
            (vc <= 0) & (d1 >= 0) & (d3 <= 0), a + (d1 / (d1 - d3))[:, None] * ab,
            (d3 >= 0) & (d4 <= d3), b,
            (d1 <= 0) & (d2 <= 0), a,
        ]
    for k in range(0, len(cases), 2):  # later cases take precedence, as in Ericson's order of tests
        q = np.where(cases[k][:, None], cases[k + 1], q)
    q = np.where(np.isfinite(q), q, a)  # degenerate triangles: their first corner
    return q, np.linalg.norm(p - q, axis=1)


def simplify_parts(vertices: np.ndarray, faces: np.ndarray, part: np.ndarray, budgets) -> tuple[np.ndarray, np.ndarray]:
    """Each part of a mesh decimated to its own face budget, its borders locked (pyfqmr's quadric decimation with
    preserve_border), then the parts joined again: a locked border keeps its vertices' positions exactly, so the same
    position is the same vertex again. part: int [F], the part of each face; budgets: [P] faces of parts 0..P-1 (a part
    at or under its budget is left as it is; faces of other parts are dropped). Returns vertices [V',3] float64,
    faces [F',3] int64."""
    import pyfqmr

    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    parts_v, parts_f, offset = [], [], 0
    for r, budget in enumerate(budgets):
        sel = part == r
        if not sel.any():
            continue
        used, local = np.unique(faces[sel].reshape(-1), return_inverse=True)
        v, f = vertices[used], local.reshape(-1, 3)
        if len(f) > budget:
            simp = pyfqmr.Simplify()
            simp.setMesh(v, f.astype(np.int32))
            simp.simplify_mesh(target_count=int(budget), aggressiveness=7, preserve_border=True, verbose=False)
            v, f, _ = simp.getMesh()
        parts_v.append(np.asarray(v, np.float64))
        parts_f.append(np.asarray(f, np.int64) + offset)
        offset += len(v)
    if not parts_v:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    v, f = np.concatenate(parts_v), np.concatenate(parts_f)
    _, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
    return v[first], inverse.reshape(-1)[f]
