"""Per-keyframe exposure: the map holds one colour per surface point, each photo sees it through its own exposure.

A depth camera's colour stream runs auto exposure and white balance (7-Scenes' Kinect: keyframe gains from 0.91 to
1.11 and biases from -0.10 to 0.14). A map fitted to such photos as they are averages their exposures and fits none
of them. Here every
keyframe k has an affine colour per channel, photo ~= clamp(gain_k * map + bias_k, 0, 1) (sRGB values, as the map
blends them), solved in closed form against the map's render on the covered, unsaturated pixels each time mapping
visits the keyframe (alternating with the map's gradient steps), with a small ridge towards the identity that holds
the gauge (the map's colours and every exposure could otherwise drift together); at the end the map is moved to the
keyframes' mean exposure (`regauge`), so the map and the mesh show the capture's average look. `trisplat slam`
solves the exposures in its final refinement only (SlamConfig.exposure). A frame that is not a keyframe gets the
exposure interpolated in time between the keyframes around it (from keyframes only, never from its own photo).

An exposure is a float array [2,3]: row 0 the gains, row 1 the biases, per channel (r, g, b)."""
from __future__ import annotations

import numpy as np
import torch

SATURATED = 0.98
"""photo or render values at or above this (or at or below 1 - this) are left out of the fit: clipped, they say
nothing about the gain"""


def identity() -> np.ndarray:
    return np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])


def fit_exposure(render: torch.Tensor | np.ndarray, photo: torch.Tensor | np.ndarray,
                 covered: torch.Tensor | np.ndarray, ridge: float) -> np.ndarray:
    """The exposure [2,3] minimising, per channel, sum over the covered unsaturated pixels of
    (gain * render + bias - photo)^2 + ridge * n * ((gain - 1)^2 + bias^2). render / photo [H,W,3], covered [H,W]
    bool. With fewer than 100 usable pixels: the identity."""
    r = torch.as_tensor(render).detach().reshape(-1, 3).double()
    p = torch.as_tensor(photo).detach().reshape(-1, 3).double()
    m = torch.as_tensor(covered).reshape(-1)
    lo = 1.0 - SATURATED
    m = m & (p.amax(1) < SATURATED) & (p.amin(1) > lo) & (r.amax(1) < SATURATED) & (r.amin(1) > lo)
    n = float(m.sum())
    if n < 100:
        return identity()
    x, y = r[m], p[m]
    lam = ridge * n
    sx, sy, sxx, sxy = x.sum(0), y.sum(0), (x * x).sum(0), (x * y).sum(0)
    # normal equations [[sxx + lam, sx], [sx, n + lam]] [g, b] = [sxy + lam, sy]
    det = (sxx + lam) * (n + lam) - sx * sx
    g = ((sxy + lam) * (n + lam) - sx * sy) / det
    b = ((sxx + lam) * sy - sx * (sxy + lam)) / det
    return torch.stack([g, b]).numpy()


def apply_exposure(rgb: torch.Tensor, e: np.ndarray | None, alpha: torch.Tensor | None = None) -> torch.Tensor:
    """What a photo with exposure e shows of the map's colours rgb [...,3] (clamped to [0, 1]); None: unchanged.
    alpha [...]: rgb is a render composited over black with this coverage; the bias applies to the covered part only
    (an empty pixel stays black)."""
    if e is None:
        return rgb
    g = torch.as_tensor(e[0], dtype=rgb.dtype)
    b = torch.as_tensor(e[1], dtype=rgb.dtype)
    bias = b if alpha is None else alpha[..., None].to(rgb.dtype) * b
    return (rgb * g + bias).clamp(0.0, 1.0)


def undo_exposure(rgb: np.ndarray, e: np.ndarray | None) -> np.ndarray:
    """The map's colours [...,3] that a photo with exposure e shows as rgb (clipped to [0, 1]); None: unchanged."""
    if e is None:
        return rgb
    return np.clip((rgb - e[1]) / e[0], 0.0, 1.0).astype(rgb.dtype)


def interpolate_exposure(frames: list[int], exposures: list[np.ndarray], n: int) -> np.ndarray:
    """Exposure of frame n (the run's numbering) from the keyframes' (frames sorted, one exposure each): linear in
    the frame number between the two keyframes around n, the nearest one's outside them."""
    f = np.asarray(frames)
    j = int(np.searchsorted(f, n))
    if j < len(f) and f[j] == n:
        return exposures[j]
    if j == 0:
        return exposures[0]
    if j == len(f):
        return exposures[-1]
    t = (n - f[j - 1]) / (f[j] - f[j - 1])
    return (1 - t) * exposures[j - 1] + t * exposures[j]


def regauge(exposures: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Move the gauge to the keyframes' mean exposure: returns (m [2,3], new exposures) with map colours to become
    m[0] * rgb + m[1] and each keyframe's exposure e' with e'(m(rgb)) = e(rgb)."""
    m = np.mean(np.stack(exposures), 0)
    new = []
    for e in exposures:
        g = e[0] / m[0]
        new.append(np.stack([g, e[1] - g * m[1]]))
    return m, new


def regauge_map(smap, keyframes) -> np.ndarray:
    """Move a SlamMap's colours and its keyframes' exposures (Keyframe.exposure, all set) to the keyframes' mean
    exposure (`regauge`); the photos' view of the map is unchanged. Returns the mean exposure m [2,3]."""
    from trisplat.scene.sh import rgb_to_sh_dc

    m, new = regauge([kf.exposure for kf in keyframes])
    sc = smap.scene
    with torch.no_grad():
        rgb = smap.colors()  # clamped to [0, 1], as rendered
        dc = rgb_to_sh_dc(rgb * torch.as_tensor(m[0], dtype=rgb.dtype) + torch.as_tensor(m[1], dtype=rgb.dtype))
        sc.sh[:, 0, :] = dc.to(sc.sh.dtype)
    for kf, e in zip(keyframes, new):
        kf.exposure = e
    return m


def exposure_range(keyframes, row: int) -> str:
    """'lo-hi' of the keyframes' gains (row 0) or biases (row 1) over every channel."""
    v = np.stack([kf.exposure[row] for kf in keyframes])
    return f"{v.min():.2f} to {v.max():.2f}"
