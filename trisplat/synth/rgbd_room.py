"""A synthetic hand-held RGB-D capture of a room with exact ground-truth poses, in the 7-Scenes layout that
`trisplat slam` and `trisplat bench slam --capture` read.

Scene (`rgbd_room_mesh`): `trisplat.synth.room.room_mesh` (a 5 x 5 m floor with a two-colour checker, four walls
of random pastel tiles, a pale ceiling 2.5 m up, the demo objects on a checkered disk of radius 1.2 m in the middle)
plus furniture near the walls (a cabinet, a table on four legs, a bench, a shelf, a lamp post with a round shade, a
ball): coloured boxes, cylinders and spheres, so a view holds content from about 0.8 m to 5 m away. The fixed light of
`ROOM_SHADING` is baked into the vertex colours (view independent, no specular), so the photos agree with each
other up to pixel sampling and the sensor noise.

Path (`room_walk_c2w`): one closed walk around the middle, counter-clockwise seen from above, on an ellipse of
semi-axes 1.6 m (x) by 1.3 m (y) (+-4% slow wobble; about 9 m long) at 1.4 m eye height with a 1.5 cm walking bob
(a period of about 15 frames: two steps a second at 30 frames/s) and +-5 cm slow drift. The camera looks mostly
inwards, across the room (towards the objects and the far walls), pitched 18-26 degrees down, its heading swinging
up to about 36 degrees either side of the centre and its roll up to 3 degrees, all slowly. Every term is periodic
over the walk, so frame n (which is not written) would be frame 0 again: the last frame is one step from the first,
and the sequence closes a loop. At the default 300 frames a step is about 3 cm and 1.2 degrees (2.5 at most; a person at 30
frames/s); fewer frames take longer steps along the same path. The nearest surface any pixel sees is about 0.8 m
away (never a wall closer than 0.5 m). `seed` sets the start point on the ellipse, the phases of the slow terms, the
wall and object hues, and the noise.

Sensor (`sensor=True`, the default; a Kinect-like model): depth from the pixel-centre ray of
`trisplat.synth.raycast.raycast_view` (view depth, camera z), plus Gaussian noise of sigma `depth_sigma` * z^2
(1.5 mm at 1 m, 2.4 cm at 4 m), missing (0) beyond `max_depth` (4 m) and where the ray meets the surface more than
`max_incidence_deg` (80 degrees) from its normal; colour with Gaussian noise of sigma `color_sigma` (0.01) per
channel. Colour is the box-filtered mean of `color_samples` x `color_samples` rays per pixel (2: anti-aliased, as a
camera integrates over the pixel). With `sensor=False` depth is exact up to its millimetre quantisation everywhere
and colour is exact up to its 8-bit quantisation. Noise is drawn per frame from (seed, frame number), so the result
does not depend on `workers`.

Units and axes (docs/conventions.md): metres; world z up, the floor at z = 0, the room's middle at x = y = 0;
cameras in OpenCV axes (x right, y down, z forward), pixel centres at +0.5. Files in OUT: frame-NNNNNN.color.png
(RGB, 8 bits), frame-NNNNNN.depth.png (uint16 millimetres, 0 = missing), frame-NNNNNN.pose.txt (camera-to-world
4x4 in the world above), camera-intrinsics.txt (3x3 K with an integer-centred principal point, as 7-Scenes': the
reader adds 0.5), gt_mesh.ply (the true mesh, world frame, baked vertex colours), gt_mesh_seen.ply (its faces hit by
at least one pixel with a depth measurement: the part a reconstruction can recover), synth.json (the settings).
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import trimesh

from trisplat.cameras import Camera
from trisplat.synth.orbit import intrinsics, look_at
from trisplat.synth.raycast import _intersector, raycast_view
from trisplat.synth.room import ROOM_SHADING, room_mesh
from trisplat.synth.scenes import _gradient_cylinder, _gradient_sphere, _hsv, _rgba, _unmerged, bake_shading

ROOM_HALF = 2.5  # metres: the floor is 2 ROOM_HALF square
ROOM_HEIGHT = 2.5
EYE_HEIGHT = 1.4
ELLIPSE = (1.6, 1.3)  # semi-axes of the walk along x and y, metres
BOB_PERIOD_FRAMES = 15.0  # two steps a second at 30 frames/s
KINECT_FOV_DEG = 60.0  # horizontal field of view (a Kinect v1's depth camera: about 58 degrees)


def _box(center, extents, yaw: float, hue: float) -> trimesh.Trimesh:
    """A box of `extents` (x, y, z metres) standing on the floor under `center`'s (x, y) with its middle at
    `center`, turned by `yaw` about z, each of its six sides a different flat colour of a palette about `hue`."""
    b = _unmerged(trimesh.creation.box(extents=extents))
    axis = np.argmax(np.abs(b.face_normals), axis=1)
    side = axis * 2 + (b.face_normals[np.arange(len(axis)), axis] > 0)
    palette = np.array([_hsv(hue + k / 9.0, 0.55, 0.55 + 0.07 * k) for k in range(6)])
    b.visual.vertex_colors = _rgba(np.repeat(palette[side], 3, axis=0))
    b.apply_transform(trimesh.transformations.rotation_matrix(yaw, [0, 0, 1]))
    b.apply_translation(center)
    return b


def furniture_mesh(seed: int = 0) -> trimesh.Trimesh:
    """Furniture near the walls of the 5 x 5 m room, unshaded vertex colours, standing on z = 0 (metres, z up):
    a cabinet in the (+x, +y) corner, a table on four legs in the (-x, -y) corner, a bench along the +y wall, a shelf
    along the +x wall, a lamp post with a round shade in the (-x, +y) corner and a ball on the floor near the -y
    wall. Everything stays at least 0.5 m from the walk of `room_walk_c2w`. `seed` shifts the hues."""
    rng = np.random.default_rng(seed)
    hue = float(rng.uniform(0, 1)) if seed else 0.0
    parts = [
        _box((1.95, 2.1, 0.45), (0.8, 0.5, 0.9), 0.0, hue + 0.05),  # cabinet
        _box((-1.9, -1.95, 0.735), (1.0, 0.6, 0.05), 0.0, hue + 0.3),  # table top
        _box((0.0, 2.25, 0.225), (1.2, 0.4, 0.45), 0.0, hue + 0.55),  # bench
        _box((2.3, -0.9, 0.7), (0.35, 1.0, 1.4), 0.0, hue + 0.75),  # shelf
        _gradient_cylinder((-2.15, 1.9, 0.0), 0.06, 1.5, hue + 0.15),  # lamp post
        _gradient_sphere((-2.15, 1.9, 1.65), 0.2, hue + 0.4),  # its shade
        _gradient_sphere((0.9, -2.1, 0.25), 0.25, hue + 0.9),  # ball
    ]
    for dx in (-0.45, 0.45):
        for dy in (-0.25, 0.25):
            parts.append(_gradient_cylinder((-1.9 + dx, -1.95 + dy, 0.0), 0.025, 0.71, hue + 0.3))  # table legs
    return trimesh.util.concatenate(parts)


def rgbd_room_mesh(seed: int = 0) -> trimesh.Trimesh:
    """The room of this capture (see the module docstring): room_mesh (5 x 5 x 2.5 m, the demo objects in the
    middle) plus furniture_mesh, with ROOM_SHADING baked into the vertex colours; metres, z up, floor at z = 0."""
    room = room_mesh(ROOM_HALF, ROOM_HEIGHT, seed=seed)
    return trimesh.util.concatenate([room, bake_shading(furniture_mesh(seed), ROOM_SHADING)])


def _check_frames(n_frames: int) -> None:
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 3:
        raise ValueError(f"n_frames must be an integer >= 3 (a closed walk needs at least 3 frames), got {n_frames!r}")


def room_walk_c2w(n_frames: int = 300, seed: int = 0) -> list[np.ndarray]:
    """Camera-to-world [4,4] (OpenCV camera axes, metres, world z up) of the closed walk of the module docstring at
    `n_frames` evenly timed frames: frame k is at walk fraction k / n_frames, so frame n_frames would be frame 0."""
    _check_frames(n_frames)
    rng = np.random.default_rng(seed)
    start = float(rng.uniform(0.0, 2.0 * math.pi))
    ph = rng.uniform(0.0, 2.0 * math.pi, size=10)
    bob_cycles = max(1, round(n_frames / BOB_PERIOD_FRAMES))
    tau = 2.0 * math.pi
    out = []
    for k in range(n_frames):
        s = k / n_frames
        th = start + tau * s
        a = ELLIPSE[0] * (1.0 + 0.04 * math.sin(tau * 2 * s + ph[0]))
        b = ELLIPSE[1] * (1.0 + 0.04 * math.sin(tau * 3 * s + ph[1]))
        z = EYE_HEIGHT + 0.015 * math.sin(tau * bob_cycles * s + ph[2]) + 0.05 * math.sin(tau * 2 * s + ph[3])
        eye = np.array([a * math.cos(th), b * math.sin(th), z])
        yaw = math.atan2(-eye[1], -eye[0]) + math.radians(30.0 * math.sin(tau * s + ph[4])
                                                           + 6.0 * math.sin(tau * 3 * s + ph[5]))
        pitch = -math.radians(22.0 + 4.0 * math.sin(tau * 2 * s + ph[6]))
        roll = math.radians(2.5 * math.sin(tau * 2 * s + ph[7]) + 0.5 * math.sin(tau * bob_cycles * s + ph[8]))
        fwd = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
        w2c = look_at(eye, eye + fwd)
        c, sn = math.cos(roll), math.sin(roll)
        w2c[:3] = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]]) @ w2c[:3]  # roll about the view axis
        out.append(np.linalg.inv(w2c))
    return out


@dataclass(frozen=True)
class SensorModel:
    """The Kinect-like sensor of the module docstring (sensor=True). Depth sigma = depth_sigma * z^2 (metres, z in
    metres); 0 (missing) beyond max_depth metres or at incidence beyond max_incidence_deg; colour noise sigma in
    [0, 1] units."""

    depth_sigma: float = 0.0015
    max_depth: float = 4.0
    max_incidence_deg: float = 80.0
    color_sigma: float = 0.01


@dataclass(frozen=True)
class RGBDRoomInfo:
    """What write_rgbd_room wrote (also OUT/synth.json)."""

    out: str
    n_frames: int
    width: int
    height: int
    fov_deg: float
    seed: int
    sensor: bool
    sensor_model: dict
    color_samples: int
    path_length_m: float
    mean_step_m: float
    max_step_m: float
    mean_step_deg: float
    max_step_deg: float
    missing_depth_fraction: float
    mesh_faces: int
    seen_faces: int
    seconds: float
    workers: int


def _rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def render_rgbd_frame(mesh: trimesh.Trimesh, camera: Camera, frame: int, seed: int = 0, sensor: SensorModel | None =
                      SensorModel(), color_samples: int = 2, intersector=None):
    """One frame: (rgb uint8 [H,W,3], depth uint16 [H,W] millimetres (0 = missing), face id int64 [H,W] of each
    pixel-centre ray that has a depth (-1 elsewhere)). sensor None: exact depth and colour (quantised only)."""
    v = raycast_view(mesh, camera, None, color_samples, jitter=False, shading=None, intersector=intersector)
    face = v.face_id
    z = v.depth.astype(np.float64)
    valid = face >= 0
    rgb = v.rgba[..., :3].astype(np.float64)
    if sensor is not None:
        rng = np.random.default_rng([int(seed), int(frame)])
        H, W = z.shape
        xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        d_cam = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(camera.K).T
        d_world = d_cam @ camera.world_to_camera[:3, :3]  # R^T d per pixel
        d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
        n = np.zeros((H, W, 3))
        n[valid] = mesh.face_normals[face[valid]]
        cos_inc = np.abs(np.einsum("hwk,hwk->hw", n, d_world))
        valid &= (z <= sensor.max_depth) & (cos_inc >= math.cos(math.radians(sensor.max_incidence_deg)))
        z = z + rng.normal(size=z.shape) * (sensor.depth_sigma * z * z)
        rgb = rgb + rng.normal(scale=sensor.color_sigma, size=rgb.shape)
    mm = np.where(valid, np.clip(np.round(z * 1000.0), 1, 65534), 0).astype(np.uint16)
    face = np.where(mm > 0, face, -1)
    return np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8), mm, face


def write_sevenscenes_frame(out: Path, k: int, rgb: np.ndarray, mm: np.ndarray, c2w: np.ndarray) -> None:
    """Frame k in the 7-Scenes layout: rgb [H,W,3] uint8, depth mm [H,W] uint16 (0: no reading), c2w [4,4]."""
    from PIL import Image

    Image.fromarray(rgb, "RGB").save(out / f"frame-{k:06d}.color.png")
    Image.fromarray(mm).save(out / f"frame-{k:06d}.depth.png")
    np.savetxt(out / f"frame-{k:06d}.pose.txt", c2w)


def write_noiseless_sequence(root: Path, mesh, path_w2c, K: np.ndarray, width: int, height: int) -> Path:
    """Ray-cast `mesh` (vertex colours, trisplat.synth.raycast) from each world-to-camera of `path_w2c` into `root`
    in the 7-Scenes layout: exact depth in millimetres, white where nothing is hit, no sensor noise. Returns root."""
    from trisplat.cameras import Camera

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    for k, w2c in enumerate(path_w2c):
        v = raycast_view(mesh, Camera(w2c, K, width, height), background=(1.0, 1.0, 1.0))
        write_sevenscenes_frame(root, k, (v.rgba[..., :3] * 255 + 0.5).astype(np.uint8),
                                np.round(v.depth * 1000).astype(np.uint16), np.linalg.inv(w2c))
    write_sevenscenes_intrinsics(root, K)
    return root


def write_sevenscenes_intrinsics(out: Path, K: np.ndarray) -> None:
    """camera-intrinsics.txt from K [3,3] (pixel centres at +0.5): integer-centred, as 7-Scenes' (the reader adds
    0.5 back)."""
    K_file = np.asarray(K, np.float64).copy()
    K_file[:2, 2] -= 0.5
    np.savetxt(Path(out) / "camera-intrinsics.txt", K_file)


_WORKER: dict = {}


def _worker_init(seed: int) -> None:
    mesh = rgbd_room_mesh(seed)
    _WORKER.update(mesh=mesh, isect=_intersector(mesh))


def _render_and_write(out: Path, k: int, camera: Camera, c2w: np.ndarray, seed: int, sensor, color_samples: int):
    rgb, mm, face = render_rgbd_frame(_WORKER["mesh"], camera, k, seed, sensor, color_samples, _WORKER["isect"])
    write_sevenscenes_frame(out, k, rgb, mm, c2w)
    return k, np.unique(face[face >= 0]), int((mm == 0).sum())


def write_rgbd_room(out_dir: str | Path, n_frames: int = 300, width: int = 320, height: int = 240,
                    fov_deg: float = KINECT_FOV_DEG, seed: int = 0, sensor: bool = True,
                    sensor_model: SensorModel = SensorModel(), color_samples: int = 2, workers: int = 1,
                    progress: bool = False) -> RGBDRoomInfo:
    """Ray-cast rgbd_room_mesh(seed) along room_walk_c2w(n_frames, seed) with a pinhole camera of `width` x
    `height` pixels and horizontal field of view `fov_deg`, and write the 7-Scenes folder of the module docstring
    into `out_dir`. sensor: apply `sensor_model` (False: exact depth to the millimetre, exact colour). workers:
    processes rendering frames in parallel (1: in this process). Returns what it wrote (also OUT/synth.json)."""
    _check_frames(n_frames)
    for name, val in (("width", width), ("height", height)):
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < 8:
            raise ValueError(f"{name} must be an integer >= 8 pixels, got {val!r}")
    if not 1.0 <= fov_deg <= 150.0:
        raise ValueError(f"fov_deg must be in [1, 150] degrees, got {fov_deg}")
    if color_samples < 1:
        raise ValueError(f"color_samples must be >= 1, got {color_samples}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stale = list(out.glob("frame-*"))
    if stale:  # replace an older rgbd-room capture (a shorter one must not leave frames behind), nothing else
        try:
            ours = "sensor_model" in json.loads((out / "synth.json").read_text())
        except (OSError, ValueError):
            ours = False
        if not ours:
            raise FileExistsError(f"{out}: holds frame-* files that are not an rgbd-room capture; choose another folder")
        for p in stale:
            p.unlink()
    mesh = rgbd_room_mesh(seed)
    c2ws = room_walk_c2w(n_frames, seed)
    K = intrinsics(width, height, fov_deg)
    cams = [Camera(np.linalg.inv(c), K.copy(), width, height, name=f"frame-{k:06d}") for k, c in enumerate(c2ws)]
    model = sensor_model if sensor else None
    seen = np.zeros(len(mesh.faces), bool)
    missing = 0
    bar = None
    if progress:
        from trisplat.progress import progress_bar

        bar = progress_bar(total=n_frames, desc="rendering RGB-D room", unit="frame")
    if workers == 1:
        _worker_init(seed)
        for k, (cam, c2w) in enumerate(zip(cams, c2ws)):
            _, faces, miss = _render_and_write(out, k, cam, c2w, seed, model, color_samples)
            seen[faces] = True
            missing += miss
            if bar is not None:
                bar.update(1)
        _WORKER.clear()
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_worker_init,
                                 initargs=(seed,)) as pool:
            futs = [pool.submit(_render_and_write, out, k, cam, c2w, seed, model, color_samples)
                    for k, (cam, c2w) in enumerate(zip(cams, c2ws))]
            for f in as_completed(futs):
                _, faces, miss = f.result()
                seen[faces] = True
                missing += miss
                if bar is not None:
                    bar.update(1)
    if bar is not None:
        bar.close()
    write_sevenscenes_intrinsics(out, K)
    mesh.export(out / "gt_mesh.ply")
    seen_mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[seen], process=False)
    seen_mesh.visual.vertex_colors = mesh.visual.vertex_colors
    seen_mesh.remove_unreferenced_vertices()
    seen_mesh.export(out / "gt_mesh_seen.ply")
    centres = np.array([c[:3, 3] for c in c2ws])
    closed = np.concatenate([centres, centres[:1]])
    steps = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    rots = [_rotation_deg(c2ws[k][:3, :3], c2ws[(k + 1) % n_frames][:3, :3]) for k in range(n_frames)]
    info = RGBDRoomInfo(
        out=str(out), n_frames=n_frames, width=width, height=height, fov_deg=float(fov_deg), seed=seed,
        sensor=bool(sensor), sensor_model=asdict(sensor_model) if sensor else {}, color_samples=color_samples,
        path_length_m=float(steps.sum()), mean_step_m=float(steps.mean()), max_step_m=float(steps.max()),
        mean_step_deg=float(np.mean(rots)), max_step_deg=float(np.max(rots)),
        missing_depth_fraction=missing / float(n_frames * width * height), mesh_faces=len(mesh.faces),
        seen_faces=int(seen.sum()), seconds=time.perf_counter() - t0, workers=workers)
    (out / "synth.json").write_text(json.dumps(asdict(info), indent=2))
    return info


def default_workers() -> int:
    """Processes for rendering: the cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)
