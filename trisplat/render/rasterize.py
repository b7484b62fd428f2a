"""The public soft rasterizer: rasterize(...) -> RenderOutput; SH, batching, supersampling, backend dispatch."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from trisplat.io.colour import linear_to_srgb_torch, srgb_to_linear_torch
from trisplat.render.inputs import make_options, validate
from trisplat.render.types import RenderOptions, RenderOutput, downsample, stack_views
from trisplat.scene.sh import eval_sh
from trisplat.timing import stage


def camera_center(world_to_camera: torch.Tensor) -> torch.Tensor:
    """World position [3] of the camera centre of a [4,4] world-to-camera matrix."""
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    return -(R.T @ t)


def _render_view(positions, faces, colors, opacities, sigma, w2c, K, width, height, bg, opts: RenderOptions):
    if colors.ndim == 3:  # SH: evaluate per vertex with the direction camera centre -> vertex (fused Numba kernels
        colors = eval_sh(colors, positions - camera_center(w2c))  # on the CPU, torch on a GPU)
    if opts.linear_light:
        colors = srgb_to_linear_torch(colors)
        bg = srgb_to_linear_torch(bg)
    s = opts.supersample
    if s > 1:
        K = K.clone()
        K[:2] = K[:2] * s
    W, H = width * s, height * s
    if opts.backend == "reference":
        from trisplat.render.reference import render_reference

        out = render_reference(positions, faces, colors, opacities, sigma, w2c, K, W, H, bg, opts)
    elif opts.backend == "cuda":
        from trisplat.render.cuda_backend import render_cuda

        out = render_cuda(positions, faces, colors, opacities, sigma, w2c, K, W, H, bg, opts)
    else:
        from trisplat.render.splat import render_numba

        out = render_numba(positions, faces, colors, opacities, sigma, w2c, K, W, H, bg, opts)
    out = downsample(out, s)
    if opts.linear_light:
        out = dataclasses.replace(out, rgb=linear_to_srgb_torch(out.rgb))
    return out


def rasterize(
    positions, faces, colors, opacities, sigma, world_to_camera, K, width, height, background=None, **options
) -> RenderOutput:
    """Render triangles softly (Triangle Splatting+ window, front-to-back alpha compositing). Differentiable.

    positions float [V,3] world; faces int [F,3]; colors [V,3] RGB or [V,(d+1)^2,3] SH (evaluated per vertex with the
    direction from the camera centre); opacities [V] in [0,1] (face opacity = min of its vertices, or mean);
    sigma > 0 window sharpness; world_to_camera [4,4] (OpenCV axes) or [B,4,4]; K [3,3] or [B,3,3]; pixel centres
    at +0.5; background None (black) or [3]. options: fields of RenderOptions (near, supersample, tile_size,
    opacity_mode, perspective_correct, linear_light, backend, ...). Torch tensors or numpy arrays are accepted.

    Returns RenderOutput with rgb [H,W,3], alpha [H,W], depth [H,W] (expected view depth), normal [H,W,3]
    (camera frame), max_weight [F], face_id [H,W] (int64); batched cameras add a leading B axis.
    Gradients of rgb, alpha, depth and normal reach positions, colors (hence SH) and opacities; for
    opacity_mode='min' the arg-min vertex of each face gets its face's opacity gradient.
    """
    opts = make_options(options)
    with stage("r_validate"):
        vi = validate(positions, faces, colors, opacities, sigma, world_to_camera, K, width, height, background,
                      opts.check_values)
    outs = [
        _render_view(
            vi.positions,
            vi.faces,
            vi.colors,
            vi.opacities,
            vi.sigma,
            vi.world_to_camera[b],
            vi.K[b],
            vi.width,
            vi.height,
            vi.background,
            opts,
        )
        for b in range(vi.world_to_camera.shape[0])
    ]
    if not vi.batched:
        return outs[0]
    return stack_views(outs)


def vertices_in_view(positions, faces, world_to_camera, K, width: int, height: int, near: float = RenderOptions.near,
                     far: float = RenderOptions.far):
    """uint8 [V] numpy array: 1 for a superset of the vertices whose colours and opacities a render of this view
    (the same positions, faces [F,3], [4,4] pose, [3,3] K, size and near/far planes; any supersampling) reads,
    0 for the rest, which get no gradient from it: the vertices of every face with no vertex nearer than `near`,
    not wholly beyond `far`, whose projected bounding box meets the image (kernels.vertices_in_view). A caller that
    computes per-vertex inputs of the render (the trainer's SH colours) can skip the others. CPU tensors only."""
    from trisplat.render import kernels as kn

    pos = np.ascontiguousarray(torch.as_tensor(positions).detach().to(torch.float32).numpy())
    fc = np.ascontiguousarray(torch.as_tensor(faces).detach().numpy())
    w2c = np.ascontiguousarray(torch.as_tensor(world_to_camera).detach().numpy(), dtype=np.float64)
    Kn = np.ascontiguousarray(torch.as_tensor(K).detach().numpy(), dtype=np.float64)
    mask = np.empty(pos.shape[0], np.uint8)
    kn.vertices_in_view(pos, fc, w2c, Kn, float(near), float(far), int(width), int(height), mask)
    return mask


__all__ = ["rasterize", "camera_center", "vertices_in_view"]
