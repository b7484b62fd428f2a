"""Consistent face orientation: flip faces so that neighbours across every manifold edge agree, outward when closed.

Faces are walked breadth-first across manifold edges (edges used by exactly two faces); a neighbour is flipped when
it traverses the shared edge in the same direction as the face it was reached from. Each connected piece is then
turned as a whole: outward (positive signed volume) when it is closed, otherwise towards the majority of the
optional hint normals, otherwise outward by signed volume about its centroid. With `hint_closed`, the hints turn
closed pieces too (a room closed around the cameras faces into itself: its outward side is the one nobody sees).
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np


@dataclass(frozen=True)
class EdgeTable:
    """Undirected edges of a face list.

    edges: int64 [E,2] (a < b). face_edges: int64 [F,3] edge id of the face's edges (v0v1, v1v2, v2v0).
    edge_face_count: int64 [E] number of faces using each edge.
    """

    edges: np.ndarray
    face_edges: np.ndarray
    edge_face_count: np.ndarray


def edge_table(faces: np.ndarray) -> EdgeTable:
    """Unique undirected edges of `faces` [F,3] and how many faces use each."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    und = np.sort(directed, axis=1)
    if len(und) == 0:
        return EdgeTable(np.zeros((0, 2), np.int64), np.zeros((0, 3), np.int64), np.zeros(0, np.int64))
    n = np.int64(und.max()) + 1
    keys, inverse, counts = np.unique(und[:, 0] * n + und[:, 1], return_inverse=True, return_counts=True)
    edges = np.stack([keys // n, keys % n], axis=1)
    return EdgeTable(edges, inverse.reshape(-1, 3).astype(np.int64), counts.astype(np.int64))


@nb.njit(cache=True)
def _pair_slots(edge_of, edge_face_count):
    """For every edge used by exactly two faces, its two slots (3*face + k) in first-seen order."""
    first = np.full(edge_face_count.shape[0], -1, np.int64)
    pairs = np.empty((edge_of.shape[0] // 2 + 1, 2), np.int64)
    n = 0
    for slot in range(edge_of.shape[0]):
        e = edge_of[slot]
        if edge_face_count[e] != 2:
            continue
        if first[e] < 0:
            first[e] = slot
        else:
            pairs[n, 0] = first[e]
            pairs[n, 1] = slot
            n += 1
    return pairs[:n]


def _manifold_pairs(faces: np.ndarray, table: EdgeTable):
    """Face pairs across manifold edges and whether they traverse the shared edge in the same direction."""
    F = len(faces)
    slots = _pair_slots(table.face_edges.reshape(-1), table.edge_face_count)
    fa, fb = slots[:, 0] // 3, slots[:, 1] // 3
    start = faces.reshape(-1)  # directed edge at slot s starts at faces[f, k]
    same_dir = start[slots[:, 0]] == start[slots[:, 1]]
    keep = fa != fb
    return fa[keep], fb[keep], same_dir[keep], F


@nb.njit(cache=True)
def _csr(F, fa, fb, same_dir):
    """Symmetric face adjacency in CSR form (counting sort), with the parity of each link."""
    indptr = np.zeros(F + 1, np.int64)
    for k in range(fa.shape[0]):
        indptr[fa[k] + 1] += 1
        indptr[fb[k] + 1] += 1
    for f in range(F):
        indptr[f + 1] += indptr[f]
    fill = indptr[:-1].copy()
    nbr = np.empty(2 * fa.shape[0], np.int64)
    par = np.empty(2 * fa.shape[0], np.bool_)
    for k in range(fa.shape[0]):
        a, b = fa[k], fb[k]
        nbr[fill[a]] = b
        par[fill[a]] = same_dir[k]
        fill[a] += 1
        nbr[fill[b]] = a
        par[fill[b]] = same_dir[k]
        fill[b] += 1
    return indptr, nbr, par


@nb.njit(cache=True)
def _bfs_flip(F, indptr, nbr, parity):
    flip = np.zeros(F, np.bool_)
    comp = np.full(F, -1, np.int64)
    queue = np.empty(F, np.int64)
    n_comp = 0
    for seed in range(F):
        if comp[seed] >= 0:
            continue
        comp[seed] = n_comp
        head = 0
        tail = 0
        queue[tail] = seed
        tail += 1
        while head < tail:
            f = queue[head]
            head += 1
            for j in range(indptr[f], indptr[f + 1]):
                g = nbr[j]
                if comp[g] < 0:
                    comp[g] = n_comp
                    flip[g] = flip[f] ^ parity[j]
                    queue[tail] = g
                    tail += 1
        n_comp += 1
    return flip, comp, n_comp


@dataclass(frozen=True)
class OrientReport:
    """What `orient_faces` did: flipped faces, face-connected pieces, and manifold edges it could not make agree
    (non-zero only on non-orientable pieces such as a Moebius strip)."""

    num_flipped: int
    num_pieces: int
    num_conflicting_edges: int


def orient_faces(vertices: np.ndarray, faces: np.ndarray, hint_normals: np.ndarray | None = None,
                 hint_closed: bool = False) -> tuple[np.ndarray, OrientReport]:
    """Consistently oriented copy of `faces` [F,3] (int32), and a report.

    vertices: [V,3]. hint_normals: optional [F,3] preferred normal direction per face (need not be unit; zero rows
    abstain), used to turn open pieces, and closed ones too with hint_closed (each face's vote weighs its area).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    F = len(faces)
    if F == 0:
        return faces.astype(np.int32), OrientReport(0, 0, 0)
    table = edge_table(faces)
    fa, fb, same_dir, _ = _manifold_pairs(faces, table)
    # symmetric adjacency; parity = the two faces need opposite flips to agree
    indptr, nbr, par = _csr(F, fa, fb, same_dir)
    flip, comp, n_comp = _bfs_flip(F, indptr, nbr, par)

    # orient each piece as a whole
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # 2 * area * normal, before flips
    sign = np.where(flip, -1.0, 1.0)
    closed_edge = table.edge_face_count == 2
    piece_closed = np.ones(n_comp, bool)
    open_faces = ~closed_edge[table.face_edges].all(axis=1)
    piece_closed[np.unique(comp[open_faces])] = False
    piece_centroid = np.zeros((n_comp, 3))
    for k in range(3):
        piece_centroid[:, k] = np.bincount(comp, weights=tri[:, :, k].mean(axis=1), minlength=n_comp)
    piece_centroid /= np.maximum(np.bincount(comp, minlength=n_comp), 1)[:, None]
    rel = tri[:, 0] - piece_centroid[comp]
    volume = np.bincount(comp, weights=sign * np.einsum("ij,ij->i", rel, cross), minlength=n_comp)
    turn = volume < 0
    if hint_normals is not None:
        hint = np.asarray(hint_normals, dtype=np.float64).reshape(F, 3)
        area = np.linalg.norm(cross, axis=1)
        vote = np.bincount(comp, weights=sign * area * np.sign(np.einsum("ij,ij->i", hint, cross)), minlength=n_comp)
        use_hint = (vote != 0) if hint_closed else ~piece_closed & (vote != 0)
        turn = np.where(use_hint, vote < 0, turn)
    flip ^= turn[comp]
    out = faces.copy()
    out[flip] = out[flip][:, ::-1]
    # manifold edges still traversed twice in the same direction
    conflicts = int(np.count_nonzero(same_dir ^ (flip[fa] ^ flip[fb])))
    return out.astype(np.int32), OrientReport(int(flip.sum()), int(n_comp), conflicts)
