"""Validation and normalisation of rasterize() inputs: shapes, dtypes, finiteness, index ranges, image sizes."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from trisplat.render.types import RenderOptions

MAX_IMAGE_SIDE_PX = 16384  # larger images are refused as absurd (pixels per side)
SUPERSAMPLE_FACTORS = (1, 2, 3, 4)
BACKENDS = ("numba", "reference", "cuda")
OPACITY_MODES = ("min", "mean")


def check_supersample(s, name: str = "supersample") -> int:
    """s if it is a supported supersampling factor (samples per pixel side), else ValueError naming `name`."""
    if s not in SUPERSAMPLE_FACTORS:
        raise ValueError(f"{name} must be one of {SUPERSAMPLE_FACTORS}, got {s!r}")
    return s


def scan(t: torch.Tensor, bounds: bool = True) -> tuple[int, float, float]:
    """Non-finite count, min and max of a tensor's values (vectorised numpy reductions, no big temporaries; on a GPU,
    torch reductions there and one small copy back, not the tensor).

    Finiteness is read off a sum in the array's own dtype (one fast vectorised pass; NaN or Inf in the input always
    makes it non-finite); only a non-finite sum, which finite but huge values can also give, is re-checked element
    by element, and the count is made only on failure."""
    if t.device.type != "cpu":
        return _scan_on_device(t.detach().reshape(-1), bounds)
    a = t.detach().cpu().reshape(-1).numpy()
    if a.size == 0:
        return 0, 0.0, 0.0
    bad = 0
    if a.dtype.kind == "f":
        with np.errstate(over="ignore", invalid="ignore"):
            total = np.add.reduce(a)
        if not np.isfinite(total) and not np.isfinite(a).all():
            bad = int(a.size - np.count_nonzero(np.isfinite(a)))
    if not bounds:
        return bad, 0.0, 0.0
    if bad:
        f = a[np.isfinite(a)]
        return bad, float(f.min()) if f.size else 0.0, float(f.max()) if f.size else 0.0
    return 0, float(a.min()), float(a.max())


def _scan_on_device(x: torch.Tensor, bounds: bool) -> tuple[int, float, float]:
    """scan() of a flat tensor on its own device: the reductions there, their three numbers copied back at once."""
    if x.numel() == 0:
        return 0, 0.0, 0.0
    ok = torch.isfinite(x) if x.is_floating_point() else None
    bad = (x.numel() - ok.sum()) if ok is not None else torch.zeros((), dtype=torch.int64, device=x.device)
    if not bounds:
        return int(bad), 0.0, 0.0
    f = x.double()
    if ok is not None:
        lo = torch.where(ok, f, torch.full_like(f, float("inf"))).amin()
        hi = torch.where(ok, f, torch.full_like(f, float("-inf"))).amax()
    else:
        lo, hi = f.amin(), f.amax()
    n, lo, hi = torch.stack([bad.double(), lo, hi]).tolist()
    if n and not np.isfinite(lo):  # nothing finite
        lo = hi = 0.0
    return int(n), lo, hi


@dataclass
class ViewInputs:
    """Validated tensors for one call: positions [V,3] float, faces int32 or int64 [F,3], colors [V,3] or [V,K,3],
    opacities [V], world_to_camera [B,4,4], K [B,3,3] (same dtype as positions), background [3]; batched tells
    whether the caller passed a leading B axis."""

    positions: torch.Tensor
    faces: torch.Tensor
    colors: torch.Tensor
    opacities: torch.Tensor
    world_to_camera: torch.Tensor
    K: torch.Tensor
    background: torch.Tensor
    sigma: float
    width: int
    height: int
    batched: bool


def _as_tensor(x, name: str, device=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x if device is None else x.to(device)
    if isinstance(x, np.ndarray) or isinstance(x, (list, tuple, float, int)):
        return torch.as_tensor(np.asarray(x), device=device)
    raise ValueError(f"{name} must be a torch tensor or numpy array, got {type(x).__name__}")


def make_options(options: dict) -> RenderOptions:
    """RenderOptions from keyword options, with precise errors for unknown names and bad values."""
    known = {f.name for f in fields(RenderOptions)}
    unknown = sorted(set(options) - known)
    if unknown:
        raise ValueError(f"unknown rasterize option(s) {unknown}; known options: {sorted(known)}")
    opts = RenderOptions(**options)
    if opts.backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {opts.backend!r}")
    if opts.opacity_mode not in OPACITY_MODES:
        raise ValueError(f"opacity_mode must be one of {OPACITY_MODES}, got {opts.opacity_mode!r}")
    check_supersample(opts.supersample)
    if not (isinstance(opts.tile_size, int) and 4 <= opts.tile_size <= 64):
        raise ValueError(f"tile_size must be an int in 4..64 pixels, got {opts.tile_size!r}")
    if not (0 < opts.near < opts.far):
        raise ValueError(f"need 0 < near < far, got near={opts.near}, far={opts.far}")
    if not (0 < opts.alpha_max <= 1 and 0 <= opts.alpha_min < opts.alpha_max and 0 <= opts.transmittance_min < 1):
        raise ValueError(
            f"bad alpha thresholds: alpha_max={opts.alpha_max}, alpha_min={opts.alpha_min}, "
            f"transmittance_min={opts.transmittance_min}"
        )
    return opts


def check_image_size(width, height) -> tuple[int, int]:
    if (
        isinstance(width, bool)
        or isinstance(height, bool)
        or not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer)))
    ):
        raise ValueError(f"width and height must be ints, got {width!r} x {height!r}")
    if not (1 <= width <= MAX_IMAGE_SIDE_PX and 1 <= height <= MAX_IMAGE_SIDE_PX):
        raise ValueError(
            f"image size {width}x{height} is empty or absurd (each side must be in 1..{MAX_IMAGE_SIDE_PX})"
        )
    return int(width), int(height)


def check_camera(world_to_camera, K, dtype, device) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """[B,4,4] and [B,3,3] tensors of `dtype`; a [3,3] K is shared by a batch of poses."""
    w2c = _as_tensor(world_to_camera, "world_to_camera").to(device=device, dtype=dtype)
    Kt = _as_tensor(K, "K").to(device=device, dtype=dtype)
    batched = w2c.ndim == 3
    if w2c.shape[-2:] != (4, 4) or w2c.ndim not in (2, 3):
        raise ValueError(f"world_to_camera must be [4,4] or [B,4,4], got {tuple(w2c.shape)}")
    if Kt.shape[-2:] != (3, 3) or Kt.ndim not in (2, 3):
        raise ValueError(f"K must be [3,3] or [B,3,3], got {tuple(Kt.shape)}")
    w2c = w2c if batched else w2c[None]
    if Kt.ndim == 2:
        Kt = Kt[None].expand(w2c.shape[0], 3, 3)
    elif Kt.shape[0] != w2c.shape[0]:
        raise ValueError(f"K batch {Kt.shape[0]} does not match world_to_camera batch {w2c.shape[0]}")
    if not (torch.isfinite(w2c).all() and torch.isfinite(Kt).all()):
        raise ValueError("world_to_camera or K holds NaN or Inf")
    third = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device)
    if not torch.allclose(Kt[:, 2, :], third.expand_as(Kt[:, 2, :])):
        raise ValueError(f"K must be a pinhole matrix with last row [0, 0, 1], got {Kt[:, 2, :].tolist()}")
    if (Kt[:, 0, 0] == 0).any() or (Kt[:, 1, 1] == 0).any():
        raise ValueError("K has a zero focal length")
    return w2c, Kt, batched


def validate(positions, faces, colors, opacities, sigma, world_to_camera, K, width, height, background,
             check_values: bool = True) -> ViewInputs:
    """Check everything rasterize() receives; errors name the argument and what was expected (opacities None: unused,
    ones). check_values False: shapes and dtypes only, no scan of the values (RenderOptions.check_values)."""
    pos = _as_tensor(positions, "positions")
    if not pos.is_floating_point():
        raise ValueError(f"positions must be a float tensor, got dtype {pos.dtype}")
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must be [V,3], got {tuple(pos.shape)}")
    bad = scan(pos, bounds=False)[0] if check_values else 0
    if bad:
        raise ValueError(f"positions hold {bad} NaN or Inf values ({pos.shape[0]} vertices)")
    V, dev, dtype = pos.shape[0], pos.device, pos.dtype
    fc = _as_tensor(faces, "faces", dev)
    if fc.dtype.is_floating_point or fc.dtype == torch.bool or fc.is_complex():
        raise ValueError(f"faces must be an integer tensor (int32 [F,3]), got dtype {fc.dtype}")
    if fc.ndim != 2 or fc.shape[1] != 3:
        raise ValueError(f"faces must be [F,3], got {tuple(fc.shape)}")
    if fc.dtype not in (torch.int32, torch.int64):
        fc = fc.long()
    _, lo, hi = scan(fc) if check_values else (0, 0, 0)
    if fc.numel() and (lo < 0 or hi >= V):
        raise ValueError(f"face indices must lie in [0, {V - 1}] (V={V}), got range [{int(lo)}, {int(hi)}]")
    col = _as_tensor(colors, "colors", dev)
    if not col.is_floating_point():
        raise ValueError(f"colors must be a float tensor, got dtype {col.dtype}")
    if not (
        (col.ndim == 2 and col.shape == (V, 3))
        or (col.ndim == 3 and col.shape[0] == V and col.shape[2] == 3 and col.shape[1] in (1, 4, 9, 16))
    ):
        raise ValueError(f"colors must be [V,3] RGB or [V,(d+1)^2,3] SH with V={V}, got {tuple(col.shape)}")
    if check_values and scan(col, bounds=False)[0]:
        raise ValueError("colors hold NaN or Inf")
    if opacities is None:  # callers that use no opacities (hard mode): ones, as a zero-stride view (nothing to scan)
        op = torch.ones(1, dtype=dtype, device=dev).expand(V)
    else:
        op = _as_tensor(opacities, "opacities", dev)
        if not op.is_floating_point() or op.shape != (V,):
            raise ValueError(f"opacities must be a float [V] tensor with V={V}, got {tuple(op.shape)} {op.dtype}")
        bad, lo, hi = scan(op) if check_values else (0, 0.0, 1.0)
        if bad or op.numel() and (lo < 0 or hi > 1):
            raise ValueError("opacities must lie in [0, 1] (already through the sigmoid)")
    if isinstance(sigma, torch.Tensor):
        sigma = float(sigma.detach())
    if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not np.isfinite(sigma) or sigma <= 0:
        raise ValueError(f"sigma must be a finite float > 0, got {sigma!r}")
    width, height = check_image_size(width, height)
    w2c, Kt, batched = check_camera(world_to_camera, K, dtype, dev)
    if background is None:
        bg = torch.zeros(3, dtype=dtype, device=dev)
    else:
        bg = _as_tensor(background, "background", dev).to(dtype)
        if bg.shape != (3,) or not torch.isfinite(bg).all():
            raise ValueError(f"background must be a finite [3] colour, got shape {tuple(bg.shape)}")
    return ViewInputs(pos, fc, col.to(dtype), op.to(dtype), w2c, Kt, bg, float(sigma), width, height, batched)
