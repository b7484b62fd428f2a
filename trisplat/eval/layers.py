"""Scores by layer: which part of a real capture's mesh each test pixel shows (the connected surface, another piece
of it, the far-field soup beyond it, the background sphere behind all, or nothing) and the PSNR of those pixels, so
a run says where its error is and, above all, how much of what a user sees is ONE connected surface (issue 49: a run
whose largest piece by faces was a chunk of the room the test views barely saw reported `connected: true`).

"The surface" is the piece, among the mesh rows before the far-field layer, that shows the most test pixels, with
vertices at the same position merged (a viewer or a physics engine that welds coincident vertices sees the same
pieces); every other piece of those rows is "other_pieces"."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LAYERS = ("surface", "other_pieces", "far_field", "background_sphere", "empty")


def surface_pieces(positions: np.ndarray, faces: np.ndarray, surface_faces: int) -> np.ndarray:
    """int64 [surface_faces]: the vertex-connected piece of each of the first `surface_faces` faces (the rows before
    the far-field layer), vertices at exactly the same position merged."""
    from trisplat.mesh.cleanup import face_components

    f = np.asarray(faces, dtype=np.int64)[: int(surface_faces)]
    if len(f) == 0:
        return np.zeros(0, np.int64)
    used, local = np.unique(f.reshape(-1), return_inverse=True)
    _, merged = np.unique(np.asarray(positions)[used], axis=0, return_inverse=True)
    merged = merged.reshape(-1)
    return face_components(merged[local.reshape(-1)].reshape(-1, 3), int(merged.max()) + 1)[1]


def face_layers(num_faces: int, far_faces: int, background_faces: int, piece: np.ndarray | None = None,
                main_piece: int = 0) -> np.ndarray:
    """int8 [F]: the index in LAYERS of each face's layer. The face table of a run with a far field is
    [surface rows; far field], the background sphere its last `background_faces` rows (docs/conventions.md);
    piece [F - far_faces] (surface_pieces) splits the surface rows into `main_piece` (the surface) and the rest
    (other_pieces); None: all of them are the surface."""
    if not 0 <= background_faces <= far_faces <= num_faces:
        raise ValueError(f"layer sizes must satisfy 0 <= background_faces ({background_faces}) <= far_faces "
                         f"({far_faces}) <= num_faces ({num_faces})")
    out = np.full(num_faces, LAYERS.index("surface"), np.int8)
    n = num_faces - far_faces
    if piece is not None:
        if len(piece) != n:
            raise ValueError(f"piece labels must cover the {n} surface rows, got {len(piece)}")
        out[:n][np.asarray(piece) != main_piece] = LAYERS.index("other_pieces")
    out[n:] = LAYERS.index("far_field")
    out[num_faces - background_faces:] = LAYERS.index("background_sphere")
    return out


def layer_labels(face_id: np.ndarray, layer_of_face: np.ndarray) -> np.ndarray:
    """int8 array like face_id: the layer each pixel shows (layer_of_face [F]: face_layers); face_id -1 is an empty
    pixel."""
    fid = np.asarray(face_id)
    F = len(layer_of_face)
    if fid.size and (fid.max() >= F or fid.min() < -1):
        raise ValueError(f"face ids must lie in [-1, {F - 1}], got {fid.min()}..{fid.max()}")
    out = np.full(fid.shape, LAYERS.index("empty"), np.int8)
    hit = fid >= 0
    out[hit] = np.asarray(layer_of_face)[fid[hit]]
    return out


def main_piece(face_ids, piece: np.ndarray) -> int:
    """The piece (labels `piece` of the surface rows) that the most pixels of the face-id maps `face_ids` show."""
    n = len(piece)
    counts = np.zeros(int(piece.max()) + 1 if n else 1, np.int64)
    for fid in face_ids:
        f = np.asarray(fid).reshape(-1)
        f = f[(f >= 0) & (f < n)]
        counts += np.bincount(piece[f], minlength=len(counts))
    return int(counts.argmax())


@dataclass
class LayerScores:
    """Pixel counts and summed squared errors (mean over the colour channels) per layer, pooled over views."""

    pixels: np.ndarray = field(default_factory=lambda: np.zeros(len(LAYERS), np.int64))
    sq_error: np.ndarray = field(default_factory=lambda: np.zeros(len(LAYERS), np.float64))

    def add(self, labels: np.ndarray, render: np.ndarray, photo: np.ndarray) -> None:
        """One view: labels [H,W] (layer_labels), render and photo [H,W,3] in [0,1]."""
        err = ((np.asarray(render, np.float64) - np.asarray(photo, np.float64)) ** 2).mean(-1)
        lab = np.asarray(labels).reshape(-1)
        self.pixels += np.bincount(lab, minlength=len(LAYERS))
        self.sq_error += np.bincount(lab, weights=err.reshape(-1), minlength=len(LAYERS))

    def to_dict(self) -> dict:
        """{layer: {"pixels": share of the pixels, "psnr": dB of those pixels, pooled}} for the layers shown."""
        total = max(int(self.pixels.sum()), 1)
        out = {}
        for k, name in enumerate(LAYERS):
            if self.pixels[k]:
                mse = self.sq_error[k] / self.pixels[k]
                out[name] = {"pixels": float(self.pixels[k] / total),
                             "psnr": float(-10.0 * np.log10(max(mse, 1e-12)))}
        return out
