"""An unbounded synthetic capture: objects on a large textured floor inside textured walls, photographed from a ring
of cameras inside the room, written as a COLMAP text model (what structure from motion gives for real photos).

This is the shape of a real capture that object scenes (lego, Spot) do not have: no background, content at many
depths, most of it (walls, floor, ceiling) well outside the camera ring, every pixel covered.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import trimesh

from trisplat.cameras import Camera
from trisplat.synth.orbit import intrinsics, look_at
from trisplat.synth.raycast import Shading, _intersector, _shade, raycast_view
from trisplat.synth.scenes import _rgba, bake_shading, demo_mesh

ROOM_SHADING = Shading(light_dir=(0.3, 0.2, 1.0), ambient=0.55)


def _tiled_quad(corners, n: int, colour_of) -> trimesh.Trimesh:
    """A quad (4 corners, counter-clockwise seen from the side its normal points to) split into n x n cells of two
    triangles each, cell (i, j) coloured colour_of(i, j) (unmerged vertices, so colours are crisp)."""
    c = np.asarray(corners, dtype=np.float64)
    tris, cols = [], []
    for i in range(n):
        for j in range(n):
            def p(a, b):
                u, v = a / n, b / n
                return (1 - u) * (1 - v) * c[0] + u * (1 - v) * c[1] + u * v * c[2] + (1 - u) * v * c[3]
            q = [p(i, j), p(i + 1, j), p(i + 1, j + 1), p(i, j + 1)]
            tris += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
            col = colour_of(i, j)
            cols += [col, col]
    v = np.asarray(tris).reshape(-1, 3)
    m = trimesh.Trimesh(v, np.arange(len(v)).reshape(-1, 3), process=False)
    m.visual.vertex_colors = _rgba(np.repeat(np.asarray(cols), 3, axis=0))
    return m


def room_mesh(half: float = 3.0, height: float = 2.4, cells: int = 12, seed: int = 0) -> trimesh.Trimesh:
    """The demo objects (about 2.4 units wide) on a floor of side 2 x `half`, inside four walls and a ceiling of
    height `height`, all facing inwards, with a baked fixed light; z up. Floor: a two-colour checker; walls: random
    pastel tiles of a different hue each; ceiling: a pale grid. Content reaches `half` * sqrt(2) from the centre."""
    rng = np.random.default_rng(seed)
    h, H = float(half), float(height)
    floor = _tiled_quad([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], cells,
                        lambda i, j: (0.78, 0.7, 0.55) if (i + j) % 2 else (0.35, 0.3, 0.28))
    ceiling = _tiled_quad([(-h, -h, H), (-h, h, H), (h, h, H), (h, -h, H)], cells // 2,
                          lambda i, j: (0.92, 0.92, 0.88) if (i + j) % 2 else (0.8, 0.82, 0.85))
    walls = []
    corners = [(-h, -h), (h, -h), (h, h), (-h, h)]
    for k in range(4):
        (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
        hue = rng.uniform(0, 1)
        tiles = rng.uniform(0.45, 0.95, size=(cells, cells))

        def colour(i, j, hue=hue, tiles=tiles):
            import colorsys

            return colorsys.hsv_to_rgb((hue + 0.08 * ((i // 3) % 2)) % 1.0, 0.45, tiles[i, j])
        # counter-clockwise seen from inside the room: normal pointing to the centre
        walls.append(_tiled_quad([(x0, y0, 0), (x0, y0, H), (x1, y1, H), (x1, y1, 0)], cells, colour))
    objects = demo_mesh(seed=seed, shaded=False)
    objects.apply_translation((0.0, 0.0, 1e-3))  # the demo's ground disk sits at z = 0 like the floor
    return bake_shading(trimesh.util.concatenate([floor, ceiling, *walls, objects]), ROOM_SHADING)


def ring_cameras(n: int, radius: float, height: float, target, width: int, height_px: int, fov_deg: float,
                 phase: float = 0.0, jitter: float = 0.0, seed: int = 0, prefix: str = "img") -> list[Camera]:
    """`n` cameras evenly on a horizontal circle of `radius` at `height`, looking at `target` (z up); `jitter`
    (scene units) moves each up or down randomly, as a hand-held capture would."""
    rng = np.random.default_rng(seed)
    K = intrinsics(width, height_px, fov_deg)
    cams = []
    for i in range(n):
        a = phase + 2 * math.pi * i / n
        eye = (radius * math.cos(a), radius * math.sin(a), height + jitter * rng.uniform(-1, 1))
        cams.append(Camera(world_to_camera=look_at(eye, target), K=K.copy(), width=width, height=height_px,
                           name=f"{prefix}_{i:03d}.png"))
    return cams


@dataclass(frozen=True)
class RoomSceneInfo:
    n_views: int
    width: int
    height: int
    fov_deg: float
    ring_radius: float
    ring_height: float
    room_half: float
    room_height: float
    n_points: int
    seed: int


def _quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def write_colmap_text(out: Path, cameras: list[Camera], points: np.ndarray, colors: np.ndarray) -> Path:
    """A COLMAP text model of pinhole `cameras` (one shared camera) and `points` [P,3] with `colors` [P,3] in [0,1]
    into OUT/sparse/0 (the images are expected in OUT/images under each camera's name). Returns the model folder."""
    model = Path(out) / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    c = cameras[0]
    K = c.K
    (model / "cameras.txt").write_text(
        f"1 PINHOLE {c.width} {c.height} {K[0, 0]:.10g} {K[1, 1]:.10g} {K[0, 2]:.10g} {K[1, 2]:.10g}\n")
    lines = []
    for i, cam in enumerate(cameras):
        q = _quaternion_wxyz(cam.world_to_camera[:3, :3])
        t = cam.world_to_camera[:3, 3]
        lines.append(f"{i + 1} {' '.join(f'{v:.12g}' for v in q)} {' '.join(f'{v:.12g}' for v in t)} 1 {cam.name}")
        lines.append("")
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    rgb = np.round(np.clip(colors, 0, 1) * 255).astype(int)
    (model / "points3D.txt").write_text("".join(
        f"{k + 1} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g} {r} {g} {b} 0.5\n" for k, (p, (r, g, b)) in enumerate(zip(points, rgb))))
    return model


def write_room_scene(out_dir: str | Path, n_views: int = 48, width: int = 160, height: int = 120,
                     fov_deg: float = 70.0, ring_radius: float = 1.6, ring_height: float = 1.1,
                     room_half: float = 3.0, room_height: float = 2.4, samples_per_pixel: int = 2,
                     n_points: int = 3000, seed: int = 0, progress: bool = False) -> Path:
    """Render `room_mesh` from `n_views` ring cameras inside the room (looking at the objects in the middle, so the
    far walls, floor and ceiling fill the rest of every photo) and write a COLMAP capture: OUT/images/*.png (RGB,
    no alpha), OUT/sparse/0 (text model with `n_points` surface samples as the sparse points), OUT/gt_mesh.ply,
    OUT/synth.json. Every 8th view is a test view for trisplat (the loader's rule for captures without splits)."""
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    mesh = room_mesh(room_half, room_height, seed=seed)
    cams = ring_cameras(n_views, ring_radius, ring_height, (0.0, 0.0, 0.3), width, height, fov_deg,
                        jitter=0.15, seed=seed)
    isect = _intersector(mesh)
    it = cams
    if progress:
        from trisplat.progress import progress_bar

        it = progress_bar(cams, desc="rendering room", unit="view")
    from PIL import Image

    for i, cam in enumerate(it):
        view = raycast_view(mesh, cam, (0.0, 0.0, 0.0), samples_per_pixel, jitter=False, shading=None,
                            seed=seed + i, intersector=isect)
        rgb = np.round(np.clip(view.rgba[..., :3], 0, 1) * 255).astype(np.uint8)
        Image.fromarray(rgb, "RGB").save(out / "images" / cam.name)
    pts, face = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    col = _shade(mesh, np.asarray(face), pts, None)
    write_colmap_text(out, cams, np.asarray(pts), col)
    mesh.export(out / "gt_mesh.ply")
    info = RoomSceneInfo(n_views, width, height, fov_deg, ring_radius, ring_height, room_half, room_height,
                         n_points, seed)
    (out / "synth.json").write_text(json.dumps(asdict(info), indent=2))
    return out
