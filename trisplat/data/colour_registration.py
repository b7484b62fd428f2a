"""Colour-to-depth registration of an RGB-D stream whose two cameras were never registered to each other.

Some captures ship colour and depth images of the same size that do not line up: 7-Scenes' Kinect v1 frames have the
depth camera's intrinsics (f = 585 px) but colour from the RGB camera, whose focal length is about 525 px, so a colour
pixel 200 px from the centre sits about 20 px from the depth pixel of the same number. Mapping a depth pixel's 3D
point to that colour misplaces every colour of the map radially, differently in every frame, and no pose or map fits
the frames together.

Both cameras of a depth sensor sit a few centimetres apart and look the same way, so at the depths they work at the
colour camera's image is the depth camera's scaled about the principal point and shifted:

    p_colour = s (p_depth - c) + c + t        (pixel coordinates, centres at +0.5; c = K's principal point)

`estimate_colour_registration` finds s and t without poses: depth discontinuities are object outlines, so the colour
gradient, sampled where the depth jumps, is largest at the right (s, t) (a coarse grid, then Nelder-Mead). It is
applied only when it beats the identity clearly, so a registered capture (TUM, ETH3D, synthetic) is left alone.
`register_colour` resamples a colour image into the depth camera's pixels (separable linear interpolation), after
which the stream's one K holds for both."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# a depth jump between 4-neighbours larger than this fraction of the nearer depth is an object outline
EDGE_JUMP = 0.05
# the search range: colour-to-depth focal ratio and shift (fraction of the image width)
SCALE_RANGE = (0.80, 1.25)
SHIFT_RANGE = 0.03
# applied only if the colour gradient on the depth outlines is at least this much higher than unregistered, and the
# registration moves some pixel of the image by at least MIN_MOVE_PX (a sub-pixel match is noise, not a fault)
MIN_GAIN = 1.10
MIN_MOVE_PX = 2.0
POINTS_PER_FRAME = 3000
ESTIMATE_FRAMES = 12


@dataclass(frozen=True)
class ColourRegistration:
    """p_colour = scale * (p_depth - c) + c + shift, in the stream's full-resolution pixels (centres at +0.5).

    applied: False when the estimate did not beat the identity (the colour is read as it is).
    gain: mean colour gradient on the depth outlines at the estimate, over the same without registration.
    """

    scale: float = 1.0
    shift: tuple[float, float] = (0.0, 0.0)
    applied: bool = False
    gain: float = 1.0
    frames: int = 0
    edge_points: int = 0
    reason: str = ""

    def describe(self, K: np.ndarray) -> str:
        fx = float(K[0, 0])
        if not self.applied:
            return f"colour and depth line up (colour read as it is{': ' + self.reason if self.reason else ''})"
        return (f"colour and depth are not registered: the colour camera's focal length is {self.scale:.3f}x the "
                f"depth's ({self.scale * fx:.0f} px against {fx:.0f}), shifted by ({self.shift[0]:+.1f}, "
                f"{self.shift[1]:+.1f}) px; the outlines' colour gradient is {self.gain:.2f}x higher registered "
                f"({self.frames} frames, {self.edge_points} outline points); colour is resampled to the depth camera")

    def as_option(self) -> str:
        """The --colour-registration value that gives this registration exactly: 'SCALE,DX,DY' or 'off'."""
        return f"{self.scale!r},{self.shift[0]!r},{self.shift[1]!r}" if self.applied else "off"

    def as_dict(self) -> dict:
        return {"scale": self.scale, "shift_px": list(self.shift), "applied": self.applied, "gain": self.gain,
                "frames": self.frames, "edge_points": self.edge_points, "reason": self.reason}


IDENTITY = ColourRegistration(reason="not estimated")


def parse_registration(text: str) -> ColourRegistration | None:
    """'auto' -> None (estimate it), 'off' -> IDENTITY, 'SCALE,DX,DY' -> that registration (applied)."""
    t = text.strip().lower()
    if t == "auto":
        return None
    if t == "off":
        return ColourRegistration(reason="--colour-registration off")
    try:
        s, dx, dy = (float(v) for v in t.split(","))
    except ValueError:
        raise ValueError(f"--colour-registration: expected 'auto', 'off' or 'SCALE,DX,DY' (numbers), got {text!r}") \
            from None
    if not (np.isfinite([s, dx, dy]).all() and 0.5 <= s <= 2.0):
        raise ValueError(f"--colour-registration {text!r}: the scale must be between 0.5 and 2 and all finite")
    return ColourRegistration(scale=s, shift=(dx, dy), applied=True, reason="given")


def _axis_taps(n: int, scale: float, centre: float, shift: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Source indices (i0, i1) and weights of i1 for the n destination pixels of one axis (clamped at the border)."""
    src = scale * (np.arange(n) + 0.5 - centre) + centre + shift - 0.5
    src = np.clip(src, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(src).astype(np.intp), n - 2)
    return i0, i0 + 1, (src - i0).astype(np.float32)


def register_colour(rgb: np.ndarray, reg: ColourRegistration, K: np.ndarray) -> np.ndarray:
    """Colour [H,W,C] (any dtype) resampled into the depth camera's pixels -> float32 [H,W,C] in the input's units.
    Linear interpolation along x, then along y; samples beyond the colour image take its border pixel."""
    if not reg.applied:
        return rgb.astype(np.float32, copy=False)
    H, W = rgb.shape[:2]
    a = rgb.astype(np.float32, copy=False)
    x0, x1, wx = _axis_taps(W, reg.scale, float(K[0, 2]), reg.shift[0])
    wx = wx[None, :, None] if a.ndim == 3 else wx[None, :]
    a = a[:, x0] * (1.0 - wx) + a[:, x1] * wx
    y0, y1, wy = _axis_taps(H, reg.scale, float(K[1, 2]), reg.shift[1])
    wy = wy[:, None, None] if a.ndim == 3 else wy[:, None]
    return a[y0] * (1.0 - wy) + a[y1] * wy


def outline_points(depth: np.ndarray, rng: np.random.Generator, n: int = POINTS_PER_FRAME) -> np.ndarray:
    """Points [N,2] (x, y; pixel coordinates, centres at +0.5) midway between 4-neighbours whose valid depths (> 0)
    differ by more than EDGE_JUMP of the nearer one; at most n, drawn at random."""
    d = np.asarray(depth, np.float64)
    pts = []
    for axis in (1, 0):
        a = d[:, :-1] if axis == 1 else d[:-1]
        b = d[:, 1:] if axis == 1 else d[1:]
        near = np.minimum(a, b)
        jump = (a > 0) & (b > 0) & (np.abs(a - b) > EDGE_JUMP * np.where(near > 0, near, 1.0))
        y, x = np.nonzero(jump)
        if axis == 1:
            pts.append(np.stack([x + 1.0, y + 0.5], 1))
        else:
            pts.append(np.stack([x + 0.5, y + 1.0], 1))
    p = np.concatenate(pts, 0)
    if len(p) > n:
        p = p[rng.choice(len(p), n, replace=False)]
    return p


def _gradient(grey: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter, sobel

    g = gaussian_filter(grey, sigma)
    return np.hypot(sobel(g, 0), sobel(g, 1))


class _Objective:
    """Mean colour gradient at the outline points mapped into the colour images, for a given (s, tx, ty)."""

    def __init__(self, grads: list[np.ndarray], points: list[np.ndarray], centre: tuple[float, float]):
        self.grads, self.points, self.c = grads, points, np.asarray(centre, np.float64)

    def __call__(self, s: float, tx: float, ty: float) -> float:
        from scipy.ndimage import map_coordinates

        total, n = 0.0, 0
        for g, p in zip(self.grads, self.points):
            q = s * (p - self.c) + self.c + (tx, ty) - 0.5  # array coordinates
            total += map_coordinates(g, [q[:, 1], q[:, 0]], order=1, mode="nearest").sum()
            n += len(p)
        return total / max(n, 1)

    def grid(self, scales: np.ndarray, shifts: np.ndarray) -> np.ndarray:
        """Scores [len(scales), len(shifts), len(shifts)] (x shift, y shift) by nearest-pixel lookup."""
        out = np.zeros((len(scales), len(shifts), len(shifts)))
        for g, p in zip(self.grads, self.points):
            H, W = g.shape
            for k, s in enumerate(scales):
                q = s * (p - self.c) + self.c - 0.5
                xi = np.clip(np.rint(q[:, 0][None, :] + shifts[:, None]).astype(np.intp), 0, W - 1)  # [S,N]
                yi = np.clip(np.rint(q[:, 1][None, :] + shifts[:, None]).astype(np.intp), 0, H - 1)
                out[k] += g[yi[None, :, :], xi[:, None, :]].sum(-1)  # [Sx,Sy]
        return out / max(sum(len(p) for p in self.points), 1)


def estimate_from_frames(frames: list[tuple[np.ndarray, np.ndarray]], K: np.ndarray,
                         seed: int = 0) -> ColourRegistration:
    """The registration that best puts colour edges on depth outlines, from (rgb [H,W,3] in [0,1], depth [H,W]
    metres, 0 = invalid) pairs at the stream's full resolution; IDENTITY-like (applied False) with the reason when
    it does not clearly beat reading the colour as it is."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(seed)
    grads, points = [], []
    for rgb, depth in frames:
        p = outline_points(depth, rng)
        if len(p) < 50:
            continue
        grey = np.asarray(rgb, np.float64)[..., :3].mean(-1)
        grads.append(_gradient(grey, 1.0))
        points.append(p)
    n_pts = int(sum(len(p) for p in points))
    if n_pts < 500:
        return ColourRegistration(frames=len(points), edge_points=n_pts,
                                  reason=f"too few depth outlines to measure ({n_pts} points)")
    W = frames[0][0].shape[1]
    centre = (float(K[0, 2]), float(K[1, 2]))
    fine = _Objective(grads, points, centre)
    from scipy.ndimage import gaussian_filter

    coarse = _Objective([gaussian_filter(g, 2.0) for g in grads], points, centre)
    max_shift = SHIFT_RANGE * W
    step = max(1.0, round(max_shift / 8))
    shifts = np.arange(-np.floor(max_shift / step) * step, max_shift + 1e-9, step)
    scales = np.arange(SCALE_RANGE[0], SCALE_RANGE[1] + 1e-9, 0.01)
    g = coarse.grid(scales, shifts)
    k, ix, iy = np.unravel_index(int(np.argmax(g)), g.shape)
    x0 = np.array([scales[k], shifts[ix], shifts[iy]])
    res = minimize(lambda v: -fine(*v), x0, method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-6, "initial_simplex": x0 + np.array(
                       [[0, 0, 0], [0.01, 0, 0], [0, step / 2, 0], [0, 0, step / 2]])})
    s, tx, ty = (float(v) for v in res.x)
    best, ident = float(-res.fun), fine(1.0, 0.0, 0.0)
    gain = float(best / max(ident, 1e-12))
    common = dict(scale=s, shift=(tx, ty), gain=gain, frames=len(points), edge_points=n_pts)
    at_bound = not (SCALE_RANGE[0] + 0.005 < s < SCALE_RANGE[1] - 0.005 and max(abs(tx), abs(ty)) < max_shift)
    if at_bound:
        return ColourRegistration(**common, reason="the best match lies at the edge of the search range")
    H = frames[0][0].shape[0]
    corners = np.array([[0.0, 0.0], [W, 0.0], [0.0, H], [W, H]]) - np.asarray(centre)
    move = float(np.abs((s - 1.0) * corners + (tx, ty)).max())
    if move < MIN_MOVE_PX:
        return ColourRegistration(**common, reason=f"it would move no pixel by more than {move:.1f} px")
    if gain < MIN_GAIN:
        return ColourRegistration(**common, reason=f"registering gains only {gain:.2f}x")
    return ColourRegistration(**common, applied=True, reason="estimated from depth outlines")


def estimate_colour_registration(stream, n_frames: int = ESTIMATE_FRAMES) -> ColourRegistration:
    """estimate_from_frames on n_frames frames spread evenly over the stream, read at full resolution as they are."""
    from trisplat.data.rgbd_stream import load_frame

    ids = np.unique(np.linspace(0, len(stream) - 1, min(n_frames, len(stream))).round().astype(int))
    saved, stream.colour_registration = stream.colour_registration, IDENTITY
    try:
        frames = [load_frame(stream, int(i), 1) for i in ids]
    finally:
        stream.colour_registration = saved
    return estimate_from_frames(frames, stream.K)


def apply_colour_registration(stream, mode: str = "auto") -> ColourRegistration:
    """Set stream.colour_registration from --colour-registration ('auto' estimates it) and return it."""
    reg = parse_registration(mode)
    if reg is None:
        reg = estimate_colour_registration(stream)
    stream.colour_registration = reg
    return reg


__all__ = ["ColourRegistration", "IDENTITY", "apply_colour_registration", "estimate_colour_registration",
           "estimate_from_frames", "outline_points", "parse_registration", "register_colour"]
