"""Pinhole cameras in OpenCV axes: the one camera type every stage shares."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A pinhole camera (no distortion: loaders undistort once at load time).

    Axes are OpenCV: x right, y down, z forward. Pixel centres sit at integer + 0.5.

    world_to_camera: float64 [4,4], maps homogeneous world points into the camera frame.
    K: float64 [3,3] intrinsics for an image of `width` x `height` pixels.
    image_path: the (undistorted, downscaled) image this camera sees, or None for a synthetic camera.
    depth_path: optional depth image (RGB-D captures), metres = value * depth_scale.
    """

    world_to_camera: np.ndarray
    K: np.ndarray
    width: int
    height: int
    image_path: Path | None = None
    name: str = ""
    depth_path: Path | None = None
    depth_scale: float = 1.0
    extras: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        w2c = np.asarray(self.world_to_camera, dtype=np.float64)
        K = np.asarray(self.K, dtype=np.float64)
        if w2c.shape != (4, 4):
            raise ValueError(f"camera {self.name!r}: world_to_camera must be [4,4], got {w2c.shape}")
        if K.shape != (3, 3):
            raise ValueError(f"camera {self.name!r}: K must be [3,3], got {K.shape}")
        if not (np.isfinite(w2c).all() and np.isfinite(K).all()):
            raise ValueError(f"camera {self.name!r}: non-finite values in world_to_camera or K")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera {self.name!r}: image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "world_to_camera", w2c)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def stem(self) -> str:
        """The source photo's file stem ('r_0' for 'train/r_0.png'): what users call the view, in output names
        and mask names. Not the stem of `image_path`, which may be a cached copy with a hash in its name. The
        image's stem when the camera has no name; '' for a synthetic camera with neither."""
        if self.name:
            return Path(self.name).stem
        return Path(self.image_path).stem if self.image_path is not None else ""

    @property
    def camera_to_world(self) -> np.ndarray:
        return np.linalg.inv(self.world_to_camera)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, [3]."""
        R, t = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -R.T @ t

    @property
    def forward(self) -> np.ndarray:
        """Unit viewing direction (camera +z) in world coordinates, [3]."""
        return self.world_to_camera[2, :3] / np.linalg.norm(self.world_to_camera[2, :3])

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by `factor` (e.g. 0.5 halves width and height).

        With pixel centres at +0.5, a pixel edge maps to a pixel edge: K's focal and principal point scale by
        exactly `factor` (the principal point is measured from the image corner, not the first pixel centre).
        """
        w, h = round(self.width * factor), round(self.height * factor)
        sx, sy = w / self.width, h / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return replace(self, K=K, width=w, height=h)
