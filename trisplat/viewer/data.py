"""What the viewer shows: a coloured mesh and the training cameras in the capture frame, packed for the browser."""
from __future__ import annotations

import io
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trisplat.cameras import Camera
from trisplat.io.axes import estimate_capture_up

# OpenCV camera axes (x right, y down, z forward) -> three.js / OpenGL axes (x right, y up, z back).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
DEFAULT_COLOR = (0.7, 0.7, 0.7)  # mesh files without vertex colours are shown in this grey


@dataclass
class ViewerData:
    """A mesh and (optionally) cameras with their photos, all in one frame (the capture's, for runs).

    positions float32 [V,3], faces int32 [F,3], colors float32 [V,3] in [0,1].
    cameras: OpenCV cameras in the same frame as the mesh (their world_to_camera is a rigid motion).
    load_image: index into `cameras` -> float32 [H,W,3] ground-truth photo, or None when there are no photos.
    up: the scene's up direction (unit [3]) for orbit and walk controls.
    """

    positions: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    cameras: list[Camera] = field(default_factory=list)
    load_image: Callable[[int], np.ndarray] | None = None
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    title: str = "trisplat"

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        if self.positions.ndim != 2 or self.positions.shape[1] != 3 or len(self.positions) == 0:
            raise ValueError(f"viewer: positions must be a non-empty [V,3], got {self.positions.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise ValueError(f"viewer: faces must be a non-empty [F,3], got {self.faces.shape}")
        if self.faces.min() < 0 or self.faces.max() >= len(self.positions):
            raise ValueError("viewer: faces index vertices outside the vertex table")
        self.colors = np.clip(np.asarray(self.colors, dtype=np.float64), 0.0, 1.0)
        if self.colors.shape != self.positions.shape:
            raise ValueError(f"viewer: colors must be [V,3] like positions, got {self.colors.shape}")
        self.up = np.asarray(self.up, dtype=np.float64) / np.linalg.norm(self.up)

    @property
    def origin(self) -> np.ndarray:
        """Centre of the mesh's bounding box: the browser works relative to it (float32 precision)."""
        return (self.positions.min(0) + self.positions.max(0)) / 2.0

    def mesh_bytes(self) -> bytes:
        """positions float32 [V*3] (relative to `origin`) | colours uint8 [V*3] padded to 4 bytes | indices uint32."""
        pos = (self.positions - self.origin).astype("<f4").tobytes()
        rgb = np.round(self.colors * 255.0).astype(np.uint8).tobytes()
        rgb += b"\0" * (-len(rgb) % 4)
        return pos + rgb + self.faces.astype("<u4").tobytes()

    def scene_dict(self) -> dict:
        """JSON-ready description: counts, bounds, up, and per camera its OpenGL camera-to-world (row-major,
        relative to `origin`), intrinsics and image size."""
        rel = self.positions - self.origin
        cams = []
        for i, cam in enumerate(self.cameras):
            c2w = cam.camera_to_world @ OPENCV_TO_OPENGL
            c2w[:3, 3] -= self.origin
            cams.append(
                {
                    "index": i,
                    "name": cam.name or f"camera {i}",
                    "c2w": c2w.reshape(-1).tolist(),
                    "K": cam.K.reshape(-1).tolist(),
                    "width": cam.width,
                    "height": cam.height,
                    "has_image": self.load_image is not None,
                }
            )
        return {
            "title": self.title,
            "num_vertices": int(len(self.positions)),
            "num_faces": int(len(self.faces)),
            "origin": self.origin.tolist(),
            "bounds_min": rel.min(0).tolist(),
            "bounds_max": rel.max(0).tolist(),
            "up": self.up.tolist(),
            "cameras": cams,
        }

    def image_png(self, index: int) -> bytes:
        """The ground-truth photo of camera `index` as PNG bytes."""
        from PIL import Image

        if self.load_image is None or not 0 <= index < len(self.cameras):
            raise ValueError(f"viewer: no photo for camera {index}")
        img = np.clip(np.asarray(self.load_image(index), dtype=np.float32), 0.0, 1.0)
        buf = io.BytesIO()
        Image.fromarray(np.round(img * 255.0).astype(np.uint8)).save(buf, format="PNG")
        return buf.getvalue()


def rigid_cameras_in_capture_frame(cameras: list[Camera], normalization: np.ndarray) -> list[Camera]:
    """Cameras of the normalised frame expressed in the capture frame (x_norm = normalization @ x_capture, a
    translation and uniform scale): same orientation and intrinsics, centre mapped by the inverse normalisation."""
    N = np.asarray(normalization, dtype=np.float64)
    inv = np.linalg.inv(N)
    scale = float(np.cbrt(np.linalg.det(inv[:3, :3])))
    out = []
    for cam in cameras:
        c2w = inv @ cam.camera_to_world
        c2w[:3, :3] /= scale  # the rotation part carried the normalisation's scale
        out.append(Camera(np.linalg.inv(c2w), cam.K, cam.width, cam.height, cam.image_path, cam.name))
    return out


def viewer_data_from_mesh(path: str | Path) -> ViewerData:
    """A mesh file (.ply / .obj / .glb), no cameras."""
    from trisplat.io import load_mesh

    positions, faces, colors = load_mesh(path)
    if colors is None:
        colors = np.broadcast_to(np.asarray(DEFAULT_COLOR), positions.shape)
    return ViewerData(positions, faces, colors, title=Path(path).name)


def viewer_data_from_run(run_dir: str | Path) -> ViewerData:
    """A run: its mesh (RUN/mesh.ply when training wrote one, else the model's faces with their base colour) in
    the capture frame, and its training cameras and photos (when the capture can still be read)."""
    from trisplat import run as run_layout
    from trisplat.io import load_mesh

    run = run_layout.open_run(run_dir)
    mesh_file = Path(run_dir) / "mesh.ply"
    if mesh_file.is_file():
        positions, faces, colors = load_mesh(mesh_file)
        if colors is None:
            colors = np.broadcast_to(np.asarray(DEFAULT_COLOR), positions.shape)
    else:
        scene, normalization = run.load_model()
        inv = np.linalg.inv(np.asarray(normalization, dtype=np.float64))
        positions = scene.positions.detach().cpu().numpy().astype(np.float64) @ inv[:3, :3].T + inv[:3, 3]
        faces = scene.faces.detach().cpu().numpy()
        colors = scene.base_colors().detach().cpu().clamp(0.0, 1.0).numpy()
    cameras: list[Camera] = []
    load_image = None
    try:
        data = run.load_scene_data()
    except (FileNotFoundError, ValueError, KeyError) as exc:
        warnings.warn(f"{run_dir}: showing the mesh without cameras: cannot read the capture ({exc})", stacklevel=2)
    else:
        train = [int(i) for i in data.train_indices]
        cameras = rigid_cameras_in_capture_frame([data.cameras[i] for i in train], data.normalization)

        def load_image(i: int, _data=data, _train=train) -> np.ndarray:
            return _data.load_image(_train[i])

    up = estimate_capture_up(cameras) if cameras else None
    return ViewerData(
        positions, faces, colors, cameras, load_image, up=np.array([0.0, 1.0, 0.0]) if up is None else up,
        title=Path(run_dir).name,
    )
