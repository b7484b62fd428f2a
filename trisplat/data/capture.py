"""RawCapture: what a format reader hands over (capture frame, original camera models) before assembly."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# COLMAP camera models we read and undistort, with their parameter names (COLMAP order).
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
FISHEYE_MODELS = ("OPENCV_FISHEYE",)


@dataclass(frozen=True)
class SourceCamera:
    """An original (possibly distorted) camera: COLMAP model name, image size, parameters in COLMAP order.

    Principal points follow COLMAP: pixel centres at +0.5 (the project convention).
    """

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODELS:
            raise ValueError(f"unsupported camera model {self.model!r} (supported: {', '.join(CAMERA_MODELS)})")
        want = len(CAMERA_MODELS[self.model])
        if len(self.params) != want:
            raise ValueError(f"camera model {self.model} takes {want} parameters, got {len(self.params)}")
        object.__setattr__(self, "params", tuple(float(p) for p in self.params))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def needs_undistortion(self) -> bool:
        """False for pinhole models and for distortion models whose distortion parameters are all zero."""
        if self.model in PINHOLE_MODELS:
            return False
        n_intr = 3 if self.model in ("SIMPLE_RADIAL", "RADIAL") else 4
        return any(p != 0.0 for p in self.params[n_intr:])

    def pinhole_K(self) -> np.ndarray:
        """K of the model's pinhole part (focal and principal point, distortion ignored)."""
        p = self.params
        if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            fx = fy = p[0]
            cx, cy = p[1], p[2]
        else:
            fx, fy, cx, cy = p[:4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def with_size(self, width: int, height: int) -> SourceCamera:
        return SourceCamera(self.model, width, height, self.params)


@dataclass
class RawView:
    """One image of a capture in its own frame: OpenCV world-to-camera [4,4], original camera, files."""

    name: str
    world_to_camera: np.ndarray
    camera: SourceCamera
    image_path: Path
    depth_path: Path | None = None
    depth_scale: float = 1.0


@dataclass
class RawCapture:
    """A capture as read from disk, before normalisation, undistortion, downscaling and splitting.

    split: per-view 'train' / 'test' labels when the format has its own split, else None (every n-th held out).
    points / point_colors: float64 [P,3] capture frame and float32 [P,3] RGB in [0,1], or None.
    object_bounds: float64 [2,3] known content box in the capture frame (synthetic scenes), or None.
    """

    format: str
    root: Path
    views: list[RawView]
    split: list[str] | None = None
    points: np.ndarray | None = None
    point_colors: np.ndarray | None = None
    object_bounds: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)
    source_files: list[Path] = field(default_factory=list)


def is_plain_image_folder(root: Path) -> bool:
    """True for a folder holding image files directly and no poses in any format trisplat reads (no COLMAP model,
    no transforms*.json, no RGB-D layout): photos that `trisplat poses` must pose first."""
    from trisplat.data.colmap import find_model_dir
    from trisplat.data.rgbd import find_rgbd_layout
    from trisplat.sfm.inputs import find_images

    root = Path(root)
    if not root.is_dir():
        return False
    if any((root / n).is_file() for n in ("transforms_train.json", "transforms.json", "rgb.txt")):
        return False
    if find_model_dir(root) is not None or find_rgbd_layout(root) is not None:
        return False
    return len(find_images(root)) > 0
