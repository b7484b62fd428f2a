"""Write a synthetic capture in the NeRF-synthetic (Blender) format, with its ground-truth mesh and surface samples.

Layout (as /work/shared/data/lego):
  OUT/transforms_train.json, OUT/transforms_test.json   {"camera_angle_x": ..., "frames": [{"file_path": "./train/r_0",
                                                         "rotation": 0.0, "transform_matrix": c2w (OpenGL) 4x4}]}
  OUT/train/r_<i>.png, OUT/test/r_<i>.png                RGBA, 8 bit, straight alpha (transparent background)
  OUT/gt_mesh.ply                                        the mesh the images were rendered from (vertex colours)
  OUT/points3d.ply                                       surface samples with their colour (optional initialisation)
  OUT/synth.json                                         the generation settings, for the record
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import trimesh

from trisplat.cameras import Camera
from trisplat.synth.orbit import orbit_cameras
from trisplat.synth.raycast import Shading, _intersector, _shade, raycast_view

# OpenCV camera axes -> OpenGL/Blender camera axes (flip y and z), an involution
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
FRAMING_MARGIN = 1.05  # camera distance / distance at which the bounding sphere just fills the field of view


@dataclass(frozen=True)
class BlenderSceneInfo:
    """What write_blender_scene did (also saved as synth.json)."""

    n_train: int
    n_test: int
    width: int
    height: int
    fov_deg: float
    radius: float
    center: tuple[float, float, float]
    elevation_deg: tuple[float, float]
    samples_per_pixel: int
    shading: dict | None
    seed: int
    n_points: int
    object_bounds: tuple[tuple[float, float, float], tuple[float, float, float]]


def camera_to_blender_matrix(camera: Camera) -> np.ndarray:
    """OpenGL camera-to-world [4,4] (the `transform_matrix` of transforms_*.json) of an OpenCV camera."""
    return camera.camera_to_world @ CV_TO_GL


def default_radius(mesh: trimesh.Trimesh, fov_deg: float, center: np.ndarray) -> float:
    """Distance at which the mesh's bounding sphere about `center` fills the narrower field of view, times a margin."""
    r = float(np.linalg.norm(mesh.vertices - center, axis=1).max())
    return FRAMING_MARGIN * r / math.sin(math.radians(fov_deg) / 2.0)


def _write_png(path: Path, rgba: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.round(np.clip(rgba, 0, 1) * 255).astype(np.uint8), "RGBA").save(path)


def _write_split(out: Path, split: str, mesh, cameras, fov_x: float, spp: int, shading, seed: int, isect,
                 progress: bool) -> None:
    (out / split).mkdir(parents=True, exist_ok=True)
    frames = []
    it = cameras
    if progress:
        from trisplat.progress import progress_bar

        it = progress_bar(cameras, desc=f"rendering {split}", unit="view")
    for i, cam in enumerate(it):
        view = raycast_view(mesh, cam, None, spp, jitter=False, shading=shading, seed=seed + i, intersector=isect)
        _write_png(out / split / f"r_{i}.png", view.rgba)
        frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0,
                       "transform_matrix": camera_to_blender_matrix(cam).tolist()})
    (out / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov_x, "frames": frames}, indent=4))


def write_blender_scene(
    out_dir: str | Path,
    mesh: trimesh.Trimesh,
    n_train: int = 64,
    n_test: int = 16,
    width: int = 160,
    height: int = 160,
    fov_deg: float = 40.0,
    radius: float | None = None,
    center=None,
    elevation_deg: tuple[float, float] = (10.0, 80.0),
    samples_per_pixel: int = 2,
    shading: Shading | None = None,
    seed: int = 0,
    n_points: int = 2000,
    progress: bool = False,
) -> Path:
    """Render `mesh` from orbit cameras and write a Blender-format capture to `out_dir`; returns `out_dir`.

    Train and test cameras lie on two differently rotated Fibonacci spirals over `elevation_deg` (degrees, z up),
    all at distance `radius` (default: the bounding sphere fills the view with a 5% margin) from `center` (default:
    the bounding-box centre), looking at it. fov_deg: horizontal field of view, degrees (camera_angle_x); pixels
    square. samples_per_pixel: s x s antialiasing rays per pixel. shading: optional baked light (None: unlit).
    n_points: surface samples in points3d.ply (0: none). Existing files of the same names are overwritten.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if n_train < 1 or n_test < 0:
        raise ValueError(f"write_blender_scene: need n_train >= 1 and n_test >= 0, got {n_train}, {n_test}")
    center = np.asarray(mesh.bounds.mean(0) if center is None else center, dtype=np.float64)
    if radius is None:
        fov_y_deg = math.degrees(2 * math.atan(height / width * math.tan(math.radians(fov_deg) / 2)))
        radius = default_radius(mesh, min(fov_deg, fov_y_deg), center)
    train = orbit_cameras(n_train, radius, width, height, fov_deg, center, seed, elevation_deg, name_prefix="r")
    test = orbit_cameras(n_test, radius, width, height, fov_deg, center, seed + 1, elevation_deg, name_prefix="r") \
        if n_test else []
    fov_x = math.radians(fov_deg)
    isect = _intersector(mesh)
    _write_split(out, "train", mesh, train, fov_x, samples_per_pixel, shading, seed, isect, progress)
    if n_test:
        _write_split(out, "test", mesh, test, fov_x, samples_per_pixel, shading, seed + 10_000, isect, progress)

    export_colored_mesh(mesh, out / "gt_mesh.ply")
    if n_points > 0:
        pts, face = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
        col = _shade(mesh, np.asarray(face), pts, shading)
        trimesh.PointCloud(pts, colors=np.round(np.clip(col, 0, 1) * 255).astype(np.uint8)).export(
            out / "points3d.ply")
    info = BlenderSceneInfo(n_train, n_test, width, height, fov_deg, float(radius), tuple(float(c) for c in center),
                            tuple(elevation_deg), samples_per_pixel, asdict(shading) if shading else None, seed,
                            n_points, tuple(tuple(float(x) for x in b) for b in mesh.bounds))
    (out / "synth.json").write_text(json.dumps(asdict(info), indent=2))
    return out


def export_colored_mesh(mesh: trimesh.Trimesh, path: Path) -> None:
    """Write `mesh` as PLY with per-vertex colours (a textured mesh gets its texture sampled at the vertices)."""
    m = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    if mesh.visual.kind == "texture":
        m.visual.vertex_colors = mesh.visual.to_color().vertex_colors
    elif mesh.visual.kind in ("vertex", "face"):
        m.visual.vertex_colors = mesh.visual.vertex_colors
    m.export(path)
