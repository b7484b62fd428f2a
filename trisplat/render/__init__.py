"""Differentiable triangle splatting: rasterize(...) -> RenderOutput (soft) and rasterize_hard(...) (z-buffer)."""
from __future__ import annotations

from trisplat.render.rasterize import rasterize
from trisplat.render.types import RenderOptions, RenderOutput


def __getattr__(name: str):
    if name == "rasterize_hard":
        from trisplat.render.hard import rasterize_hard

        return rasterize_hard
    raise AttributeError(f"module 'trisplat.render' has no attribute {name!r}")


__all__ = ["rasterize", "rasterize_hard", "RenderOptions", "RenderOutput"]
