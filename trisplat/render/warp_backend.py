"""The Warp backend (`backend="warp"`): device binning, soft rendering wired into torch autograd, and the hard
z-buffer renderer, on the tensors' own device (CUDA, or Warp's CPU device for CPU tensors). The wiring only; the
maths is in warp_kernels.py.

torch <-> Warp without copies: every buffer is a torch tensor on the input's device, handed to the kernels through
wp.from_torch (a view). Kernels run on torch's current CUDA stream, so they are ordered with the surrounding torch
work. Vertex data in float64 is converted to float32 once (the kernels store float32, like the Numba ones).
"""
from __future__ import annotations

import math
from contextlib import contextmanager

import torch

from trisplat.render.types import RenderOptions, RenderOutput, stack_views

INSTALL_HINT = "backend='warp' needs NVIDIA Warp: pip install 'trisplat[gpu]' (or pip install warp-lang)"


def _modules():
    """(warp, warp_kernels), or ImportError with the install hint."""
    try:
        import warp as wp
    except ImportError as exc:
        raise ImportError(INSTALL_HINT) from exc
    from trisplat.render import warp_kernels as wk

    wp.init()  # idempotent; device lookups need an initialised runtime
    return wp, wk


def _warp():
    """warp, initialised, or ImportError with the install hint (without loading the rasterizer's kernels)."""
    try:
        import warp as wp
    except ImportError as exc:
        raise ImportError(INSTALL_HINT) from exc
    wp.init()
    return wp


@contextmanager
def warp_scope(device: torch.device):
    """Warp (initialised; ImportError with the install hint without it) with its device set to the torch device's
    and, for CUDA tensors, its launches on torch's current stream: the context of every Warp launch in trisplat."""
    wp = _warp()
    with _scope(wp, torch.device(device)):
        yield wp


def available() -> bool:
    """Whether the Warp backend can be imported here (warp-lang installed)."""
    try:
        _modules()
    except ImportError:
        return False
    return True


def cuda_available() -> bool:
    """Whether Warp sees a CUDA device (False without warp-lang)."""
    try:
        wp, _ = _modules()
    except ImportError:
        return False
    return bool(wp.is_cuda_available())


@contextmanager
def _scope(wp, device: torch.device):
    """Warp's device for a torch device, with Warp's launches on torch's current stream for CUDA tensors."""
    wdev = wp.device_from_torch(device)
    with wp.ScopedDevice(wdev):
        if wdev.is_cuda:
            with wp.ScopedStream(wp.stream_from_torch(device)):
                yield wdev
        else:
            yield wdev


def _f32(t: torch.Tensor, device) -> torch.Tensor:
    return t.detach().to(device=device, dtype=torch.float32).contiguous()


def _bits(n: int) -> int:
    return max(1, int(math.ceil(math.log2(n + 1))))


def bin_faces(wp, wk, rows, rect, ntiles, depth, tile: int, width: int, height: int, closed: bool):
    """Per-tile face lists from a device sort. Faces are ranked by `depth` (a stable radix sort: equal depths keep
    the face order), each (face, overlapped tile) pair gets the key tile << 32 | rank, and the pairs are radix-sorted
    by key, so each tile's list is contiguous and front to back. Returns (sorted face ids [P] int32, tile_start [NT],
    tile_end [NT], tiles per row)."""
    dev = ntiles.device
    F = ntiles.shape[0]
    ntx, nty = (width + tile - 1) // tile, (height + tile - 1) // tile
    nt = ntx * nty
    dkey = torch.zeros(2 * F, dtype=torch.float32, device=dev)
    dkey[:F] = depth
    order = torch.zeros(2 * F, dtype=torch.int32, device=dev)
    order[:F] = torch.arange(F, dtype=torch.int32, device=dev)
    wp.utils.radix_sort_pairs(wp.from_torch(dkey), wp.from_torch(order), F)
    rank = torch.empty(F, dtype=torch.int32, device=dev)
    wp.launch(wk.invert_order, dim=F, inputs=[wp.from_torch(order[:F]), wp.from_torch(rank)])
    offsets = torch.empty(F, dtype=torch.int32, device=dev)
    wp.utils.array_scan(wp.from_torch(ntiles), wp.from_torch(offsets), inclusive=True)
    P = int(offsets[-1].item())
    tile_start = torch.zeros(nt, dtype=torch.int32, device=dev)
    tile_end = torch.zeros(nt, dtype=torch.int32, device=dev)
    if P == 0:
        return torch.zeros(0, dtype=torch.int32, device=dev), tile_start, tile_end, ntx
    keys = torch.empty(2 * P, dtype=torch.int64, device=dev)
    vals = torch.empty(2 * P, dtype=torch.int32, device=dev)
    wkeys, wvals = wp.from_torch(keys), wp.from_torch(vals)
    wp.launch(wk.emit_pairs, dim=F, inputs=[wp.from_torch(rows), wp.from_torch(rect), wp.from_torch(ntiles),
                                            wp.from_torch(offsets), wp.from_torch(rank), tile, ntx, int(closed),
                                            wkeys, wvals])
    wp.utils.radix_sort_pairs(wkeys, wvals, P, 0, 32 + _bits(nt))
    wp.launch(wk.tile_ranges, dim=P, inputs=[wkeys, P, wp.from_torch(tile_start), wp.from_torch(tile_end)])
    return vals[:P], tile_start, tile_end, ntx


class _Saved:
    """What the forward pass leaves for the backward pass (tensors on the render device)."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


def forward_warp(positions, faces, vertex_rgb, opacities, sigma, world_to_camera, K, width, height, background,
                 opts: RenderOptions):
    """Setup, binning and the forward pixel kernel. Returns (rgb, alpha, depth, normal), max_weight [F], face_id,
    pairs evaluated, faces visible, saved state."""
    wp, wk = _modules()
    dev = positions.device
    pos, rgbv, op, bg = (_f32(t, dev) for t in (positions, vertex_rgb, opacities, background))
    w2c = world_to_camera.detach().to(device=dev, dtype=torch.float64).contiguous()  # the setup is float64
    Km = K.detach().to(device=dev, dtype=torch.float64).contiguous()
    fc = faces.detach().to(device=dev, dtype=torch.int32).contiguous()
    F, W, H, tile = fc.shape[0], int(width), int(height), int(opts.tile_size)
    z = lambda *s, dt=torch.float32: torch.zeros(*s, dtype=dt, device=dev)  # noqa: E731
    theta, rect, depth_key = z(F, wk.N_THETA), z(F, 4, dt=torch.int32), z(F)
    argmin, ntiles = z(F, dt=torch.int32), z(F, dt=torch.int32)
    rgb, alpha, depth, normal = z(H, W, 3), z(H, W), z(H, W), z(H, W, 3)
    face_id = torch.full((H, W), -1, dtype=torch.int64, device=dev)
    max_weight, t_final = z(F), torch.ones(H, W, dtype=torch.float32, device=dev)
    last, evals = z(H, W, dt=torch.int32), z(H, W, dt=torch.int32)
    A = wp.from_torch
    with _scope(wp, dev):
        if F:
            wp.launch(wk.setup_faces, dim=F, inputs=[
                A(pos), A(fc), A(w2c), A(Km), A(rgbv), A(op), int(opts.opacity_mode == "min"), float(opts.near),
                float(opts.far), float(opts.min_area_px), float(opts.grazing_cos), W, H, tile, A(theta), A(rect),
                A(depth_key), A(argmin), A(ntiles)])
            vals, tile_start, tile_end, ntx = bin_faces(wp, wk, theta, rect, ntiles, depth_key, tile, W, H, False)
        else:
            ntx = (W + tile - 1) // tile
            vals = z(0, dt=torch.int32)
            tile_start = tile_end = z(ntx * ((H + tile - 1) // tile), dt=torch.int32)
        nt = tile_start.shape[0]
        wp.launch(wk.raster_forward, dim=nt * tile * tile, inputs=[
            A(theta), A(rect), A(vals), A(tile_start), A(tile_end), W, H, tile, ntx, float(sigma),
            float(opts.alpha_min), float(opts.alpha_max), float(opts.transmittance_min),
            int(bool(opts.perspective_correct)), A(bg), A(rgb), A(alpha), A(depth), A(normal), A(face_id),
            A(max_weight), A(t_final), A(last), A(evals)])
    saved = _Saved(pos=pos, faces=fc, w2c=w2c, K=Km, theta=theta, rect=rect, argmin=argmin, ntiles=ntiles, vals=vals,
                   tile_start=tile_start, ntx=ntx, bg=bg, t_final=t_final, last=last)
    return ((rgb, alpha, depth, normal), max_weight, face_id, int(evals.sum().item()),
            int((ntiles > 0).sum().item()), saved)


def backward_warp(s: _Saved, sigma, width, height, opts: RenderOptions, g_rgb, g_alpha, g_depth, g_normal):
    """Exact gradients w.r.t. vertex positions [V,3], vertex colours [V,3] and vertex opacities [V] (float32)."""
    wp, wk = _modules()
    dev = s.pos.device
    F, V, tile = s.faces.shape[0], s.pos.shape[0], int(opts.tile_size)
    g_theta = torch.zeros(F, wk.N_THETA, dtype=torch.float32, device=dev)
    g_pos = torch.zeros(V, 3, dtype=torch.float32, device=dev)
    g_col = torch.zeros(V, 3, dtype=torch.float32, device=dev)
    g_op = torch.zeros(V, dtype=torch.float32, device=dev)
    if F == 0:
        return g_pos, g_col, g_op
    A = wp.from_torch
    nt = s.tile_start.shape[0]
    with _scope(wp, dev):
        wp.launch(wk.raster_backward, dim=nt * tile * tile, inputs=[
            A(s.theta), A(s.rect), A(s.vals), A(s.tile_start), int(width), int(height), tile, s.ntx, float(sigma),
            float(opts.alpha_min), float(opts.alpha_max), int(bool(opts.perspective_correct)), A(s.bg),
            A(s.t_final), A(s.last), A(g_rgb), A(g_alpha), A(g_depth), A(g_normal), A(g_theta)])
        wp.launch(wk.setup_backward, dim=F, inputs=[A(s.pos), A(s.faces), A(s.w2c), A(s.K), A(s.argmin),
                                                    A(s.ntiles), A(g_theta), A(g_pos), A(g_col), A(g_op)])
    return g_pos, g_col, g_op


def _grad(g, shape, dev):
    if g is None:
        return torch.zeros(shape, dtype=torch.float32, device=dev)
    return g.detach().to(device=dev, dtype=torch.float32).contiguous()


class _WarpRasterize(torch.autograd.Function):
    """rgb, alpha, depth, normal = f(positions, vertex colours, vertex opacities); the rest are constants."""

    @staticmethod
    def forward(ctx, positions, vertex_rgb, opacities, faces, sigma, w2c, K, width, height, background, opts, extra):
        images, max_weight, face_id, evals, visible, saved = forward_warp(
            positions, faces, vertex_rgb, opacities, sigma, w2c, K, width, height, background, opts)
        ctx.saved, ctx.sigma, ctx.size, ctx.opts = saved, sigma, (width, height), opts
        ctx.dtypes = (positions.dtype, vertex_rgb.dtype, opacities.dtype)
        extra.update(max_weight=max_weight, face_id=face_id, evals=evals, visible=visible)
        return tuple(x.to(positions.dtype) for x in images)

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_normal):
        w, h = ctx.size
        dev = ctx.saved.pos.device
        g_pos, g_col, g_op = backward_warp(ctx.saved, ctx.sigma, w, h, ctx.opts, _grad(g_rgb, (h, w, 3), dev),
                                           _grad(g_alpha, (h, w), dev), _grad(g_depth, (h, w), dev),
                                           _grad(g_normal, (h, w, 3), dev))
        dp, dc, do = ctx.dtypes
        return (g_pos.to(dp), g_col.to(dc), g_op.to(do)) + (None,) * 9


def render_warp(positions, faces, vertex_rgb, opacities, sigma, world_to_camera, K, width, height, background,
                opts: RenderOptions) -> RenderOutput:
    """One view with the Warp kernels on the tensors' device; same contract as reference.render_reference
    (pairs_evaluated counts the (pixel, face) pairs whose pixel lies in the face's pixel box in its tile's list)."""
    extra: dict = {}
    rgb, alpha, depth, normal = _WarpRasterize.apply(
        positions, vertex_rgb, opacities, faces, sigma, world_to_camera, K, width, height, background, opts, extra)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, normal=normal,
                        max_weight=extra["max_weight"].to(positions.dtype), face_id=extra["face_id"],
                        pairs_evaluated=extra["evals"], faces_visible=extra["visible"])


def hard_view_warp(positions, faces, colors, world_to_camera, K, width, height, background, near: float,
                   perspective_correct: bool, tile: int = 16) -> RenderOutput:
    """One opaque z-buffer view with the Warp kernels (no gradients); colors [V,3] RGB (SH already evaluated).
    Same outputs as hard.rasterize_hard for one view at one sample per pixel."""
    wp, wk = _modules()
    dev = positions.device
    pos, col, bg = (_f32(t, dev) for t in (positions, colors, background))
    w2c, Km = _f32(world_to_camera, dev), _f32(K, dev)
    fc = faces.detach().to(device=dev, dtype=torch.int32).contiguous()
    F, W, H = fc.shape[0], int(width), int(height)
    z = lambda *s, dt=torch.float32: torch.zeros(*s, dtype=dt, device=dev)  # noqa: E731
    hth, rect, znear, ntiles = z(F, 12), z(F, 4, dt=torch.int32), z(F), z(F, dt=torch.int32)
    fid, evals = torch.full((H, W), -1, dtype=torch.int32, device=dev), z(H, W, dt=torch.int32)
    rgb, depth, normal = z(H, W, 3), z(H, W), z(H, W, 3)
    face_id, won = z(H, W, dt=torch.int64), z(F)
    A = wp.from_torch
    with _scope(wp, dev):
        if F:
            wp.launch(wk.hard_setup, dim=F, inputs=[A(pos), A(fc), A(w2c), A(Km), float(near), W, H, tile, A(hth),
                                                    A(rect), A(znear), A(ntiles)])
            vals, tile_start, tile_end, ntx = bin_faces(wp, wk, hth, rect, ntiles, znear, tile, W, H, True)
            wp.launch(wk.hard_pixels, dim=tile_start.shape[0] * tile * tile, inputs=[
                A(hth), A(rect), A(vals), A(tile_start), A(tile_end), A(znear), W, H, tile, ntx, A(fid), A(evals)])
        wp.launch(wk.hard_resolve, dim=(H, W), inputs=[A(pos), A(fc), A(w2c), A(Km), A(col), A(fid),
                                                        int(bool(perspective_correct)), A(bg), A(rgb), A(depth),
                                                        A(normal), A(face_id), A(won)])
    dt = positions.dtype
    return RenderOutput(rgb=rgb.to(dt), alpha=(face_id >= 0).to(dt), depth=depth.to(dt), normal=normal.to(dt),
                        max_weight=won.to(dt), face_id=face_id, pairs_evaluated=int(evals.sum().item()),
                        faces_visible=int((ntiles > 0).sum().item()))


def rasterize_hard_warp(vi, near: float, perspective_correct: bool, ss: int) -> RenderOutput:
    """rasterize_hard(..., backend='warp') on validated inputs (render.inputs.ViewInputs): every view, SH evaluated
    per view, supersampled by ss and box-filtered like the Numba path."""
    from trisplat.render.types import downsample
    from trisplat.scene.warp_sh import eval_sh_warp

    outs = []
    with torch.no_grad():
        for b in range(vi.world_to_camera.shape[0]):
            w2c, Kb = vi.world_to_camera[b], vi.K[b]
            col = vi.colors
            if col.ndim == 3:
                R, t = w2c[:3, :3], w2c[:3, 3]
                col = eval_sh_warp(col, vi.positions - (-(R.T @ t)))
            Kb = torch.cat([Kb[:2] * ss, Kb[2:]])
            out = hard_view_warp(vi.positions, vi.faces, col, w2c, Kb, vi.width * ss, vi.height * ss, vi.background,
                                 near, perspective_correct)
            outs.append(downsample(out, ss))
    if not vi.batched:
        return outs[0]
    return stack_views(outs)


DEVICE_CHOICES = ("auto", "cpu", "cuda")


def resolve_device(name: str) -> torch.device:
    """A --device choice as a torch device. 'cpu'; 'cuda' (rendering there is the Warp backend: ValueError when
    torch sees no CUDA device, since tensors are shared with Warp without copies and need a CUDA build of torch, or
    when warp-lang is missing); 'auto': cuda when both are there, else cpu."""
    if name not in DEVICE_CHOICES:
        raise ValueError(f"device must be one of {DEVICE_CHOICES}, got {name!r}")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() and available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' asked for, but torch sees no CUDA device (a CUDA build of torch and an NVIDIA "
                         "GPU are needed; trisplat installs CPU torch by default)")
    if name == "cuda" and not available():
        raise ValueError(f"device 'cuda' renders with the Warp backend: {INSTALL_HINT}")
    return torch.device(name)


def backend_for(device: torch.device) -> str:
    """The renderer backend for tensors on `device`: warp on CUDA, numba (the parallel CPU kernels) on the CPU."""
    return "warp" if torch.device(device).type == "cuda" else "numba"


def device_name(device: torch.device) -> str:
    """What a device is, in words, for benchmark notes ('cpu', or the GPU's name)."""
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    return str(device)
