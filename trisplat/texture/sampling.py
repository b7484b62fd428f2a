"""Bilinear texture lookups as OpenGL / glTF define them: texel centres at ((i + 0.5) / W, (j + 0.5) / H), uv (0, 0)
at the top-left corner of the image's first row, wrap modes CLAMP_TO_EDGE, REPEAT, MIRRORED_REPEAT."""
from __future__ import annotations

import numpy as np

from trisplat.io.gltf import GL_CLAMP_TO_EDGE, GL_MIRRORED_REPEAT, GL_REPEAT


def _wrap(i: np.ndarray, n: int, mode: int) -> np.ndarray:
    if mode == GL_CLAMP_TO_EDGE:
        return np.clip(i, 0, n - 1)
    if mode == GL_REPEAT:
        return np.mod(i, n)
    if mode == GL_MIRRORED_REPEAT:
        m = np.mod(i, 2 * n)
        return np.where(m < n, m, 2 * n - 1 - m)
    raise ValueError(f"unknown wrap mode {mode}")


def bilinear_taps(uv: np.ndarray, width: int, height: int, wrap: tuple[int, int] = (GL_CLAMP_TO_EDGE, GL_CLAMP_TO_EDGE)
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The four texels a bilinear lookup at each uv [N,2] reads and their weights: (flat index row * width + column
    int64 [N,4], weight float32 [N,4], summing to 1)."""
    x = np.asarray(uv[:, 0], np.float64) * width - 0.5
    y = np.asarray(uv[:, 1], np.float64) * height - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    xa, xb = _wrap(x0, width, wrap[0]), _wrap(x0 + 1, width, wrap[0])
    ya, yb = _wrap(y0, height, wrap[1]), _wrap(y0 + 1, height, wrap[1])
    idx = np.stack([ya * width + xa, ya * width + xb, yb * width + xa, yb * width + xb], 1)
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    return idx, w


def sample_bilinear(image: np.ndarray, uv: np.ndarray, wrap: tuple[int, int] = (GL_CLAMP_TO_EDGE, GL_CLAMP_TO_EDGE)
                    ) -> np.ndarray:
    """Bilinear lookups of a float image [H,W,C] at uv [N,2] -> [N,C] (filtering in whatever space `image` is:
    glTF filters colour textures after decoding them to linear)."""
    h, w = image.shape[:2]
    idx, wt = bilinear_taps(uv, w, h, wrap)
    flat = image.reshape(h * w, -1)
    return np.einsum("nk,nkc->nc", wt, flat[idx])
