"""The deliverable surface: the run's opaque mesh, optionally decimated to a face budget (level of detail), with its
base-colour texture fitted to the photos."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trisplat.io.gltf import TextureMap


@dataclass
class MeshAsset:
    """positions [V,3] (the run's normalised frame), faces [F,3], colors [V,3] sRGB (vertex colours, what PLY holds),
    texture (None: vertex colours only) and what texturing reported (metrics.json's `texture`)."""

    positions: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    texture: TextureMap | None = None
    texture_report: dict | None = None


def decimate(positions: np.ndarray, faces: np.ndarray, colors: np.ndarray, target_faces: int):
    """Quadric edge-collapse decimation (fast-simplification) to about `target_faces` faces; each new vertex takes
    the colour of the nearest original vertex. Returns the mesh unchanged when it already has at most that many."""
    if target_faces <= 0:
        raise ValueError(f"target_faces must be > 0, got {target_faces}")
    if len(faces) <= target_faces:
        return positions, faces, colors
    import fast_simplification
    from scipy.spatial import cKDTree

    p, f = fast_simplification.simplify(np.asarray(positions, np.float32), np.asarray(faces, np.int32),
                                        target_reduction=1.0 - target_faces / len(faces))
    _, nearest = cKDTree(positions).query(p)
    return np.asarray(p, np.float32), np.asarray(f, np.int64), np.asarray(colors)[nearest]


MIN_TEXTURE_SIZE = 64


def photo_texture_cap(data) -> int:
    """The largest useful texture side for a capture: the power of two at or above sqrt(pixels of all training
    photos), at least MIN_TEXTURE_SIZE. A texture with more texels than the photos have pixels holds nothing they
    say, and fitting it costs time (a 2048 texture for six 40x40 views took most of a test's minutes)."""
    pixels = sum(int(data.cameras[int(i)].width) * int(data.cameras[int(i)].height) for i in data.train_indices)
    side = MIN_TEXTURE_SIZE
    while side * side < pixels:
        side *= 2
    return side


def build_asset(scene, data, texture_size: int = 2048, faces: int | None = None, supersample: int = 2,
                near: float = 0.01) -> MeshAsset:
    """The mesh files' content for a TriangleScene trained on `data` (SceneData): SH band 0 as vertex colours,
    decimated to `faces` when given, textured over the training views when texture_size > 0."""
    from trisplat.scene.sh import sh_dc_to_rgb
    from trisplat.texture import texture_mesh

    positions = scene.positions.detach().cpu().numpy()
    fc = scene.faces.detach().cpu().numpy().astype(np.int64)
    colors = sh_dc_to_rgb(scene.sh[:, 0].detach().cpu()).clamp(0, 1).numpy()
    if faces is not None:
        positions, fc, colors = decimate(positions, fc, colors, int(faces))
    asset = MeshAsset(positions=positions, faces=fc, colors=colors)
    if texture_size and len(fc):
        size = min(int(texture_size), photo_texture_cap(data))
        asset.texture, rep = texture_mesh(positions, fc, colors, data, size, supersample, near)
        asset.texture_report = rep.to_dict()
    return asset
