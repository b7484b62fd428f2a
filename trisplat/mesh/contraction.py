"""Scene contraction: the whole unbounded scene squeezed into a cube, so that one voxel grid holds the near table and
the far walls at about the same cost per object.

The map is Mip-NeRF 360's contraction with the L-infinity norm in place of the Euclidean one (nerfstudio's
`SceneContraction(order=inf)`): with `m = max_i |x_i|`,

    c(x) = x                         if m <= 1 (the inner cube, unchanged)
    c(x) = (2 - 1/m) x / m           otherwise (a radial squeeze onto the shell between the cubes of half-side 1 and 2)

so the inner cube `[-1, 1]^3` (where a capture's cameras are, docs/conventions.md) keeps its scale, everything beyond
it lands in the shell, and infinity on the outer cube's faces. It is continuous and keeps orientation (its Jacobian's
determinant is positive: h^3 / (2m - 1) with h = (2 - 1/m) / m), so a fused surface's outward side stays outward
and a surface crossing the shell stays in one piece. (MERF's piecewise-projective variant keeps planes flat but
is discontinuous across its pyramids' boundaries: a wall crossing one would be torn in two.)
A contracted voxel of edge `v` at L-infinity distance `m` is `m^2 v` deep along the ray from the centre (the depth
uncertainty of a stereo point at that distance grows the same way) and between `m v / 2` and `m v` across it (about a
constant angle seen from the centre). A plane facing the centre stays flat within its pyramid of the shell.
"""
from __future__ import annotations

import numba as nb
import numpy as np

OUTER = 2.0  # the contracted cube's half-side (infinity)


def contract(x: np.ndarray) -> np.ndarray:
    """Contracted coordinates [N,3] of world (normalised-frame) points x [N,3] (module docstring)."""
    x = np.asarray(x, dtype=np.float64)
    m = np.maximum(np.abs(x).max(axis=-1, keepdims=True), 1.0)
    return x * ((OUTER - 1.0 / m) / m)


def uncontract(y: np.ndarray) -> np.ndarray:
    """World points [N,3] of contracted coordinates y [N,3] (the inverse of contract; |y_i| < 2)."""
    y = np.asarray(y, dtype=np.float64)
    m = np.abs(y).max(axis=-1, keepdims=True)
    if (m >= OUTER).any():
        raise ValueError(f"contracted coordinates must lie inside the open cube (-{OUTER}, {OUTER})^3 (its faces are "
                         f"infinitely far), got an L-infinity norm of {float(m.max())}")
    m = np.maximum(m, 1.0)
    return y * (1.0 / (OUTER - m) / m)  # the world point's L-infinity norm is 1 / (2 - m)


def stretch(y: np.ndarray) -> np.ndarray:
    """[N]: world length of a unit contracted length along the ray from the centre at contracted points y [N,3] (the
    inverse map's largest stretch): 1 in the inner cube, m^2 beyond it (m the world point's L-infinity norm),
    continuous across the inner cube's faces."""
    m = np.abs(np.asarray(y, dtype=np.float64)).max(axis=-1)
    s = 1.0 / (OUTER - np.minimum(np.maximum(m, 1.0), OUTER - 1e-12))
    return s * s


def outer_extent(radius: float) -> float:
    """Half-side of the contracted cube that holds the world cube of half-side `radius` (>= 1)."""
    return OUTER - 1.0 / max(float(radius), 1.0)


@nb.njit(cache=True, inline="always")
def uncontract_point(y0, y1, y2):
    """(x0, x1, x2, stretch) of one contracted point: `uncontract` and `stretch` for compiled kernels."""
    m = max(abs(y0), max(abs(y1), abs(y2)))
    if m <= 1.0:
        return y0, y1, y2, 1.0
    s = 1.0 / (OUTER - m)
    f = s / m
    return y0 * f, y1 * f, y2 * f, s * s


@nb.njit(cache=True, inline="always")
def contract_point(x0, x1, x2):
    """(y0, y1, y2) of one world point: `contract` for compiled kernels."""
    m = max(abs(x0), max(abs(x1), abs(x2)))
    if m <= 1.0:
        return x0, x1, x2
    f = (OUTER - 1.0 / m) / m
    return x0 * f, x1 * f, x2 * f
