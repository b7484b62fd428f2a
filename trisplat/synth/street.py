"""A synthetic street: a row of objects on a long checkered ground strip, photographed by cameras walking along it.

The scene partitioned training is measured on (trisplat.blocks, `trisplat bench blocks`): larger than one object
capture, long in one direction, every photo seeing a few objects only. z-up, units of metres. Written as a COLMAP
capture (OUT/images/*.png with alpha: the sky is transparent; OUT/sparse/0 text model whose points are surface samples,
half on the ground and half on the objects), with OUT/gt_mesh.ply (the true geometry) and OUT/synth.json.
Every 8th photo is a test view (the loader's rule for captures without splits).
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import trimesh

from trisplat.cameras import Camera
from trisplat.synth.orbit import look_at
from trisplat.synth.scenes import (
    DEMO_SHADING,
    _coloured_box,
    _gradient_cylinder,
    _gradient_sphere,
    _rgba,
    _striped_torus,
    bake_shading,
)

STREET_SPACING = 40.0 / 7.0  # metres between object centres: 8 objects span 40 m
GROUND_OVERHANG = 4.0  # metres of ground beyond the first and last object
GROUND_HALF_WIDTH = 4.0  # metres either side of the street's axis
OBJECT_SCALE = 2.5  # the demo scene's objects (0.3-0.6 units) grown to street furniture (0.8-1.5 m)


@dataclass(frozen=True)
class StreetInfo:
    n_objects: int
    length: float
    n_views: int
    width: int
    height: int
    fov_deg: float
    camera_distance: float
    camera_height: float
    n_points: int
    seed: int


def street_ground(x0: float, x1: float, half_width: float = GROUND_HALF_WIDTH, cell: float = 1.0) -> trimesh.Trimesh:
    """A flat strip z = 0 over [x0, x1] x [-half_width, half_width] with a checker of `cell`-metre squares in two
    colours (unmerged vertices, normal +z)."""
    nx, ny = max(1, int(round((x1 - x0) / cell))), max(1, int(round(2 * half_width / cell)))
    xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(-half_width, half_width, ny + 1)
    tris, cols = [], []
    palette = np.array([(0.82, 0.78, 0.62), (0.35, 0.45, 0.55)])
    for i in range(nx):
        for j in range(ny):
            a, b = (xs[i], ys[j], 0.0), (xs[i + 1], ys[j], 0.0)
            c, d = (xs[i + 1], ys[j + 1], 0.0), (xs[i], ys[j + 1], 0.0)
            tris += [[a, b, c], [a, c, d]]
            cols += [palette[(i + j) % 2]] * 2
    v = np.asarray(tris, dtype=np.float64).reshape(-1, 3)
    m = trimesh.Trimesh(v, np.arange(len(v)).reshape(-1, 3), process=False)
    m.visual.vertex_colors = _rgba(np.repeat(np.asarray(cols), 3, axis=0))
    return m


def street_objects(n_objects: int, spacing: float = STREET_SPACING, seed: int = 0) -> list[trimesh.Trimesh]:
    """`n_objects` objects centred on the x axis, `spacing` metres apart, centred on x = 0: the demo scene's torus,
    box, sphere and cylinder in turn, scaled by OBJECT_SCALE, with hues that change along the street."""
    rng = np.random.default_rng(seed)
    out = []
    x0 = -0.5 * spacing * (n_objects - 1)
    for k in range(n_objects):
        hue = float(rng.uniform(0, 1))
        kind = k % 4
        if kind == 0:
            m = _striped_torus((0.0, 0.0, 0.4), hue)
        elif kind == 1:
            m = _coloured_box((0.0, 0.0, 0.2), 0.4, yaw=float(rng.uniform(0, 1.5)), hue=hue)
        elif kind == 2:
            m = _gradient_sphere((0.0, 0.0, 0.3), 0.3, hue)
        else:
            m = _gradient_cylinder((0.0, 0.0, 0.0), 0.13, 0.55, hue)
        m.apply_scale(OBJECT_SCALE)
        m.apply_translation((x0 + k * spacing, float(rng.uniform(-0.8, 0.8)), 0.0))
        out.append(m)
    return out


def street_mesh(n_objects: int = 8, spacing: float = STREET_SPACING, seed: int = 0) -> tuple[trimesh.Trimesh, np.ndarray]:
    """(mesh, is_ground bool [F]): the ground strip and the objects, with DEMO_SHADING's light baked into the
    vertex colours."""
    if n_objects < 1:
        raise ValueError(f"street_mesh: need at least one object, got {n_objects}")
    half = 0.5 * spacing * (n_objects - 1) + GROUND_OVERHANG
    ground = street_ground(-half, half)
    objects = street_objects(n_objects, spacing, seed)
    mesh = bake_shading(trimesh.util.concatenate([ground] + objects), DEMO_SHADING)
    is_ground = np.zeros(len(mesh.faces), bool)
    is_ground[: len(ground.faces)] = True
    return mesh, is_ground


def street_cameras(n_views: int, x0: float, x1: float, width: int, height: int, fov_deg: float = 60.0,
                   distance: float = 7.0, camera_height: float = 3.0) -> list[Camera]:
    """`n_views` cameras on both sides of the street (alternating), evenly spaced over x in [x0, x1], `distance`
    metres from its axis and `camera_height` up, each looking at the street's axis a little ahead of or behind
    itself (alternately), so that every object is seen from several directions."""
    fx = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1]], dtype=np.float64)
    cams = []
    xs = np.linspace(x0, x1, n_views)
    for i, x in enumerate(xs):
        side = 1.0 if i % 2 == 0 else -1.0
        ahead = 2.0 if (i // 2) % 2 == 0 else -2.0
        eye = (float(x), side * distance, camera_height)
        target = (float(x) + ahead, 0.0, 0.5)
        cams.append(Camera(look_at(eye, target), K.copy(), width, height, name=f"v_{i:04d}.png"))
    return cams


def write_street_scene(out_dir: str | Path, n_objects: int = 8, views_per_object: int = 8, width: int = 96,
                       height: int = 64, fov_deg: float = 60.0, spacing: float = STREET_SPACING,
                       samples_per_pixel: int = 2, n_points: int | None = None, seed: int = 0,
                       progress: bool = False) -> Path:
    """Render the street (street_mesh) from n_objects x views_per_object cameras (street_cameras) and write a COLMAP
    capture to `out_dir` (see the module's docstring); returns `out_dir`. n_points: sparse points (default 400 per
    object), half on the ground and half on the objects."""
    from PIL import Image

    from trisplat.synth.raycast import _intersector, _shade, raycast_view
    from trisplat.synth.room import write_colmap_text

    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    mesh, is_ground = street_mesh(n_objects, spacing, seed)
    half = 0.5 * spacing * (n_objects - 1)
    cams = street_cameras(n_objects * views_per_object, -half - 1.0, half + 1.0, width, height, fov_deg)
    isect = _intersector(mesh)
    it = cams
    if progress:
        from trisplat.progress import progress_bar

        it = progress_bar(cams, desc="rendering street", unit="view")
    for i, cam in enumerate(it):
        view = raycast_view(mesh, cam, None, samples_per_pixel, jitter=False, shading=None, seed=seed + i,
                            intersector=isect)
        Image.fromarray(np.round(np.clip(view.rgba, 0, 1) * 255).astype(np.uint8), "RGBA").save(out / "images" / cam.name)
    n_points = 400 * n_objects if n_points is None else int(n_points)
    area = mesh.area_faces
    weight = np.where(is_ground, area / area[is_ground].sum(), area / max(area[~is_ground].sum(), 1e-12))
    pts, face = trimesh.sample.sample_surface(mesh, n_points, face_weight=weight, seed=seed)
    col = _shade(mesh, np.asarray(face), pts, None)
    write_colmap_text(out, cams, np.asarray(pts), col)
    from trisplat.synth.blender import export_colored_mesh

    export_colored_mesh(mesh, out / "gt_mesh.ply")
    info = StreetInfo(n_objects, float(spacing * (n_objects - 1)), len(cams), width, height, fov_deg, 7.0, 3.0,
                      n_points, seed)
    (out / "synth.json").write_text(json.dumps(asdict(info), indent=2))
    return out
