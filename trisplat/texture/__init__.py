"""Textures for the final opaque surface: a UV atlas (xatlas) and the base-colour texture that best fits the
training photos (sparse linear least squares), written into GLB (baseColorTexture) and OBJ (map_Kd) files."""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from trisplat.io.gltf import TextureMap
from trisplat.texture.atlas import Atlas, build_atlas
from trisplat.texture.fit import FitStats, TexelRows, fit_texture, solve_texture
from trisplat.texture.raster import view_samples

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


def texture_mesh(positions: np.ndarray, faces: np.ndarray, colors, data, size: int = DEFAULT_TEXTURE_SIZE,
                 supersample: int = 2, near: float = 0.01, indices=None, also: Sequence = ()
                 ) -> tuple[TextureMap, TextureReport]:
    """Atlas + least-squares texture of an opaque mesh over the training views of `data` (a SceneData; the mesh
    in its normalised frame). colors [V,3]: sRGB vertex colours for texels no photo sees, or a function returning
    them, called once every view has been rasterised. indices: the views to fit (default: the training split).
    also: more row accumulators (add(samples, photo), e.g. trisplat.texture.vertex_colours.VertexRows) fed the
    same rasterised views, so a vertex-colour fit whose result `colors` returns costs no second pass."""
    t0 = time.perf_counter()
    atlas = build_atlas(positions, faces, size)
    t_atlas = time.perf_counter() - t0
    idx = [int(i) for i in (data.train_indices if indices is None else indices)]
    t1 = time.perf_counter()
    rows = TexelRows(faces, atlas, data.background)
    views = ((data.cameras[i], np.asarray(data.load_image(i), np.float32)) for i in idx)
    for ss, photo in view_samples(positions, rows.faces, views, supersample, near):
        for acc in (rows, *also):
            acc.add(ss, photo)
        del ss, photo
    t_raster = time.perf_counter() - t1
    prior = colors() if callable(colors) else colors
    image, stats = solve_texture(rows.finish(prior), t_raster)
    tex = TextureMap(uv=atlas.uv.astype(np.float32), uv_faces=atlas.uv_faces, image=image)
    return tex, TextureReport(size=size, faces=len(faces), atlas_seconds=t_atlas, fit=stats,
                              seconds=time.perf_counter() - t0)


__all__ = ["Atlas", "FitStats", "TextureReport", "build_atlas", "fit_texture", "texture_mesh"]
