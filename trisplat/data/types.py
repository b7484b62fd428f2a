"""SceneData: the typed hand-off from a capture on disk to initialisation and training."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trisplat.cameras import Camera


@dataclass
class SceneData:
    """A posed capture, in a normalised world frame.

    cameras: every camera of the capture (train and test), OpenCV axes, already undistorted and downscaled.
    train_indices / test_indices: int64 indices into `cameras`.
    points / point_colors: float32 [P,3] sparse points (normalised frame) and their RGB in [0,1], or None.
    normalization: float64 [4,4] similarity with x_normalised = normalization @ x_capture (homogeneous);
        exports apply its inverse so meshes land in the capture's original frame and units.
    background: RGB in [0,1] that transparent ground-truth pixels were composited over.
    format: 'colmap' | 'blender' | 'ngp' | 'rgbd' (what the loader detected).
    warnings: things the loader fixed or skipped, in words a person can read.
    bounds: float64 [2,3] (min, max) box of the scene content in the normalised frame (the object box of a
        synthetic scene, the robust box of the sparse points, or the box of the camera centres), or None.
    options: the loader options actually used (plain JSON-able values): `load_dataset(root, **options)`
        reloads the same dataset.
    depth_loader: callable index -> float32 [H,W] depth in normalised units (RGB-D captures), or None.
    alpha_loader: callable index -> float32 [H,W] alpha in [0,1] of an image with an alpha channel, or None for an
        image without one (RGB); None when the capture cannot load alpha at all.
    """

    cameras: list[Camera]
    train_indices: np.ndarray
    test_indices: np.ndarray
    points: np.ndarray | None = None
    point_colors: np.ndarray | None = None
    normalization: np.ndarray = field(default_factory=lambda: np.eye(4))
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    format: str = ""
    root: Path | None = None
    warnings: list[str] = field(default_factory=list)
    image_loader: object | None = field(default=None, repr=False)
    bounds: np.ndarray | None = None
    options: dict = field(default_factory=dict)
    depth_loader: object | None = field(default=None, repr=False)
    alpha_loader: object | None = field(default=None, repr=False)

    def load_image(self, index: int) -> np.ndarray:
        """Ground-truth image of camera `index`: float32 [H,W,3] in [0,1], composited over `background`."""
        if self.image_loader is None:
            raise RuntimeError("this SceneData has no image loader")
        return self.image_loader(index)

    def load_depth(self, index: int) -> np.ndarray:
        """Depth of camera `index` (RGB-D captures): float32 [H,W] view depth in normalised units, 0 = invalid."""
        if self.depth_loader is None:
            raise RuntimeError(f"this SceneData ({self.format or 'unknown format'}) has no depth maps")
        return self.depth_loader(index)

    def load_alpha(self, index: int) -> np.ndarray | None:
        """Alpha of camera `index`'s image: float32 [H,W] in [0,1], or None when that image has no alpha channel."""
        if self.alpha_loader is None:
            return None
        return self.alpha_loader(index)

    @property
    def scale(self) -> float:
        """Normalised units per capture unit (the uniform scale inside `normalization`)."""
        return float(np.cbrt(abs(np.linalg.det(self.normalization[:3, :3]))))

    @property
    def bounds_radius(self) -> float:
        """Half the diagonal of `bounds` (normalised frame): a content scale that stays meaningful when the
        cameras barely move (RGB-D, forward-facing), where `scene_radius` is tiny. scene_radius when no bounds."""
        if self.bounds is None:
            return self.scene_radius
        return float(0.5 * np.linalg.norm(np.asarray(self.bounds[1]) - np.asarray(self.bounds[0]))) or 1.0

    @property
    def scene_radius(self) -> float:
        """Radius of the camera centres around their mean (normalised frame), a scale for thresholds."""
        c = np.stack([cam.center for cam in self.cameras])
        return float(np.linalg.norm(c - c.mean(0), axis=1).max()) or 1.0
