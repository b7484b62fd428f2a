"""Differentiable triangle splatting: rasterize(...) -> RenderOutput (soft) and rasterize_hard(...) (z-buffer)."""
