"""LoadOptions: every knob of load_dataset, validated, with a JSON-able record of the values used."""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path

ALLOWED_DOWNSCALES = (1, 2, 4, 8)
NORMALIZE_RULES = ("auto", "cameras", "points", "none")
PREPARE_MODES = ("eager", "lazy")
FORMATS = ("auto", "colmap", "blender", "ngp", "rgbd")


def default_cache_dir() -> Path:
    """$XDG_CACHE_HOME/trisplat (or ~/.cache/trisplat): derived images live here, never in the capture folder."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "trisplat"


@dataclass(frozen=True)
class LoadOptions:
    """Options of `load_dataset` (see its docstring); `as_dict()` is what SceneData.options records.

    downscale: 1, 2, 4 or 8; images are area-filtered (Pillow BOX) and K scaled exactly.
    background: RGB in [0,1] that transparent pixels are composited over (white by default).
    test_every: every n-th image (sorted by name, index 0 first) is held out for test when the capture has no
        split of its own; 0 = no test images.
    depth_scale: capture units per raw depth value (RGB-D), or None for the format's own (1/1000 for 16-bit PNG
        depth in millimetres, 1/5000 for TUM).
    cache_dir: where undistorted / downscaled images go (default: $XDG_CACHE_HOME/trisplat or ~/.cache/trisplat).
    memory_budget_mb: the most decoded images kept in memory (least recently used are dropped), in MiB.
    normalize: 'auto' | 'cameras' | 'points' | 'none' (the rule is documented in trisplat.data.normalize).
    images: COLMAP image folder relative to the capture root (default 'images').
    format: 'auto' (detected from the folder) or one of 'colmap', 'blender', 'ngp', 'rgbd' (a folder with both a
        transforms.json and sparse/0 reads as 'ngp' unless told; passing root/sparse/0 as the path means 'colmap').
    prepare: 'eager' writes every cached image at load time (so every Camera.image_path exists);
        'lazy' writes each one on first load_image (fast `trisplat info`).
    """

    downscale: int = 1
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    test_every: int = 8
    depth_scale: float | None = None
    cache_dir: str | None = None
    memory_budget_mb: float = 1024.0
    normalize: str = "auto"
    images: str = "images"
    prepare: str = "eager"
    format: str = "auto"

    def __post_init__(self) -> None:
        if int(self.downscale) not in ALLOWED_DOWNSCALES:
            raise ValueError(f"downscale must be one of {ALLOWED_DOWNSCALES}, got {self.downscale!r}")
        object.__setattr__(self, "downscale", int(self.downscale))
        bg = tuple(float(v) for v in self.background)
        if len(bg) != 3 or not all(0.0 <= v <= 1.0 for v in bg):
            raise ValueError(f"background must be 3 values in [0,1], got {self.background!r}")
        object.__setattr__(self, "background", bg)
        if int(self.test_every) < 0:
            raise ValueError(f"test_every must be >= 0, got {self.test_every}")
        object.__setattr__(self, "test_every", int(self.test_every))
        if self.depth_scale is not None and not float(self.depth_scale) > 0:
            raise ValueError(f"depth_scale must be > 0, got {self.depth_scale}")
        if not float(self.memory_budget_mb) >= 0:
            raise ValueError(f"memory_budget_mb must be >= 0, got {self.memory_budget_mb}")
        if self.normalize not in NORMALIZE_RULES:
            raise ValueError(f"normalize must be one of {NORMALIZE_RULES}, got {self.normalize!r}")
        if self.prepare not in PREPARE_MODES:
            raise ValueError(f"prepare must be one of {PREPARE_MODES}, got {self.prepare!r}")
        if self.format not in FORMATS:
            raise ValueError(f"format must be one of {FORMATS}, got {self.format!r}")
        if self.cache_dir is not None:
            object.__setattr__(self, "cache_dir", str(self.cache_dir))

    @classmethod
    def from_kwargs(cls, downscale: int = 1, **options) -> LoadOptions:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise ValueError(f"unknown load_dataset option(s) {unknown}; known: {sorted(known)}")
        return cls(downscale=downscale, **options)

    @property
    def cache_root(self) -> Path:
        return Path(self.cache_dir).expanduser() if self.cache_dir else default_cache_dir()

    def as_dict(self) -> dict:
        d = asdict(self)
        d["background"] = list(self.background)
        return d
