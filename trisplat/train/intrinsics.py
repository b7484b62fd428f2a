"""Focal length and principal point refined through the renderer, with the scene (issue 24; as 3DGS variants do).

The kernels project world positions themselves, so they return gradients for the positions, not for K. A change of
a view's intrinsics is exactly a change of the camera-space positions of everything it sees, depth unchanged:

    u = fx e^s x / z + cx + dx  =  fx (e^s x + (dx / fx) z) / z + cx        (and v likewise with fy, dy)

A training view is rendered with its current refined K, and the positions pass through that camera-space warp at
the identity (each parameter minus its detached value): the render is bit for bit the same, and autograd carries
dL/ds, dL/d(dx), dL/d(dy) out of the kernels' position gradients. Parameters per group of cameras with the same
intrinsics and image size (a capture from one camera: 3 numbers): s = log of the focal length's scale (fx and fy
together: pixels stay square), dx, dy = principal point shift in pixels.

The refined K is the capture's calibration: evaluation, the switch, texturing and file scoring use it. The run keeps
it in `intrinsics.json`, which `Run.load_scene_data` applies.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from trisplat.io.atomic import atomic_write_text

FILE = "intrinsics.json"


def _group_key(cam) -> tuple:
    K = np.asarray(cam.K, np.float64)
    return (int(cam.width), int(cam.height), *np.round([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], 6).tolist())


def camera_groups(cameras) -> np.ndarray:
    """int [N]: the group of each camera (cameras with equal intrinsics and image size share one)."""
    keys: dict[tuple, int] = {}
    return np.array([keys.setdefault(_group_key(c), len(keys)) for c in cameras], dtype=np.int64)


def refined_K(K: np.ndarray, params) -> np.ndarray:
    """K with the focal lengths scaled by e^s and the principal point moved by (dx, dy) pixels."""
    s, dx, dy = (float(v) for v in params)
    out = np.array(K, dtype=np.float64, copy=True)
    out[0, 0] *= np.exp(s)
    out[1, 1] *= np.exp(s)
    out[0, 2] += dx
    out[1, 2] += dy
    return out


class Intrinsics:
    """Refined intrinsics of `cameras` (indexed like SceneData.cameras), with their own Adam."""

    def __init__(self, cameras, lr_focal: float, lr_principal: float, values: torch.Tensor | None = None):
        self.group = camera_groups(cameras)
        n = int(self.group.max()) + 1 if len(self.group) else 0
        first = [int(np.flatnonzero(self.group == g)[0]) for g in range(n)]
        self.base = [np.asarray(cameras[i].K, np.float64).copy() for i in first]
        init = torch.zeros(n, 3) if values is None else torch.as_tensor(values).detach().clone().float()
        if init.shape != (n, 3):
            raise ValueError(f"intrinsics parameters must be [{n},3] for {n} camera group(s), got {tuple(init.shape)}")
        self.focal = torch.nn.Parameter(torch.zeros(n, 1))  # s: log of the focal length's scale
        self.shift = torch.nn.Parameter(torch.zeros(n, 2))  # dx, dy: the principal point's shift, pixels
        self.lr = (float(lr_focal), float(lr_principal))
        self.load_state(init)

    @property
    def params(self) -> torch.Tensor:
        """[G,3]: s, dx, dy per camera group."""
        return torch.cat([self.focal, self.shift], 1)

    def K(self, index: int) -> np.ndarray:
        """The current refined K of camera `index` (float64 [3,3])."""
        g = int(self.group[index])
        return refined_K(self.base[g], self.params.detach()[g])

    def warp(self, positions: torch.Tensor, world_to_camera: torch.Tensor, index: int) -> torch.Tensor:
        """positions [V,3] unchanged in value, carrying the gradient of this view's intrinsics (module docstring)."""
        g = int(self.group[index])
        p = self.params[g]
        d = p - p.detach()  # zeros, with the gradient path
        K = self.K(index)
        R = world_to_camera[:3, :3].to(positions.dtype)
        t = world_to_camera[:3, 3].to(positions.dtype)
        pc = positions @ R.T + t
        x, y, z = pc.unbind(-1)
        moved = torch.stack([x * torch.expm1(d[0]) + d[1] * z / float(K[0, 0]),
                             y * torch.expm1(d[0]) + d[2] * z / float(K[1, 1]),
                             torch.zeros_like(z)], -1)  # exactly zero in value
        return positions + moved @ R

    def step(self, scale: float = 1.0) -> None:
        for group, lr in zip(self.optimizer.param_groups, self.lr):
            group["lr"] = lr * scale
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def state(self) -> torch.Tensor:
        return self.params.detach().clone()

    def load_state(self, values) -> None:
        """Set the parameters (a `state()`), keeping the base intrinsics; the optimiser starts afresh."""
        values = torch.as_tensor(values).detach().float()
        if values.shape != self.params.shape:
            raise ValueError(f"intrinsics parameters must be {list(self.params.shape)}, got {list(values.shape)}")
        with torch.no_grad():
            self.focal.copy_(values[:, :1])
            self.shift.copy_(values[:, 1:])
        self.optimizer = torch.optim.Adam([{"params": [self.focal], "lr": self.lr[0]},
                                           {"params": [self.shift], "lr": self.lr[1]}], eps=1e-15)

    def apply(self, cameras: list) -> None:
        """Write the refined K into `cameras` (a SceneData's list, same order), in place."""
        for i, cam in enumerate(cameras):
            cameras[i] = replace(cam, K=self.K(i))

    def summary(self) -> dict:
        """Per group: focal length before and after (pixels), its change (%), the principal point's shift (pixels)."""
        out = []
        for g, K in enumerate(self.base):
            s, dx, dy = (float(v) for v in self.params.detach()[g])
            out.append({"cameras": int((self.group == g).sum()), "fx_before": float(K[0, 0]),
                        "fx_after": float(K[0, 0] * np.exp(s)), "focal_change_percent": 100.0 * float(np.expm1(s)),
                        "principal_point_shift_px": [dx, dy]})
        return {"groups": out}

    def save(self, run_dir: Path) -> None:
        record = {"group": self.group.tolist(), "params": self.params.detach().tolist(), **self.summary()}
        atomic_write_text(Path(run_dir) / FILE, json.dumps(record, indent=1))


def apply_saved(run_dir: Path, data) -> None:
    """Give `data` (the run's capture, loaded as the run loaded it) the refined intrinsics the run saved, if any."""
    path = Path(run_dir) / FILE
    if not path.is_file():
        return
    try:
        record = json.loads(path.read_text())
        group, params = np.asarray(record["group"], np.int64), np.asarray(record["params"], np.float64)
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: malformed refined intrinsics ({exc})") from exc
    if len(group) != len(data.cameras) or params.ndim != 2 or params.shape[1] != 3 or group.max(initial=-1) >= len(params):
        raise ValueError(f"{path}: refined intrinsics for {len(group)} cameras in {len(params)} group(s), but the "
                         f"capture has {len(data.cameras)} cameras: was it loaded with other options?")
    if not np.array_equal(camera_groups(data.cameras), group):
        raise ValueError(f"{path}: the capture's cameras do not group as when the run refined them")
    for i, cam in enumerate(data.cameras):
        data.cameras[i] = replace(cam, K=refined_K(cam.K, params[group[i]]))
