"""trisplat: posed photographs (or RGB-D) -> an opaque, connected triangle mesh, by differentiable triangle splatting.

Public entry points (stable; outside checks call them):
    trisplat.rasterize(positions, faces, colors, opacities, sigma, world_to_camera, K, width, height,
                       background=None, **options) -> RenderOutput
    trisplat.load_dataset(path, downscale=1, **options) -> SceneData

The Python API for notebooks (what the `train`, `slam` and `export` commands run; trisplat/api.py):
    import trisplat.api as ts
    ts.train(data, out, minutes=None, preset="default", **config) -> TrainedRun  (.render, .mesh, .export, .psnr)
    ts.load_run(run_dir) -> TrainedRun;  ts.slam(capture, out, **slam_config) -> SlamRun  (.trajectory, .mesh)
"""
from __future__ import annotations

__version__ = "0.1.0"

_LAZY = {
    "rasterize": ("trisplat.render", "rasterize"),
    "rasterize_hard": ("trisplat.render", "rasterize_hard"),
    "RenderOutput": ("trisplat.render.types", "RenderOutput"),
    "RenderOptions": ("trisplat.render.types", "RenderOptions"),
    "load_dataset": ("trisplat.data", "load_dataset"),
    "SceneData": ("trisplat.data.types", "SceneData"),
    "Camera": ("trisplat.cameras", "Camera"),
    "TriangleScene": ("trisplat.scene.model", "TriangleScene"),
    "TrainedRun": ("trisplat.api", "TrainedRun"),
    "SlamRun": ("trisplat.api", "SlamRun"),
    "load_run": ("trisplat.api", "load_run"),
}

__all__ = sorted(_LAZY) + ["__version__", "api"]


def __getattr__(name: str):
    if name == "api":  # `import trisplat; trisplat.api.train(...)` without importing the submodule first
        import importlib

        return importlib.import_module("trisplat.api")
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'trisplat' has no attribute {name!r}")
