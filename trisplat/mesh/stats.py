"""Mesh statistics: counts, vertex/face ratio, valence, boundary and non-manifold edges, pieces, watertightness."""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from trisplat.mesh.arrays import mesh_arrays
from trisplat.mesh.bvh import build_bvh, segment_any_hit
from trisplat.mesh.cleanup import face_areas, face_components
from trisplat.mesh.orient import edge_table

SELF_INTERSECTION_MAX_FACES = 5_000_000  # above this many faces the self-intersection test is skipped (None)


@dataclass
class MeshStats:
    """Statistics of a triangle mesh. Edges are undirected vertex pairs; a boundary edge has one face, a
    non-manifold edge three or more. Pieces are vertex-connected."""

    num_vertices: int
    num_faces: int
    num_edges: int
    num_unreferenced_vertices: int
    vertex_face_ratio: float  # num_vertices / num_faces (closed manifold ~0.5, unconnected soup 3.0)
    valence_mean: float  # mean number of edges at a referenced vertex
    valence_histogram: dict[int, int]  # valence -> number of referenced vertices
    boundary_edges: int
    non_manifold_edges: int
    non_manifold_edge_fraction: float  # non_manifold_edges / num_edges
    connected_components: int
    largest_component_faces: int  # faces of the largest vertex-connected piece
    largest_component_fraction: float  # ... as a share of all faces (1.0 = one piece)
    watertight: bool  # every edge has exactly two faces
    consistently_oriented: bool  # every two-face edge is traversed once in each direction
    euler_characteristic: int  # referenced vertices - edges + faces
    genus: int | None  # total genus when watertight and consistently oriented, else None
    degenerate_faces: int  # faces repeating a vertex or with zero area
    duplicate_faces: int  # faces using the same three vertices as another
    self_intersecting_edges: int | None  # edges crossing a face that has neither endpoint; None when skipped
    surface_area: float
    bbox_diagonal: float

    def to_dict(self) -> dict:
        d = asdict(self)
        d["valence_histogram"] = {str(k): v for k, v in self.valence_histogram.items()}
        return d


def self_intersecting_edges(vertices: np.ndarray, faces: np.ndarray, edges: np.ndarray | None = None) -> int:
    """Number of mesh edges that cross a face containing neither of their endpoints (BVH + segment test).
    Coplanar overlaps and faces crossing only at a shared vertex are not counted."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if edges is None:
        edges = edge_table(faces).edges
    if len(edges) == 0:
        return 0
    v = np.asarray(vertices, dtype=np.float64)
    hit = segment_any_hit(build_bvh(v, faces), v[edges[:, 0]], v[edges[:, 1]], exclude=edges)
    return int(np.count_nonzero(hit >= 0))


def mesh_statistics(vertices: np.ndarray, faces: np.ndarray, check_self_intersections: bool = True) -> MeshStats:
    """Statistics of the mesh (vertices [V,3], faces int [F,3])."""
    v, f = mesh_arrays(vertices, faces)
    V, F = len(v), len(f)
    table = edge_table(f)
    E = len(table.edges)
    used = np.zeros(V, bool)
    used[f.reshape(-1)] = True
    n_used = int(used.sum())

    valence = np.bincount(table.edges.reshape(-1), minlength=V)[used]
    vals, counts = np.unique(valence, return_counts=True)
    boundary = int(np.count_nonzero(table.edge_face_count == 1))
    non_manifold = int(np.count_nonzero(table.edge_face_count > 2))
    watertight = F > 0 and boundary == 0 and non_manifold == 0

    # orientation: every two-face edge should appear once as (a,b) and once as (b,a)
    directed = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    forward = (directed[:, 0] < directed[:, 1]).astype(np.int64)
    eid = table.face_edges.reshape(-1)
    fwd_count = np.bincount(eid, weights=forward, minlength=E)
    two = table.edge_face_count == 2
    consistent = bool(np.all(fwd_count[two] == 1))

    n_comp, label = face_components(f, V)
    largest = int(np.bincount(label).max()) if F else 0
    chi = n_used - E + F
    genus = (2 * n_comp - chi) // 2 if (watertight and consistent) else None
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    area = face_areas(v, f)
    degenerate |= area <= 0
    dup = F - len(np.unique(np.sort(f, axis=1), axis=0)) if F else 0
    si = None
    if check_self_intersections and F <= SELF_INTERSECTION_MAX_FACES:
        si = self_intersecting_edges(v, f, table.edges)
    diag = float(np.linalg.norm(v[used].max(axis=0) - v[used].min(axis=0))) if n_used else 0.0
    return MeshStats(
        num_vertices=V,
        num_faces=F,
        num_edges=E,
        num_unreferenced_vertices=V - n_used,
        vertex_face_ratio=V / F if F else float("inf"),
        valence_mean=float(valence.mean()) if n_used else 0.0,
        valence_histogram={int(a): int(b) for a, b in zip(vals, counts)},
        boundary_edges=boundary,
        non_manifold_edges=non_manifold,
        non_manifold_edge_fraction=non_manifold / E if E else 0.0,
        connected_components=n_comp,
        largest_component_faces=largest,
        largest_component_fraction=largest / F if F else 0.0,
        watertight=bool(watertight),
        consistently_oriented=consistent,
        euler_characteristic=int(chi),
        genus=None if genus is None else int(genus),
        degenerate_faces=int(degenerate.sum()),
        duplicate_faces=int(dup),
        self_intersecting_edges=si,
        surface_area=float(area.sum()),
        bbox_diagonal=diag,
    )
