"""Scores by layer: which part of a real capture's mesh each test pixel shows (the connected surface, the far-field
layer beyond it, the background sphere behind all, or nothing) and the PSNR of those pixels, so a run says where its
error is (docs/benchmarks.md, issue 24: bonsai's far field shows in 68% of the test pixels and holds 83% of what the
switch loses)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LAYERS = ("surface", "far_field", "background_sphere", "empty")


def layer_labels(face_id: np.ndarray, num_faces: int, far_faces: int, background_faces: int) -> np.ndarray:
    """int8 array like face_id: the index in LAYERS of the layer each pixel shows. The face table of a run with a
    far field is [surface; far field], the background sphere its last `background_faces` rows (docs/conventions.md);
    face_id -1 is an empty pixel."""
    if not 0 <= background_faces <= far_faces <= num_faces:
        raise ValueError(f"layer sizes must satisfy 0 <= background_faces ({background_faces}) <= far_faces "
                         f"({far_faces}) <= num_faces ({num_faces})")
    fid = np.asarray(face_id)
    if fid.size and (fid.max() >= num_faces or fid.min() < -1):
        raise ValueError(f"face ids must lie in [-1, {num_faces - 1}], got {fid.min()}..{fid.max()}")
    labels = np.full(fid.shape, LAYERS.index("surface"), np.int8)
    labels[fid >= num_faces - far_faces] = LAYERS.index("far_field")
    labels[fid >= num_faces - background_faces] = LAYERS.index("background_sphere")
    labels[fid < 0] = LAYERS.index("empty")
    return labels


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
