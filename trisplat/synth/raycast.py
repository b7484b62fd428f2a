"""An independent renderer for ground truth: one embree ray per pixel sample through trimesh, unlit or with a baked light.

It shares no code with trisplat.render, so images it makes can judge that renderer. Pixel centres at (x + 0.5, y + 0.5)
in OpenCV axes (docs/conventions.md). With `samples_per_pixel = s`, each pixel is the box-filtered mean of an s x s
grid of sub-pixel rays (stratified; `jitter=True` moves each ray randomly inside its stratum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from trisplat.cameras import Camera
from trisplat.synth.surface import barycentric, surface_colors


@dataclass(frozen=True)
class Shading:
    """A fixed directional light baked onto the surface: view independent (it depends only on the surface normal).

    colour = albedo * (ambient + (1 - ambient) * max(0, n . light_dir)); n is the smooth (barycentrically
    interpolated vertex) normal, outward by the mesh's winding. Back faces therefore get `ambient` only.
    light_dir: world direction towards the light (normalised internally). ambient: fraction of albedo in shadow.
    """

    light_dir: tuple[float, float, float] = (0.3, 0.2, 1.0)
    ambient: float = 0.45


@dataclass
class RayCastView:
    """One ray-cast view. rgba: float32 [H,W,4], colour not premultiplied (as a PNG stores it), or composited over
    the background when one was given. face_id: int64 [H,W] face hit by the pixel-centre ray (-1: none).
    depth: float32 [H,W] view depth (camera z) of the pixel-centre hit, 0 where nothing was hit."""

    rgba: np.ndarray
    face_id: np.ndarray
    depth: np.ndarray


def _intersector(mesh: trimesh.Trimesh):
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    except ImportError:  # embreex missing: trimesh's pure-python intersector gives the same answers, slowly
        from trimesh.ray.ray_triangle import RayMeshIntersector

        return RayMeshIntersector(mesh)


def _pixel_rays(camera: Camera, offset: tuple[float, float] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origins and world directions [H*W,3] of rays through pixel corner + offset (offset (0.5, 0.5) = centres)."""
    W, H = camera.width, camera.height
    off = np.broadcast_to(np.asarray(offset, dtype=np.float64), (H, W, 2)) if np.ndim(offset) == 1 else offset
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pix = np.stack([xs + off[..., 0], ys + off[..., 1], np.ones_like(xs)], -1).reshape(-1, 3)
    d_cam = pix @ np.linalg.inv(camera.K).T
    R = camera.world_to_camera[:3, :3]
    d_world = d_cam @ R  # R^T d for each row
    d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
    origins = np.broadcast_to(camera.center, d_world.shape)
    return np.ascontiguousarray(origins), d_world


def _cast(intersector, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit per ray: face index [N] (-1 none) and location [N,3] (nan where none)."""
    n = len(origins)
    face = np.full(n, -1, dtype=np.int64)
    loc = np.full((n, 3), np.nan)
    tri, ray, pts = intersector.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    face[ray] = tri
    loc[ray] = pts
    return face, loc


def _shade(mesh: trimesh.Trimesh, face: np.ndarray, pts: np.ndarray, shading: Shading | None) -> np.ndarray:
    rgb = surface_colors(mesh, face, pts)
    if shading is None or len(face) == 0:
        return rgb
    bary = barycentric(mesh, face, pts)
    n = np.einsum("nk,nkd->nd", bary, mesh.vertex_normals[mesh.faces[face]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    light = np.asarray(shading.light_dir, dtype=np.float64)
    light = light / np.linalg.norm(light)
    k = shading.ambient + (1.0 - shading.ambient) * np.clip(n @ light, 0.0, None)
    return (rgb * k[:, None]).astype(np.float32)


def _stratified_offsets(s: int, jitter: bool, rng: np.random.Generator, shape: tuple[int, int]) -> list:
    """s*s sub-pixel offsets in [0,1)^2 (one per stratum), each either a constant [2] or a per-pixel [H,W,2] array."""
    out = []
    for j in range(s):
        for i in range(s):
            if jitter:
                u = rng.random(shape + (2,))
                out.append(np.stack([(i + u[..., 0]) / s, (j + u[..., 1]) / s], -1))
            else:
                out.append(np.array([(i + 0.5) / s, (j + 0.5) / s]))
    return out


def raycast_view(
    mesh: trimesh.Trimesh,
    camera: Camera,
    background: tuple[float, float, float] | None = None,
    samples_per_pixel: int = 1,
    jitter: bool = False,
    shading: Shading | None = None,
    seed: int = 0,
    intersector=None,
) -> RayCastView:
    """Ray-cast one view of `mesh` (world frame) seen by `camera` (see RayCastView for the outputs).

    samples_per_pixel: s -> s x s stratified rays per pixel, box-filtered (s = 1: the pixel centre only).
    background: None -> straight (non-premultiplied) RGBA, colour 0 where alpha is 0; an RGB triple -> the colour
    channels are composited over it (alpha still reported).
    """
    if samples_per_pixel < 1:
        raise ValueError(f"samples_per_pixel must be >= 1, got {samples_per_pixel}")
    isect = intersector if intersector is not None else _intersector(mesh)
    H, W = camera.height, camera.width
    # the pixel-centre ray gives face ids and depth
    o, d = _pixel_rays(camera, (0.5, 0.5))
    face_c, loc_c = _cast(isect, o, d)
    hit_c = face_c >= 0
    depth = np.zeros(H * W, dtype=np.float32)
    if hit_c.any():
        cam_pts = loc_c[hit_c] @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3]
        depth[hit_c] = cam_pts[:, 2]

    rng = np.random.default_rng(seed)
    premult = np.zeros((H * W, 3), dtype=np.float64)
    alpha = np.zeros(H * W, dtype=np.float64)
    offsets = _stratified_offsets(samples_per_pixel, jitter, rng, (H, W))
    for off in offsets:
        if samples_per_pixel == 1 and not jitter:
            face, loc = face_c, loc_c
        else:
            o, d = _pixel_rays(camera, off)
            face, loc = _cast(isect, o, d)
        hit = face >= 0
        if hit.any():
            premult[hit] += _shade(mesh, face[hit], loc[hit], shading)
            alpha[hit] += 1.0
    n = float(len(offsets))
    premult /= n
    alpha /= n
    if background is None:
        rgb = np.where(alpha[:, None] > 0, premult / np.maximum(alpha[:, None], 1e-12), 0.0)
    else:
        rgb = premult + (1.0 - alpha[:, None]) * np.asarray(background, dtype=np.float64)[None]
    rgba = np.concatenate([np.clip(rgb, 0.0, 1.0), alpha[:, None]], 1).astype(np.float32).reshape(H, W, 4)
    return RayCastView(rgba=rgba, face_id=face_c.reshape(H, W), depth=depth.reshape(H, W))


def render_views(
    mesh: trimesh.Trimesh,
    cameras: list[Camera],
    background: tuple[float, float, float] | None = None,
    samples_per_pixel: int = 1,
    jitter: bool = False,
    shading: Shading | None = None,
    seed: int = 0,
    progress: bool = False,
) -> list[np.ndarray]:
    """RGBA float32 [H,W,4] images of `mesh` from each camera (see raycast_view for the settings).

    Unlit by default: colour = vertex colours (barycentric), face colours, or the texture at the interpolated UV.
    `shading` bakes a fixed light that does not depend on the view.
    """
    isect = _intersector(mesh)
    it = cameras
    if progress:
        from trisplat.progress import progress_bar

        it = progress_bar(cameras, desc="ray-casting views", unit="view")
    return [
        raycast_view(mesh, cam, background, samples_per_pixel, jitter, shading, seed + i, isect).rgba
        for i, cam in enumerate(it)
    ]


def render_face_ids(mesh: trimesh.Trimesh, cameras: list[Camera]) -> list[np.ndarray]:
    """Per camera, int64 [H,W]: the face hit by each pixel-centre ray (-1 where the ray misses): a z-buffer's ids."""
    isect = _intersector(mesh)
    out = []
    for cam in cameras:
        o, d = _pixel_rays(cam, (0.5, 0.5))
        out.append(_cast(isect, o, d)[0].reshape(cam.height, cam.width))
    return out
