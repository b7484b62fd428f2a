"""Soft rendering of one view with the Numba kernels, wired into torch autograd (the wiring only; maths in kernels.py)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from trisplat.render import kernels as kn
from trisplat.timing import stage
from trisplat.render.types import RenderOptions, RenderOutput

BACKWARD_FACE_CHUNK = 1 << 16  # faces per chunk of the per-face backward (bounds its scratch memory)


@dataclass
class _Bins:
    """Everything the forward pass leaves for the backward pass (numpy arrays)."""

    pos: np.ndarray
    faces: np.ndarray
    w2c: np.ndarray
    K: np.ndarray
    theta: np.ndarray
    rect: np.ndarray
    argmin: np.ndarray
    face_start: np.ndarray
    pair_face: np.ndarray
    tile_start: np.ndarray
    tile_pairs: np.ndarray
    pos_of: np.ndarray
    images: tuple
    bg: np.ndarray


def _np32(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float32).cpu().numpy())


def forward_numba(
    positions, faces, vertex_rgb, opacities, sigma, world_to_camera, K, width, height, background, opts: RenderOptions
):
    """Run setup, binning and the forward tile kernel. Returns (images tuple, max_weight, face_id, counters, bins)."""
    pos = _np32(positions)
    fc = np.ascontiguousarray(faces.detach().cpu().numpy(), dtype=np.int32)
    w2c = np.ascontiguousarray(world_to_camera.detach().cpu().numpy().astype(np.float64))
    Kn = np.ascontiguousarray(K.detach().cpu().numpy().astype(np.float64))
    rgb_v, op_v, bg = _np32(vertex_rgb), _np32(opacities), _np32(background)
    F = fc.shape[0]
    tile = int(opts.tile_size)
    # (setup_faces writes every face's ntiles, and theta, rect and argmin of the faces it keeps, the only ones read
    # after it; culled faces keep the key 0)
    theta = np.empty((F, kn.N_THETA), np.float32)
    rect = np.empty((F, 4), np.int32)
    key = np.zeros(F, np.float32)
    argmin = np.empty(F, np.int8)
    ntiles = np.empty(F, np.int64)
    with stage("r_setup"):
        kn.setup_faces(
            pos,
            fc,
            w2c,
            Kn,
            rgb_v,
            op_v,
            opts.opacity_mode == "min",
            float(opts.near),
            float(opts.far),
            float(opts.min_area_px),
            float(opts.grazing_cos),
            width,
            height,
            tile,
            theta,
            rect,
            key,
            argmin,
            ntiles,
        )
    # Front-to-back face order: a stable sort of the depth keys of the faces on screen (bin_faces skips the others;
    # on a surface seen from inside, most faces are culled) by their int32 bits (positive float32 depths order like
    # them): kernels.depth_order, a parallel radix sort giving numpy's stable argsort's order
    with stage("r_sort"):
        order = kn.depth_order(ntiles, key)
    with stage("r_bin"):
        face_start, pair_face, tile_start, tile_pairs, pos_of = kn.bin_faces(
            theta, rect, ntiles, order, width, height, tile
        )
    rgb = np.empty((height, width, 3), np.float32)
    alpha = np.empty((height, width), np.float32)
    depth = np.empty((height, width), np.float32)
    normal = np.empty((height, width, 3), np.float32)
    face_id = np.empty((height, width), np.int64)
    pair_weight = np.zeros(pair_face.shape[0], np.float32)
    evals = np.zeros(tile_start.shape[0] - 1, np.int64)
    with stage("r_raster"):
        kn.raster_forward(
            theta,
            rect,
            pair_face,
            tile_start,
            tile_pairs,
            width,
            height,
            tile,
            float(sigma),
            float(opts.alpha_min),
            float(opts.alpha_max),
            float(opts.transmittance_min),
            bool(opts.perspective_correct),
            bg,
            rgb,
            alpha,
            depth,
            normal,
            face_id,
            pair_weight,
            evals,
        )
    with stage("r_maxw"):
        max_weight = kn.reduce_max_weight(pair_weight, face_start, pos_of)
    bins = _Bins(
        pos,
        fc,
        w2c,
        Kn,
        theta,
        rect,
        argmin,
        face_start,
        pair_face,
        tile_start,
        tile_pairs,
        pos_of,
        (rgb, alpha, depth, normal),
        bg,
    )
    return (rgb, alpha, depth, normal), max_weight, face_id, int(evals.sum()), int((ntiles > 0).sum()), bins


def backward_numba(bins: _Bins, sigma, width, height, opts: RenderOptions, g_rgb, g_alpha, g_depth, g_normal):
    """Exact gradients w.r.t. vertex positions [V,3], vertex colours [V,3] and vertex opacities [V] (float32)."""
    rgb, alpha, depth, normal = bins.images
    P = bins.pair_face.shape[0]
    with stage("rb_zero"):
        pair_grad = np.empty((P, kn.N_THETA), np.float32)  # (raster_backward writes every row)
    with stage("rb_raster"):
        kn.raster_backward(
            bins.theta,
            bins.rect,
            bins.pair_face,
            bins.tile_start,
            bins.tile_pairs,
            width,
            height,
            int(opts.tile_size),
            float(sigma),
            float(opts.alpha_min),
            float(opts.alpha_max),
            float(opts.transmittance_min),
            bool(opts.perspective_correct),
            bins.bg,
            rgb,
            alpha,
            depth,
            normal,
            g_rgb,
            g_alpha,
            g_depth,
            g_normal,
            pair_grad,
        )
    F = bins.faces.shape[0]
    V = bins.pos.shape[0]
    g_pos = np.zeros((V, 3), np.float32)
    g_rgbv = np.zeros((V, 3), np.float32)
    g_op = np.zeros(V, np.float32)
    n = min(F, BACKWARD_FACE_CHUNK)
    g_pos_f = np.empty((n, 3, 3), np.float32)
    g_rgb_f = np.empty((n, 3, 3), np.float32)
    g_op_f = np.empty((n, 3), np.float32)
    for f0 in range(0, F, BACKWARD_FACE_CHUNK):  # chunks keep the per-face-vertex buffers small
        m = min(F, f0 + BACKWARD_FACE_CHUNK) - f0
        with stage("rb_setup"):
            kn.setup_backward(
                bins.pos,
                bins.faces,
                bins.w2c,
                bins.K,
                bins.argmin,
                pair_grad,
                bins.pos_of,
                bins.face_start,
                f0,
                g_pos_f[:m],
                g_rgb_f[:m],
                g_op_f[:m],
            )
        with stage("rb_scatter"):
            kn.scatter_vertices(bins.faces, f0, g_pos_f[:m], g_rgb_f[:m], g_op_f[:m], g_pos, g_rgbv, g_op,
                                bins.face_start)
    return g_pos, g_rgbv, g_op


class _SoftRasterize(torch.autograd.Function):
    """rgb, alpha, depth, normal = f(positions, vertex colours, vertex opacities); the rest are constants."""

    @staticmethod
    def forward(ctx, positions, vertex_rgb, opacities, faces, sigma, w2c, K, width, height, background, opts, extra):
        with stage("render_forward"):
            images, max_weight, face_id, evals, visible, bins = forward_numba(
                positions, faces, vertex_rgb, opacities, sigma, w2c, K, width, height, background, opts
            )
        ctx.bins, ctx.sigma, ctx.size, ctx.opts = bins, sigma, (width, height), opts
        ctx.dtypes = (positions.dtype, vertex_rgb.dtype, opacities.dtype)
        extra.update(
            max_weight=torch.from_numpy(max_weight), face_id=torch.from_numpy(face_id), evals=evals, visible=visible
        )
        dt = positions.dtype
        return tuple(torch.from_numpy(x).to(dt) for x in images)

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_normal):
        w, h = ctx.size
        with stage("render_backward"):
            g_pos, g_col, g_op = backward_numba(
                ctx.bins, ctx.sigma, w, h, ctx.opts, _np32(g_rgb), _np32(g_alpha), _np32(g_depth), _np32(g_normal)
            )
        dp, dc, do = ctx.dtypes
        return (
            torch.from_numpy(g_pos).to(dp),
            torch.from_numpy(g_col).to(dc),
            torch.from_numpy(g_op).to(do),
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
        )


def render_numba(
    positions, faces, vertex_rgb, opacities, sigma, world_to_camera, K, width, height, background, opts: RenderOptions
) -> RenderOutput:
    """One view with the Numba kernels; same contract as trisplat.render.reference.render_reference."""
    extra: dict = {}
    rgb, alpha, depth, normal = _SoftRasterize.apply(
        positions, vertex_rgb, opacities, faces, sigma, world_to_camera, K, width, height, background, opts, extra
    )
    return RenderOutput(
        rgb=rgb,
        alpha=alpha,
        depth=depth,
        normal=normal,
        max_weight=extra["max_weight"].to(positions.dtype),
        face_id=extra["face_id"],
        pairs_evaluated=extra["evals"],
        faces_visible=extra["visible"],
    )
