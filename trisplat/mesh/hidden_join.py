"""Pieces of the seen surface that stand apart, joined to the main one through the nearest hidden surface.

A fused surface bounds everything the views did not see as solid (`trisplat.mesh.contracted_fusion`: inside some
view, never observed), so between a table whose lower cloth no photo shows and the floor there is hidden surface:
the sides of that solid. The switch drops unseen faces but the hidden sides that face something seen and join
two seen pieces (`trisplat.train.switch.hidden_bridges`). That rule misses a hidden side that faces more hidden
surface (bonsai's cloth-draped table, 0.53 above the floor in two 30-minute runs of three: its hidden skirt looks
out at the unseen backs of the room's furniture, so the tree and its table, 31% of the test pixels, stayed a piece
apart; issue 49). The same holds for a room scanned by SLAM: chairs whose joins to the floor were not seen.

Here each piece that stands apart (at least `min_piece` x the main piece's faces) is joined to the main piece by
the hidden surface nearest to it: the geodesic distance d from the piece over the hidden faces' edges to the main
piece is found (Dijkstra, scipy), and, when d is at most `size_factor` x the piece's own size (the diagonal of its
bounding box: the hidden side of an object is no larger than the object), every hidden face within d of the piece
is kept. That is the piece's hidden skirt all round down to where it meets the main piece (not a thin strip), and
the hidden floor around its foot. Pieces are joined largest first; a piece joined becomes part of the main one.

With the capture's floor known (`trisplat.mesh.ground.Ground`), the piece is joined where the main piece meets the
floor when that is within reach: it stands on the floor, not on whatever hidden surface of the room comes nearest
(bonsai: the table's skirt reaches the room 0.29 away, 0.27 above the floor, and the floor 0.62 away).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from trisplat.mesh.cleanup import face_components
from trisplat.mesh.orient import edge_table

SIZE_FACTOR = 1.0
FLOOR_TOLERANCE = 0.05  # a vertex of the main piece this close to the floor plane is on the floor (world units)


def _edge_graph(verts: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Sparse graph of the faces' edges (each once, a < b), weighted by their length (dijkstra reads it undirected)."""
    e = edge_table(faces).edges
    w = np.maximum(np.linalg.norm(verts[e[:, 0]] - verts[e[:, 1]], axis=1), 1e-12)  # (a zero weight reads as no edge)
    return sp.csr_matrix((w, (e[:, 0], e[:, 1])), shape=(len(verts), len(verts)))


def join_through_hidden(verts: np.ndarray, faces: np.ndarray, hidden: np.ndarray, min_piece: float = 0.0,
                        size_factor: float = SIZE_FACTOR, ground=None,
                        floor_tolerance: float = FLOOR_TOLERANCE) -> tuple[np.ndarray, list[dict]]:
    """bool [F]: the `hidden` faces (bool [F]) to keep so that the pieces of the other faces stand joined to the
    largest (see the module docstring), and one record per piece joined (its faces, size, distance, whether it
    stands on the floor, hidden faces kept). verts float [V,3] (world units), faces int [F,3]; ground: an object
    with `up` and `height` (the floor plane x . up = height) or None."""
    verts = np.asarray(verts, np.float64)
    faces = np.asarray(faces, np.int64)
    keep = np.zeros(len(faces), dtype=bool)
    shown = ~hidden
    if not hidden.any() or not shown.any():
        return keep, []
    n, label = face_components(faces[shown], len(verts))
    if n < 2:
        return keep, []
    size = np.bincount(label, minlength=n)
    main = int(np.argmax(size))
    piece = np.full(len(verts), -1, dtype=np.int64)
    piece[faces[shown].ravel()] = np.repeat(label, 3)  # (pieces are vertex-connected: one piece a vertex)
    in_main = piece == main
    on_floor = np.zeros(len(verts), dtype=bool)
    if ground is not None:
        on_floor = np.abs(verts @ np.asarray(ground.up, np.float64) - float(ground.height)) <= floor_tolerance
    hf = faces[hidden]
    on_graph = np.zeros(len(verts), dtype=bool)
    on_graph[hf.ravel()] = True
    graph = None
    joined = []
    for p in np.argsort(-size):
        if p == main or size[p] < min_piece * size[main]:
            continue
        src = np.nonzero((piece == p) & on_graph)[0]
        if len(src) == 0:
            continue
        pv = verts[piece == p]
        extent = float(np.linalg.norm(pv.max(0) - pv.min(0)))
        if graph is None:
            graph = _edge_graph(verts, hf)
        dist = dijkstra(graph, directed=False, indices=src, min_only=True, limit=size_factor * extent)
        reach = in_main & np.isfinite(dist)
        if not reach.any():
            continue
        floor = reach & on_floor
        d = float(dist[floor].min() if floor.any() else dist[reach].min())
        sel = dist[hf].min(1) <= d  # (unreached vertices are at inf)
        new = np.nonzero(hidden)[0][sel]
        keep[new] = True
        in_main |= piece == p
        in_main[hf[sel].ravel()] = True
        joined.append(dict(faces=int(size[p]), size=round(extent, 4), distance=round(d, 4),
                           floor=bool(floor.any()), hidden_faces=int(len(new))))
    return keep, joined
