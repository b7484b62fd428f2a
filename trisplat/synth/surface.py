"""Unlit surface colour of a trimesh at surface points: vertex colours, face colours, or a UV texture."""

from __future__ import annotations

import weakref

import numpy as np
import trimesh
from scipy import ndimage

_TEXTURES: dict[int, np.ndarray] = {}  # id(PIL image) -> float32 array, converted once, dropped with the image


def barycentric(mesh: trimesh.Trimesh, face_idx: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Barycentric coordinates [N,3] of `points` [N,3] in faces `face_idx` [N] (clipped to the triangle, renormalised)."""
    if len(face_idx) == 0:
        return np.zeros((0, 3))
    tri = mesh.vertices[mesh.faces[face_idx]]
    bary = trimesh.triangles.points_to_barycentric(tri, np.asarray(points, dtype=np.float64))
    bary = np.clip(np.nan_to_num(bary, nan=1.0 / 3.0), 0.0, 1.0)
    return bary / np.maximum(bary.sum(1, keepdims=True), 1e-12)


def _texture_image(mesh: trimesh.Trimesh) -> np.ndarray:
    """The base-colour texture of a TextureVisuals mesh as float32 [h,w,3] in [0,1]."""
    mat = mesh.visual.material
    img = getattr(mat, "image", None)
    if img is None:
        img = getattr(mat, "baseColorTexture", None)
    if img is None:
        raise ValueError("mesh has UV coordinates but its material carries no texture image")
    arr = _TEXTURES.get(id(img))
    if arr is None:
        arr = np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0
        _TEXTURES[id(img)] = arr
        weakref.finalize(img, _TEXTURES.pop, id(img), None)
    return arr


def sample_texture(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping lookup of `image` [h,w,3] at `uv` [N,2] (u right, v up, [0,1] spans the image): [N,3]."""
    h, w = image.shape[:2]
    # texel centres at (i + 0.5) / size; v = 1 is the top row of the image
    x = uv[:, 0] * w - 0.5
    y = (1.0 - uv[:, 1]) * h - 0.5
    out = np.empty((len(uv), 3), dtype=np.float32)
    for c in range(3):
        out[:, c] = ndimage.map_coordinates(image[:, :, c], [y, x], order=1, mode="grid-wrap")
    return out


def surface_colors(mesh: trimesh.Trimesh, face_idx: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unlit RGB float32 [N,3] in [0,1] at `points` [N,3] lying on faces `face_idx` [N].

    Vertex colours are interpolated with barycentrics; face colours are constant per face; a texture is looked up
    (bilinear) at the barycentrically interpolated UV. A mesh without any colour is mid-grey.
    """
    face_idx = np.asarray(face_idx, dtype=np.int64)
    kind = mesh.visual.kind
    if kind == "texture":
        uv = np.asarray(mesh.visual.uv, dtype=np.float64)
        bary = barycentric(mesh, face_idx, points)
        uv_hit = np.einsum("nk,nkd->nd", bary, uv[mesh.faces[face_idx]])
        return sample_texture(_texture_image(mesh), uv_hit)
    if kind == "face":
        fc = np.asarray(mesh.visual.face_colors, dtype=np.float32)[:, :3] / 255.0
        return fc[face_idx]
    if kind == "vertex":
        vc = np.asarray(mesh.visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
        bary = barycentric(mesh, face_idx, points)
        return np.einsum("nk,nkd->nd", bary, vc[mesh.faces[face_idx]]).astype(np.float32)
    return np.full((len(face_idx), 3), 0.5, dtype=np.float32)
