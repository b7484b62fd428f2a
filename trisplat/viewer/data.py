"""What the viewer shows: a mesh (a GLB file as it is, or coloured vertices) and the training and test cameras in the
capture frame, packed for the browser."""
from __future__ import annotations

import io
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trisplat.cameras import Camera
from trisplat.io.axes import capture_up

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
    glb: the bytes of a .glb file the page loads itself with three.js's GLTFLoader (materials, textures and colour
    spaces as the file defines them), instead of `positions`/`faces`/`colors`, which then only give the counts and
    bounds; glb_to_frame [4,4] maps the file's coordinates into this frame (e.g. the Y-up export back into the
    capture frame; identity by default).
    test_cameras / load_test_image: held-out cameras (not drawn as frusta), reachable with `?testcam=K`.
    """

    positions: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    cameras: list[Camera] = field(default_factory=list)
    load_image: Callable[[int], np.ndarray] | None = None
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    title: str = "trisplat"
    glb: bytes | None = None
    glb_to_frame: np.ndarray | None = None
    test_cameras: list[Camera] = field(default_factory=list)
    load_test_image: Callable[[int], np.ndarray] | None = None

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
        if self.glb is not None and self.glb[:4] != b"glTF":
            raise ValueError("viewer: glb must be the bytes of a binary glTF file")
        self.glb_to_frame = np.eye(4) if self.glb_to_frame is None else np.asarray(self.glb_to_frame, np.float64)

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

    def _camera_dict(self, i: int, cam: Camera, split: str, has_image: bool) -> dict:
        c2w = cam.camera_to_world @ OPENCV_TO_OPENGL
        c2w[:3, 3] -= self.origin
        return {
            "index": i,
            "split": split,
            "name": cam.name or f"{split} camera {i}",
            "c2w": c2w.reshape(-1).tolist(),
            "K": cam.K.reshape(-1).tolist(),
            "width": cam.width,
            "height": cam.height,
            "has_image": has_image,
        }

    def scene_dict(self) -> dict:
        """JSON-ready description: counts, bounds, up, and per camera its OpenGL camera-to-world (row-major,
        relative to `origin`), intrinsics and image size. Test cameras are numbered after the training ones (their
        photo is /api/image/<len(cameras) + k>.png). With a GLB: `glb_matrix`, the file's frame -> the page's
        frame (row-major, relative to `origin`)."""
        rel = self.positions - self.origin
        cams = [self._camera_dict(i, c, "train", self.load_image is not None) for i, c in enumerate(self.cameras)]
        n = len(self.cameras)
        test = [self._camera_dict(n + k, c, "test", self.load_test_image is not None)
                for k, c in enumerate(self.test_cameras)]
        to_page = np.eye(4)
        to_page[:3, 3] = -self.origin
        return {
            "title": self.title,
            "num_vertices": int(len(self.positions)),
            "num_faces": int(len(self.faces)),
            "origin": self.origin.tolist(),
            "bounds_min": rel.min(0).tolist(),
            "bounds_max": rel.max(0).tolist(),
            "up": self.up.tolist(),
            "cameras": cams,
            "test_cameras": test,
            "glb": self.glb is not None,
            "glb_matrix": (to_page @ self.glb_to_frame).reshape(-1).tolist(),
        }

    def image_png(self, index: int) -> bytes:
        """The ground-truth photo of camera `index` (test cameras numbered after the training ones) as PNG bytes."""
        from PIL import Image

        n = len(self.cameras)
        if 0 <= index < n and self.load_image is not None:
            img = self.load_image(index)
        elif n <= index < n + len(self.test_cameras) and self.load_test_image is not None:
            img = self.load_test_image(index - n)
        else:
            raise ValueError(f"viewer: no photo for camera {index}")
        img = np.clip(np.asarray(img, dtype=np.float32), 0.0, 1.0)
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


def _glb_geometry(path: Path, to_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions in the frame, faces, grey colours) of every triangle primitive of a GLB: counts and bounds only."""
    from trisplat.eval.spec_render import prepare_asset
    from trisplat.io.gltf import read_glb

    asset = prepare_asset(read_glb(path), to_frame)
    return asset.positions, asset.faces, np.broadcast_to(np.asarray(DEFAULT_COLOR), asset.positions.shape)


def viewer_data_from_mesh(path: str | Path) -> ViewerData:
    """A mesh file (.ply / .obj / .glb), no cameras. A .glb is shown by the page's glTF loader, as it is."""
    from trisplat.io import load_mesh

    path = Path(path)
    if path.suffix.lower() == ".glb":
        positions, faces, colors = _glb_geometry(path, np.eye(4))
        return ViewerData(positions, faces, colors, title=path.name, glb=path.read_bytes())
    positions, faces, colors = load_mesh(path)
    if colors is None:
        colors = np.broadcast_to(np.asarray(DEFAULT_COLOR), positions.shape)
    return ViewerData(positions, faces, colors, title=path.name)


def viewer_data_from_run(run_dir: str | Path, file: str | Path | None = None) -> ViewerData:
    """A run in the capture frame: its mesh, its training cameras and photos and its test cameras (when the capture
    can still be read). The mesh is `file` (a .glb, .ply or .obj; relative paths are taken in the run folder), by
    default RUN/mesh.glb (loaded by the page's glTF loader as any engine loads it, mapped back from the file's Y-up
    frame onto the cameras), else RUN/mesh.ply, else the model's faces with their base colour."""
    from trisplat import run as run_layout
    from trisplat.io import load_mesh

    run_dir = Path(run_dir)
    run = run_layout.open_run(run_dir)
    cameras: list[Camera] = []
    test_cameras: list[Camera] = []
    load_image = load_test_image = None
    data = None
    try:
        data = run.load_scene_data()
    except (FileNotFoundError, ValueError, KeyError) as exc:
        warnings.warn(f"{run_dir}: showing the mesh without cameras: cannot read the capture ({exc})", stacklevel=2)
    else:
        train = [int(i) for i in data.train_indices]
        test = [int(i) for i in data.test_indices]
        cameras = rigid_cameras_in_capture_frame([data.cameras[i] for i in train], data.normalization)
        test_cameras = rigid_cameras_in_capture_frame([data.cameras[i] for i in test], data.normalization)

        def load_image(i: int, _data=data, _train=train) -> np.ndarray:
            return _data.load_image(_train[i])

        def load_test_image(i: int, _data=data, _test=test) -> np.ndarray:
            return _data.load_image(_test[i])

    if file is not None:
        mesh_file = Path(file) if Path(file).is_absolute() or Path(file).exists() else run_dir / file
        if not mesh_file.is_file():
            raise FileNotFoundError(f"{mesh_file}: no such mesh file")
    else:
        mesh_file = next((run_dir / n for n in ("mesh.glb", "mesh.ply") if (run_dir / n).is_file()), None)
    glb, glb_to_frame = None, None
    if mesh_file is not None and mesh_file.suffix.lower() == ".glb":
        glb_to_frame = np.eye(4)
        if data is not None:  # the export's Y-up rotation undone: file -> normalised -> capture frame
            from trisplat.eval.file_scores import file_to_normalized

            glb_to_frame = np.linalg.inv(np.asarray(data.normalization, np.float64)) @ file_to_normalized(
                run, data, mesh_file)
        positions, faces, colors = _glb_geometry(mesh_file, glb_to_frame)
        glb = mesh_file.read_bytes()
    elif mesh_file is not None:
        positions, faces, colors = load_mesh(mesh_file)
        if colors is None:
            colors = np.broadcast_to(np.asarray(DEFAULT_COLOR), positions.shape)
    else:
        scene, normalization = run.load_model()
        inv = np.linalg.inv(np.asarray(normalization, dtype=np.float64))
        positions = scene.positions.detach().cpu().numpy().astype(np.float64) @ inv[:3, :3].T + inv[:3, 3]
        faces = scene.faces.detach().cpu().numpy()
        colors = scene.base_colors().detach().cpu().clamp(0.0, 1.0).numpy()
    up = capture_up(data) if data is not None and cameras else None
    return ViewerData(
        positions, faces, colors, cameras, load_image, up=np.array([0.0, 1.0, 0.0]) if up is None else up,
        title=run_dir.name if mesh_file is None else f"{run_dir.name}/{mesh_file.name}", glb=glb,
        glb_to_frame=glb_to_frame, test_cameras=test_cameras, load_test_image=load_test_image,
    )
