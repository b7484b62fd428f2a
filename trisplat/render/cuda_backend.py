"""The CUDA backend (`backend="cuda"`): device binning, soft rendering wired into torch autograd, and the hard z-buffer
renderer, on a GPU with the numba-cuda kernels (the wiring only; kernels in cuda_kernels.py, maths in
kernel_math.py).

torch <-> numba without copies: every buffer is a torch tensor on the GPU, handed to the kernels through
__cuda_array_interface__ (a view), and the kernels run on torch's current stream, ordered with the torch work around
them. Binning sorts (tile, depth) keys with torch.sort on the device. Under numba's CUDA simulator
(NUMBA_ENABLE_CUDASIM=1, how CI tests the kernels without a GPU) the same code renders CPU tensors, through numpy
views, one Python thread per CUDA thread: slow, for tiny scenes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from trisplat.render.types import RenderOptions, RenderOutput, downsample, stack_views

INSTALL_HINT = ("backend='cuda' needs numba-cuda and an NVIDIA GPU with a CUDA build of torch: pip install "
                "'trisplat[gpu]' (numba-cuda); trisplat installs the CPU build of torch by default")


def _modules():
    """(numba.cuda, cuda_kernels), or ImportError with the install hint."""
    try:
        from numba import cuda
    except ImportError as exc:  # pragma: no cover - numba is a dependency; its CUDA target may be missing
        raise ImportError(INSTALL_HINT) from exc
    from trisplat.render import cuda_kernels

    return cuda, cuda_kernels


def simulated() -> bool:
    """Whether numba's CUDA target is its simulator (NUMBA_ENABLE_CUDASIM=1): kernels then run on CPU tensors."""
    import numba

    return bool(numba.config.ENABLE_CUDASIM)


def check_tile_size(tile: int) -> int:
    """tile if the CUDA kernels support it (tile^2 threads per block: whole warps, at most 1024), else ValueError."""
    from trisplat.render.cuda_kernels import TILE_SIZES

    if tile not in TILE_SIZES:
        raise ValueError(f"backend='cuda' needs tile_size in {TILE_SIZES} (one thread per pixel of a tile, whole "
                         f"warps), got {tile}")
    return tile


class _Launcher:
    """Launches kernels on the tensors' device: GPU tensors through __cuda_array_interface__ on torch's current
    stream, or, under the simulator, CPU tensors through numpy views."""

    def __init__(self, device: torch.device):
        self.cuda, self.kernels = _modules()
        self.device = torch.device(device)
        self.sim = simulated()
        if self.sim:
            if self.device.type != "cpu":
                raise ValueError(f"numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1) renders CPU tensors, got tensors "
                                 f"on {self.device}")
            self.stream = 0
        else:
            if self.device.type != "cuda":
                raise ValueError(f"backend='cuda' renders CUDA tensors, got tensors on {self.device} (move the scene "
                                 "with .to('cuda'), or use backend='numba' on the CPU)")
            self.stream = self.cuda.external_stream(torch.cuda.current_stream(self.device).cuda_stream)

    def arg(self, x):
        if not isinstance(x, torch.Tensor):
            return x
        if self.sim:
            return x.numpy()
        return self.cuda.as_cuda_array(x, sync=False)

    def __call__(self, kernel, grid, block, *args):
        if grid == 0 or (isinstance(grid, tuple) and 0 in grid):
            return
        args = [self.arg(a) for a in args]
        if self.sim:
            kernel[grid, block](*args)
        else:
            with self.cuda.gpus[self.device.index or 0]:
                kernel[grid, block, self.stream](*args)

    def per_face(self, kernel, n: int, *args):
        """One thread per face (or per any of n items)."""
        threads = self.kernels.FACE_THREADS
        self(kernel, (n + threads - 1) // threads, threads, *args)


def _f32(t: torch.Tensor, dev) -> torch.Tensor:
    return t.detach().to(device=dev, dtype=torch.float32).contiguous()


def bin_pairs(launch: _Launcher, rows, rect, ntiles, depth, tile: int, width: int, height: int, closed: bool):
    """Per-tile face lists on the device. Each (face, overlapped tile) pair gets the key tile << 32 | the bits of the
    face's (positive float32) depth, emitted in face order; a stable sort of the keys (torch.sort on the device)
    makes every tile's list contiguous and front to back, equal depths in face order (as the CPU kernels).
    Returns (tile_faces int32 [P], tile_start int32 [NT+1], tiles per row)."""
    dev = ntiles.device
    ntx, nty = (width + tile - 1) // tile, (height + tile - 1) // tile
    nt = ntx * nty
    offsets = torch.cumsum(ntiles, 0, dtype=torch.int64)
    P = int(offsets[-1]) if offsets.numel() else 0
    tile_start = torch.zeros(nt + 1, dtype=torch.int32, device=dev)
    if P == 0:
        return torch.zeros(0, dtype=torch.int32, device=dev), tile_start, ntx
    keys = torch.empty(P, dtype=torch.int64, device=dev)
    vals = torch.empty(P, dtype=torch.int32, device=dev)
    launch.per_face(launch.kernels.emit_pairs, ntiles.shape[0], rows, rect, ntiles, offsets, depth.view(torch.int32),
                    tile, ntx, closed, keys, vals)
    keys, perm = torch.sort(keys, stable=True)
    counts = torch.bincount(keys >> 32, minlength=nt)
    tile_start[1:] = torch.cumsum(counts, 0)
    return vals[perm].contiguous(), tile_start, ntx


@dataclass
class _Saved:
    """What the forward pass leaves for the backward pass (tensors on the render device)."""

    pos: torch.Tensor
    faces: torch.Tensor
    w2c: torch.Tensor
    K: torch.Tensor
    theta: torch.Tensor
    rect: torch.Tensor
    argmin: torch.Tensor
    ntiles: torch.Tensor
    tile_faces: torch.Tensor
    tile_start: torch.Tensor
    ntx: int
    images: tuple


def forward_cuda(positions, faces, vertex_rgb, opacities, sigma, world_to_camera, K, width, height, background,
                 opts: RenderOptions):
    """Setup, binning and the forward pixel kernel. Returns (rgb, alpha, depth, normal), max_weight [F], face_id,
    pairs evaluated, faces visible, saved state."""
    dev = positions.device
    launch = _Launcher(dev)
    kn = launch.kernels
    tile = check_tile_size(int(opts.tile_size))
    pos, rgbv, op, bg = (_f32(t, dev) for t in (positions, vertex_rgb, opacities, background))
    w2c = world_to_camera.detach().to(device=dev, dtype=torch.float64).contiguous()  # the setup is float64
    Km = K.detach().to(device=dev, dtype=torch.float64).contiguous()
    fc = faces.detach().to(device=dev, dtype=torch.int32).contiguous()
    F, W, H = fc.shape[0], int(width), int(height)
    z = lambda *s, dt=torch.float32: torch.zeros(*s, dtype=dt, device=dev)  # noqa: E731
    theta, rect, key = z(F, kn.N_THETA), z(F, 4, dt=torch.int32), z(F)
    argmin, ntiles = z(F, dt=torch.int32), z(F, dt=torch.int32)
    launch.per_face(kn.setup_faces, F, pos, fc, w2c, Km, rgbv, op, opts.opacity_mode == "min", float(opts.near),
                    float(opts.far), float(opts.min_area_px), float(opts.grazing_cos), W, H, tile, theta, rect, key,
                    argmin, ntiles)
    tile_faces, tile_start, ntx = bin_pairs(launch, theta, rect, ntiles, key, tile, W, H, False)
    rgb, alpha, depth, normal = z(H, W, 3), z(H, W), z(H, W), z(H, W, 3)
    face_id = torch.full((H, W), -1, dtype=torch.int64, device=dev)
    max_weight, evals = z(F), z(H, W, dt=torch.int32)
    launch(kn.raster_forward, tile_start.shape[0] - 1, tile * tile, theta, rect, tile_faces, tile_start, W, H, tile,
           ntx, float(sigma), float(opts.alpha_min), float(opts.alpha_max), float(opts.transmittance_min),
           bool(opts.perspective_correct), bg, rgb, alpha, depth, normal, face_id, max_weight, evals)
    images = (rgb, alpha, depth, normal)
    saved = _Saved(pos, fc, w2c, Km, theta, rect, argmin, ntiles, tile_faces, tile_start, ntx, images)
    return images, max_weight, face_id, int(evals.sum()), int((ntiles > 0).sum()), saved


def backward_cuda(s: _Saved, sigma, width, height, opts: RenderOptions, g_rgb, g_alpha, g_depth, g_normal):
    """Exact gradients w.r.t. vertex positions [V,3], vertex colours [V,3] and vertex opacities [V] (float32)."""
    dev = s.pos.device
    launch = _Launcher(dev)
    kn = launch.kernels
    F, V, tile = s.faces.shape[0], s.pos.shape[0], int(opts.tile_size)
    g_theta = torch.zeros(F, kn.N_THETA, dtype=torch.float32, device=dev)
    g_pos = torch.zeros(V, 3, dtype=torch.float32, device=dev)
    g_col = torch.zeros(V, 3, dtype=torch.float32, device=dev)
    g_op = torch.zeros(V, dtype=torch.float32, device=dev)
    rgb, alpha, depth, normal = s.images
    launch(kn.raster_backward, s.tile_start.shape[0] - 1, tile * tile, s.theta, s.rect, s.tile_faces, s.tile_start,
           int(width), int(height), tile, s.ntx, float(sigma), float(opts.alpha_min), float(opts.alpha_max),
           float(opts.transmittance_min), bool(opts.perspective_correct), rgb, alpha, depth, normal, g_rgb, g_alpha,
           g_depth, g_normal, g_theta)
    launch.per_face(kn.setup_backward, F, s.pos, s.faces, s.w2c, s.K, s.argmin, s.ntiles, g_theta, g_pos, g_col, g_op)
    return g_pos, g_col, g_op


def _grad(g, shape, dev):
    if g is None:
        return torch.zeros(shape, dtype=torch.float32, device=dev)
    return g.detach().to(device=dev, dtype=torch.float32).contiguous()


class _CudaRasterize(torch.autograd.Function):
    """rgb, alpha, depth, normal = f(positions, vertex colours, vertex opacities); the rest are constants."""

    @staticmethod
    def forward(ctx, positions, vertex_rgb, opacities, faces, sigma, w2c, K, width, height, background, opts, extra):
        images, max_weight, face_id, evals, visible, saved = forward_cuda(
            positions, faces, vertex_rgb, opacities, sigma, w2c, K, width, height, background, opts)
        ctx.saved, ctx.sigma, ctx.size, ctx.opts = saved, sigma, (width, height), opts
        ctx.dtypes = (positions.dtype, vertex_rgb.dtype, opacities.dtype)
        extra.update(max_weight=max_weight, face_id=face_id, evals=evals, visible=visible)
        return tuple(x.to(positions.dtype) for x in images)

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_normal):
        w, h = ctx.size
        dev = ctx.saved.pos.device
        g_pos, g_col, g_op = backward_cuda(ctx.saved, ctx.sigma, w, h, ctx.opts, _grad(g_rgb, (h, w, 3), dev),
                                           _grad(g_alpha, (h, w), dev), _grad(g_depth, (h, w), dev),
                                           _grad(g_normal, (h, w, 3), dev))
        dp, dc, do = ctx.dtypes
        return (g_pos.to(dp), g_col.to(dc), g_op.to(do)) + (None,) * 9


def render_cuda(positions, faces, vertex_rgb, opacities, sigma, world_to_camera, K, width, height, background,
                opts: RenderOptions) -> RenderOutput:
    """One view with the CUDA kernels on the tensors' GPU; same contract as reference.render_reference
    (pairs_evaluated counts, per pixel, the faces of its tile's list whose pixel box holds it while it is not yet
    opaque)."""
    extra: dict = {}
    rgb, alpha, depth, normal = _CudaRasterize.apply(
        positions, vertex_rgb, opacities, faces, sigma, world_to_camera, K, width, height, background, opts, extra)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, normal=normal,
                        max_weight=extra["max_weight"].to(positions.dtype), face_id=extra["face_id"],
                        pairs_evaluated=extra["evals"], faces_visible=extra["visible"])


HARD_TILE = 16  # tile edge (pixels) of the CUDA z-buffer


def hard_view_cuda(positions, faces, colors, world_to_camera, K, width, height, background, near: float,
                   perspective_correct: bool) -> RenderOutput:
    """One opaque z-buffer view with the CUDA kernels (no gradients); colors [V,3] RGB (SH already evaluated).
    Same outputs as hard.rasterize_hard for one view at one sample per pixel."""
    dev = positions.device
    launch = _Launcher(dev)
    kn = launch.kernels
    pos, col, bg = (_f32(t, dev) for t in (positions, colors, background))
    w2c = world_to_camera.detach().to(device=dev, dtype=torch.float64).contiguous()
    Km = K.detach().to(device=dev, dtype=torch.float64).contiguous()
    fc = faces.detach().to(device=dev, dtype=torch.int32).contiguous()
    F, W, H, tile = fc.shape[0], int(width), int(height), HARD_TILE
    z = lambda *s, dt=torch.float32: torch.zeros(*s, dtype=dt, device=dev)  # noqa: E731
    uvz, box, znear = z(F, 9), z(F, 4, dt=torch.int32), z(F)
    rows, rect, zkey, ntiles = z(F, kn.N_HARD), z(F, 4, dt=torch.int32), z(F), z(F, dt=torch.int32)
    launch.per_face(kn.hard_setup, F, pos, fc, w2c, Km, float(near), W, H, tile, uvz, box, znear, rows, rect, zkey,
                    ntiles)
    tile_faces, tile_start, ntx = bin_pairs(launch, rows, rect, ntiles, zkey, tile, W, H, True)
    fid = torch.full((H, W), -1, dtype=torch.int32, device=dev)
    evals = z(H, W, dt=torch.int32)
    launch(kn.hard_pixels, tile_start.shape[0] - 1, tile * tile, rows, rect, znear, tile_faces, tile_start, W, H, tile,
           ntx, fid, evals)
    rgb, depth, normal = z(H, W, 3), z(H, W), z(H, W, 3)
    face_id, won = z(H, W, dt=torch.int64), z(F)
    launch(kn.hard_resolve, (math.ceil(H / 16), math.ceil(W / 16)), (16, 16), uvz, pos, fc, w2c, col, fid,
           bool(perspective_correct), bg, rgb, depth, normal, face_id, won)
    dt = positions.dtype
    return RenderOutput(rgb=rgb.to(dt), alpha=(face_id >= 0).to(dt), depth=depth.to(dt), normal=normal.to(dt),
                        max_weight=won.to(dt), face_id=face_id, pairs_evaluated=int(evals.sum()),
                        faces_visible=int((ntiles > 0).sum()))


def rasterize_hard_cuda(vi, near: float, perspective_correct: bool, ss: int) -> RenderOutput:
    """rasterize_hard(..., backend='cuda') on validated inputs (render.inputs.ViewInputs): every view, SH evaluated
    per view (torch, on the device), supersampled by ss and box-filtered like the Numba path."""
    from trisplat.render.rasterize import camera_center
    from trisplat.scene.sh import eval_sh

    outs = []
    with torch.no_grad():
        for b in range(vi.world_to_camera.shape[0]):
            w2c, Kb = vi.world_to_camera[b], vi.K[b]
            col = vi.colors
            if col.ndim == 3:
                col = eval_sh(col, vi.positions - camera_center(w2c))
            Kb = torch.cat([Kb[:2] * ss, Kb[2:]])
            out = hard_view_cuda(vi.positions, vi.faces, col, w2c, Kb, vi.width * ss, vi.height * ss, vi.background,
                                 near, perspective_correct)
            outs.append(downsample(out, ss))
    return outs[0] if not vi.batched else stack_views(outs)
