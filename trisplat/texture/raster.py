"""Which surface point each sample of a view shows: face id and perspective-correct barycentrics from the opaque
z-buffer (trisplat.render.rasterize_hard), the visibility both the texture fit and the glTF spec renderer use."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from trisplat.render.inputs import check_supersample


@dataclass(frozen=True)
class SurfaceSamples:
    """Per sample (s x s per pixel, row-major [s H, s W]): the face it shows (-1: none) and its barycentrics
    (perspective-correct, as GPUs interpolate attributes; weights of the face's corners 0, 1, 2)."""

    face_id: np.ndarray  # int64 [sH, sW]
    bary: np.ndarray  # float32 [sH, sW, 3]
    supersample: int


_CORNERS = np.eye(3, dtype=np.float32)


def surface_samples(positions: np.ndarray, faces: np.ndarray, world_to_camera: np.ndarray, K: np.ndarray, width: int,
                    height: int, supersample: int = 1, near: float = 0.01,
                    cull_back_faces: bool = False) -> SurfaceSamples:
    """Rasterise an opaque mesh at s x s samples per pixel (sample (i, j) of pixel (x, y) at (x + (i + 0.5) / s,
    y + (j + 0.5) / s), docs/conventions.md). The faces are rendered as separate triangles whose corners carry the
    colours (1,0,0), (0,1,0), (0,0,1): the hard renderer's perspective-correct colour is then the barycentrics.
    cull_back_faces: faces whose front (counter-clockwise) side looks away from the camera are left out (glTF's
    single-sided materials)."""
    s = check_supersample(supersample)
    pos = np.asarray(positions, np.float64)
    faces = np.asarray(faces, np.int64)
    keep = np.arange(len(faces))
    if cull_back_faces and len(faces):
        R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
        centre = -R.T @ t
        tri = pos[faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        keep = np.nonzero(np.einsum("fi,fi->f", n, centre - tri[:, 0]) > 0)[0]
    Ks = np.asarray(K, np.float64).copy()
    Ks[:2] *= s
    W, H = width * s, height * s
    if len(keep) == 0:
        return SurfaceSamples(np.full((H, W), -1, np.int64), np.zeros((H, W, 3), np.float32), s)
    soup = torch.from_numpy(pos[faces[keep]].reshape(-1, 3).astype(np.float32))
    tri_idx = torch.arange(3 * len(keep), dtype=torch.int32).reshape(-1, 3)
    colours = torch.from_numpy(np.tile(_CORNERS, (len(keep), 1)))
    from trisplat import render

    out = render.rasterize_hard(soup, tri_idx, colours, torch.as_tensor(world_to_camera, dtype=torch.float32),
                                torch.as_tensor(Ks, dtype=torch.float32), W, H, torch.zeros(3), near=near,
                                perspective_correct=True, backend="numba")
    fid = out.face_id.numpy().astype(np.int64)
    hit = fid >= 0
    fid[hit] = keep[fid[hit]]
    bary = np.where(hit[..., None], out.rgb.numpy(), 0.0).astype(np.float32)
    return SurfaceSamples(face_id=fid, bary=bary, supersample=s)


def view_samples(positions: np.ndarray, faces: np.ndarray, views, supersample: int = 2, near: float = 0.01):
    """(SurfaceSamples, photo) of each (camera, photo) in `views`, rasterised one view at a time (a generator: one
    view's samples are held at a time). The colour fits feed their row accumulators from it."""
    for cam, photo in views:
        yield surface_samples(positions, faces, np.asarray(cam.world_to_camera, np.float64), np.asarray(cam.K),
                              cam.width, cam.height, supersample, near), photo
