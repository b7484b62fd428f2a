"""Numba-backed soft rendering of one view (temporary: delegates to the dense reference until the kernels land)."""
from __future__ import annotations

from trisplat.render.reference import render_reference


def render_numba(positions, faces, vertex_rgb, opacities, sigma, world_to_camera, K, width, height, background, opts):
    return render_reference(positions, faces, vertex_rgb, opacities, sigma, world_to_camera, K, width, height,
                            background, opts)
