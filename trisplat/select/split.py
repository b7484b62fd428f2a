"""Split a mesh by a face selection into two compact meshes (unused vertices dropped, faces re-indexed)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MeshPart:
    """A compact sub-mesh: positions [V',3], faces int32 [F',3], colors [V',3] or None,
    and vertex_index int64 [V'] / face_index int64 [F'] into the source mesh."""

    positions: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None
    vertex_index: np.ndarray
    face_index: np.ndarray


def submesh(positions: np.ndarray, faces: np.ndarray, colors: np.ndarray | None, keep: np.ndarray) -> MeshPart:
    """The faces where `keep` [F] is True, with only the vertices they use."""
    faces = np.asarray(faces, dtype=np.int64)
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != (len(faces),):
        raise ValueError(f"face selection must be bool [F]={len(faces)}, got {keep.shape}")
    face_index = np.nonzero(keep)[0]
    used = np.unique(faces[face_index])
    remap = np.full(len(positions), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return MeshPart(
        positions=np.asarray(positions)[used],
        faces=remap[faces[face_index]].astype(np.int32),
        colors=None if colors is None else np.asarray(colors)[used],
        vertex_index=used,
        face_index=face_index,
    )


def split_mesh(positions, faces, colors, selected) -> tuple[MeshPart, MeshPart]:
    """(selected part, remainder): every face lands in exactly one; vertices on the cut appear in both."""
    selected = np.asarray(selected, dtype=bool)
    return submesh(positions, faces, colors, selected), submesh(positions, faces, colors, ~selected)
