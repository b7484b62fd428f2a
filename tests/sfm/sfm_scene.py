"""A small textured synthetic scene with known cameras for the structure-from-motion tests (ray-cast by trisplat.synth)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image
from scipy import ndimage

from trisplat.cameras import Camera
from trisplat.synth import look_at, raycast_view
from trisplat.synth.orbit import intrinsics


def noise_texture(seed: int, size: int = 256) -> Image.Image:
    """Smooth random colour blobs at several scales: plenty of SIFT features, no repeated pattern."""
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size, 3))
    for sigma, weight in ((1.5, 0.5), (4.0, 0.8), (10.0, 1.0)):
        layer = ndimage.gaussian_filter(rng.random((size, size, 3)), (sigma, sigma, 0), mode="wrap")
        layer = (layer - layer.mean()) / (layer.std() + 1e-9)
        img += weight * layer
    img = (img - img.min()) / (img.max() - img.min())
    return Image.fromarray(np.round(img * 255).astype(np.uint8), "RGB")


def _quad(corners, uv_origin, uv_size) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles (counter-clockwise as given) with UVs in the atlas cell at uv_origin of size uv_size."""
    v = np.asarray(corners, dtype=np.float64)
    u0, v0 = uv_origin
    uv = np.array([[u0, v0], [u0 + uv_size, v0], [u0 + uv_size, v0 + uv_size], [u0, v0 + uv_size]])
    return v, uv


def textured_scene(seed: int = 0) -> trimesh.Trimesh:
    """A textured ground square (side 3, z = 0) with three textured boxes on it, z up, one noise texture atlas."""
    quads = [_quad([(-1.5, -1.5, 0), (1.5, -1.5, 0), (1.5, 1.5, 0), (-1.5, 1.5, 0)], (0.0, 0.0), 0.5)]
    boxes = [((-0.5, 0.3, 0.25), 0.5), ((0.55, -0.2, 0.3), 0.6), ((0.1, -0.8, 0.2), 0.4)]
    cell = 0
    for (cx, cy, cz), s in boxes:
        h = s / 2
        c = np.array([cx, cy, cz])
        faces = [  # outward counter-clockwise
            [(-h, -h, h), (h, -h, h), (h, h, h), (-h, h, h)],
            [(-h, -h, -h), (h, -h, -h), (h, -h, h), (-h, -h, h)],
            [(h, -h, -h), (h, h, -h), (h, h, h), (h, -h, h)],
            [(h, h, -h), (-h, h, -h), (-h, h, h), (h, h, h)],
            [(-h, h, -h), (-h, -h, -h), (-h, -h, h), (-h, h, h)],
        ]
        for f in faces:
            u0 = 0.5 + 0.125 * (cell % 4)
            v0 = 0.125 * (cell // 4)
            quads.append(_quad(np.asarray(f) + c, (u0, v0), 0.125))
            cell += 1
    verts, uvs, tris = [], [], []
    for v, uv in quads:
        base = len(verts) * 4
        verts.append(v)
        uvs.append(uv)
        tris += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    mesh = trimesh.Trimesh(np.concatenate(verts), np.asarray(tris), process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.concatenate(uvs), image=noise_texture(seed, 512))
    return mesh


def path_cameras(n: int, width: int = 320, height: int = 240, fov_deg: float = 60.0, radius: float = 3.0,
                 height_z: float = 1.8, arc_deg: float = 120.0) -> list[Camera]:
    """`n` cameras along a horizontal arc of `arc_deg` degrees around the scene, looking at its centre (a video path)."""
    K = intrinsics(width, height, fov_deg)
    cams = []
    for i in range(n):
        a = math.radians(-arc_deg / 2 + arc_deg * i / max(n - 1, 1))
        eye = (radius * math.cos(a), radius * math.sin(a), height_z)
        cams.append(Camera(look_at(eye, (0.0, 0.0, 0.2)), K.copy(), width, height, name=f"frame_{i:03d}"))
    return cams


def render_frames(mesh: trimesh.Trimesh, cameras: list[Camera], out: Path, suffix: str = ".png") -> list[Path]:
    """Ray-cast each camera (2x2 samples, white background) to OUT/<name><suffix>; returns the files."""
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for cam in cameras:
        rgba = raycast_view(mesh, cam, background=(1.0, 1.0, 1.0), samples_per_pixel=2).rgba
        p = out / f"{cam.name}{suffix}"
        Image.fromarray(np.round(rgba[..., :3] * 255).astype(np.uint8), "RGB").save(p)
        paths.append(p)
    return paths


def radial_undistort_points(xd: np.ndarray, k1: float, k2: float, iters: int = 30) -> np.ndarray:
    """Normalised pinhole coordinates [N,2] whose COLMAP RADIAL distortion, x (1 + k1 r^2 + k2 r^4), gives `xd` (fixed
    point iteration; converges for the mild distortions of the tests)."""
    xu = xd.copy()
    for _ in range(iters):
        r2 = (xu**2).sum(1, keepdims=True)
        xu = xd / (1 + k1 * r2 + k2 * r2**2)
    return xu


def render_distorted_frames(mesh: trimesh.Trimesh, cameras: list[Camera], k1: float, k2: float, out: Path,
                            margin: int = 48) -> list[Path]:
    """Photos of `cameras` through a lens with COLMAP RADIAL distortion (focal length and principal point of each
    camera's K, radial terms k1, k2): every distorted pixel centre is undistorted and the colour there is read
    (bilinear) from a pinhole ray-cast of the same camera with `margin` extra pixels around. Writes OUT/<name>.png."""
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for cam in cameras:
        W, H, K = cam.width, cam.height, cam.K
        wide_K = K.copy()
        wide_K[:2, 2] += margin
        wide = Camera(cam.world_to_camera, wide_K, W + 2 * margin, H + 2 * margin)
        rgb = raycast_view(mesh, wide, background=(1.0, 1.0, 1.0), samples_per_pixel=2).rgba[..., :3]
        v, u = np.mgrid[0:H, 0:W] + 0.5  # pixel centres
        f, c = np.array([K[0, 0], K[1, 1]]), K[:2, 2]
        xd = (np.stack([u.ravel(), v.ravel()], 1) - c) / f
        q = radial_undistort_points(xd, k1, k2) * f + c + margin - 0.5  # array indices in the wide render
        if q.min() < 0 or (q[:, 0] > W + 2 * margin - 1).any() or (q[:, 1] > H + 2 * margin - 1).any():
            raise ValueError(f"render_distorted_frames: a margin of {margin} px is too small for k1={k1}, k2={k2}")
        img = np.stack([ndimage.map_coordinates(rgb[..., ch], [q[:, 1], q[:, 0]], order=1) for ch in range(3)], 1)
        p = out / f"{cam.name}.png"
        Image.fromarray(np.round(np.clip(img.reshape(H, W, 3), 0, 1) * 255).astype(np.uint8), "RGB").save(p)
        paths.append(p)
    return paths
