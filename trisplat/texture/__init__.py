"""Textures for the final opaque surface: a UV atlas (xatlas) and the base-colour texture that best fits the
training photos (sparse linear least squares), written into GLB (baseColorTexture) and OBJ (map_Kd) files."""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from trisplat.io.gltf import TextureMap
from trisplat.texture.atlas import Atlas, build_atlas
from trisplat.texture.fit import FitStats, fit_texture

DEFAULT_TEXTURE_SIZE = 2048


@dataclass
class TextureReport:
    """What texturing cost and did (metrics.json's `texture`)."""

    size: int
    faces: int
    atlas_seconds: float
    fit: FitStats
    seconds: float

    def to_dict(self) -> dict:
        return {"size": self.size, "faces": self.faces, "atlas_seconds": self.atlas_seconds, "seconds": self.seconds,
                **{f"fit_{k}": v for k, v in asdict(self.fit).items()}}


def texture_mesh(positions: np.ndarray, faces: np.ndarray, colors: np.ndarray, data, size: int = DEFAULT_TEXTURE_SIZE,
                 supersample: int = 2, near: float = 0.01, indices=None) -> tuple[TextureMap, TextureReport]:
    """Atlas + least-squares texture of an opaque mesh over the training views of `data` (a SceneData; the mesh
    in its normalised frame). colors [V,3]: sRGB vertex colours for texels no photo sees. indices: the views to fit
    (default: the training split)."""
    t0 = time.perf_counter()
    atlas = build_atlas(positions, faces, size)
    t_atlas = time.perf_counter() - t0
    idx = [int(i) for i in (data.train_indices if indices is None else indices)]
    views = ((data.cameras[i], np.asarray(data.load_image(i), np.float32)) for i in idx)
    image, stats = fit_texture(positions, faces, atlas, views, data.background, colors, supersample, near)
    tex = TextureMap(uv=atlas.uv.astype(np.float32), uv_faces=atlas.uv_faces, image=image)
    return tex, TextureReport(size=size, faces=len(faces), atlas_seconds=t_atlas, fit=stats,
                              seconds=time.perf_counter() - t0)


__all__ = ["Atlas", "FitStats", "TextureReport", "build_atlas", "fit_texture", "texture_mesh"]
