"""UV atlas of a triangle mesh (xatlas): charts cut and flattened, packed into one square texture with gutters."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ATLAS_PIECE_FACES = 20_000  # xatlas is given the mesh in spatial pieces of at most this many faces (it crashed on a
#                             327k-face sphere in one piece, and its chart growth is superlinear in the piece size:
#                             lego's 275k-face surface at 2048 took 33 s in pieces of 40k faces, 22 s in pieces of
#                             20k or 10k, with 14,089 / 14,112 / 14,357 charts and 31% of the texels inside them)
ATLAS_PADDING = 4  # texels of gutter xatlas keeps between charts (bilinear taps and the first mip levels stay inside)


@dataclass(frozen=True)
class Atlas:
    """uv [U,2] in [0,1] (glTF convention: v down, texel centres at (i + 0.5) / size), uv_faces [F,3] rows of uv
    per face corner (the mesh's faces in the same order), size: texture side in texels, charts [F] chart id per
    face (faces of one chart share uv rows along their edges)."""

    uv: np.ndarray
    uv_faces: np.ndarray
    size: int
    charts: np.ndarray


def _pieces(centroids: np.ndarray, max_faces: int) -> list[np.ndarray]:
    """Face index sets of at most max_faces faces: recursive median splits along the longest box side."""
    out, stack = [], [np.arange(len(centroids))]
    while stack:
        idx = stack.pop()
        if len(idx) <= max_faces:
            out.append(idx)
            continue
        c = centroids[idx]
        axis = int(np.argmax(c.max(0) - c.min(0)))
        order = np.argsort(c[:, axis], kind="stable")
        half = len(idx) // 2
        stack += [np.sort(idx[order[:half]]), np.sort(idx[order[half:]])]
    return out


def build_atlas(positions: np.ndarray, faces: np.ndarray, size: int, padding: int = ATLAS_PADDING,
                piece_faces: int = ATLAS_PIECE_FACES) -> Atlas:
    """Charts and packing by xatlas for a `size` x `size` texture. The mesh is split into spatial pieces of at most
    `piece_faces` faces first (their borders become chart borders)."""
    import xatlas
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    positions = np.asarray(positions, np.float32)
    faces = np.asarray(faces, np.int64)
    atlas = xatlas.Atlas()
    pieces = _pieces(positions[faces].mean(1), piece_faces)
    for idx in pieces:
        used, local = np.unique(faces[idx], return_inverse=True)
        atlas.add_mesh(np.ascontiguousarray(positions[used]), np.ascontiguousarray(local.reshape(-1, 3), np.uint32))
    chart_opts = xatlas.ChartOptions()
    chart_opts.max_iterations = 1
    pack = xatlas.PackOptions()
    pack.resolution = int(size)
    pack.padding = int(padding)
    pack.bilinear = True
    pack.bruteForce = False
    atlas.generate(chart_opts, pack)
    if atlas.atlas_count != 1:
        raise RuntimeError(f"xatlas packed the charts into {atlas.atlas_count} textures, expected one")
    uv_rows, uv_faces = [], np.empty_like(faces)
    offset = 0
    for k, idx in enumerate(pieces):
        vmap, ind, uv = atlas.get_mesh(k)
        used = np.unique(faces[idx])
        ind = np.asarray(ind, np.int64).reshape(-1, 3)
        if ind.shape[0] != len(idx) or not np.array_equal(used[np.asarray(vmap, np.int64)[ind]], faces[idx]):
            raise RuntimeError("xatlas changed the faces of a piece (order or count)")
        uv_faces[idx] = ind + offset
        uv_rows.append(np.asarray(uv, np.float64))
        offset += len(uv)
    uv = np.concatenate(uv_rows)
    w, h = atlas.width, atlas.height
    uv *= np.array([w, h], np.float64) / max(w, h)  # xatlas's uv fill its w x h rectangle: keep texels square
    n = len(uv)
    e = np.concatenate([uv_faces[:, [0, 1]], uv_faces[:, [1, 2]], uv_faces[:, [2, 0]]])
    _, labels = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)
    return Atlas(uv=uv, uv_faces=uv_faces, size=int(size), charts=labels[uv_faces[:, 0]])
