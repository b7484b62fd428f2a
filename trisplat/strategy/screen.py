"""Each face's size on screen: the longest projected edge in pixels, the statistic behind the pruning's "oversized"
rule, the densification's "too small to split" and the surface refinement's floor (trisplat.strategy).

Measured every training step for the view just rendered (a running maximum per face), so it is a Numba kernel on CPU
tensors (`trisplat bench losses`, a 328k-face sphere, 2 threads, idle: torch 26.8 ms, the kernel 4.4 ms).
`projected_edge_px_torch` is its readable twin and test oracle.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange


def projected_edge_px(positions: torch.Tensor, faces: torch.Tensor, world_to_camera: torch.Tensor,
                      K: torch.Tensor, near: float, width: int | None = None, height: int | None = None) -> torch.Tensor:
    """projected_edge_px_torch's values [F] (float32); the Numba kernel for CPU tensors."""
    if positions.device.type != "cpu":
        return projected_edge_px_torch(positions, faces, world_to_camera.to(positions), K.to(positions), near, width,
                                       height)
    pos = positions.detach().numpy()
    out = np.empty(len(faces), np.float32)
    check = width is not None and height is not None
    _edge_px(np.ascontiguousarray(pos), np.ascontiguousarray(faces.numpy()),
             np.asarray(world_to_camera.detach().numpy(), np.float64), np.asarray(K.detach().numpy(), np.float64),
             float(near), check, float(width or 0), float(height or 0), out)
    return torch.from_numpy(out)


@njit(cache=True, inline="always")
def _project(pos, i, w2c, near, fx, fy):
    """Vertex i in the camera: (x / z fx, y / z fy) with z clamped to `near`, and whether z > near."""
    x = w2c[0, 0] * pos[i, 0] + w2c[0, 1] * pos[i, 1] + w2c[0, 2] * pos[i, 2] + w2c[0, 3]
    y = w2c[1, 0] * pos[i, 0] + w2c[1, 1] * pos[i, 1] + w2c[1, 2] * pos[i, 2] + w2c[1, 3]
    z = w2c[2, 0] * pos[i, 0] + w2c[2, 1] * pos[i, 1] + w2c[2, 2] * pos[i, 2] + w2c[2, 3]
    zc = max(z, near)
    return x / zc * fx, y / zc * fy, z > near


@njit(parallel=True, cache=True)
def _edge_px(pos, faces, w2c, K, near, check, width, height, out):
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for f in prange(faces.shape[0]):
        u0, v0, ok0 = _project(pos, faces[f, 0], w2c, near, fx, fy)
        u1, v1, ok1 = _project(pos, faces[f, 1], w2c, near, fx, fy)
        u2, v2, ok2 = _project(pos, faces[f, 2], w2c, near, fx, fy)
        ok = ok0 and ok1 and ok2
        if ok and check:
            lo_u, hi_u = min(u0, min(u1, u2)) + cx, max(u0, max(u1, u2)) + cx
            lo_v, hi_v = min(v0, min(v1, v2)) + cy, max(v0, max(v1, v2)) + cy
            ok = hi_u >= 0.0 and lo_u <= width and hi_v >= 0.0 and lo_v <= height
        if not ok:
            out[f] = 0.0
            continue
        e01 = math.sqrt((u1 - u0) ** 2 + (v1 - v0) ** 2)
        e12 = math.sqrt((u2 - u1) ** 2 + (v2 - v1) ** 2)
        e20 = math.sqrt((u0 - u2) ** 2 + (v0 - v2) ** 2)
        out[f] = max(e01, max(e12, e20))


def projected_edge_px_torch(positions: torch.Tensor, faces: torch.Tensor, world_to_camera: torch.Tensor,
                            K: torch.Tensor, near: float, width: int | None = None, height: int | None = None) -> torch.Tensor:
    """Longest projected edge of each face in pixels [F]; 0 for faces with a vertex behind the near plane and, when
    the image size is given, for faces whose projection misses the image.

    The second rule matters wherever content surrounds the cameras (a room, an unbounded scene): a face just in
    front of the camera plane but far off to the side projects to a huge, entirely off-screen triangle (x / z with
    z near 0). Counting it as "oversized" pruned most of a room's faces in a few events (issue 24)."""
    pc = positions @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = pc[:, 2]
    uv = pc[:, :2] / z.clamp_min(near)[:, None] * torch.stack([K[0, 0], K[1, 1]])
    t = uv[faces]
    e = torch.stack([(t[:, 1] - t[:, 0]).norm(dim=1), (t[:, 2] - t[:, 1]).norm(dim=1),
                     (t[:, 0] - t[:, 2]).norm(dim=1)], 1).max(1).values
    ok = (z[faces] > near).all(1)
    if width is not None and height is not None:
        px = t + torch.stack([K[0, 2], K[1, 2]])  # pixel coordinates of the corners
        lo, hi = px.min(dim=1).values, px.max(dim=1).values
        ok &= (hi[:, 0] >= 0) & (lo[:, 0] <= width) & (hi[:, 1] >= 0) & (lo[:, 1] <= height)
    return torch.where(ok, e, torch.zeros_like(e))
