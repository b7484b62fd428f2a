"""Validated numpy arrays of a triangle mesh: the one input check the mesh tools share."""
from __future__ import annotations

import numpy as np


def mesh_arrays(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """vertices as float64 [V,3] and faces as int64 [F,3], or a ValueError saying what is wrong."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be [V,3], got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be [F,3], got shape {f.shape}")
    f = f.astype(np.int64)
    V = len(v)
    if f.size and (f.min() < 0 or f.max() >= V):
        raise ValueError(f"face index out of range [0, {V}): min {f.min()}, max {f.max()}")
    return v, f
