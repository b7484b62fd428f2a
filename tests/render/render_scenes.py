"""Small random triangle scenes for the renderer tests (overlapping, off-screen, behind the camera, degenerate...)."""
from __future__ import annotations

import numpy as np
import torch

W, H = 40, 32


def camera(width: int = W, height: int = H, dtype=torch.float64):
    """Identity pose (camera at the origin looking down +z) and a pinhole K with a ~53 degree horizontal view."""
    K = torch.tensor([[width * 1.0, 0.0, width / 2], [0.0, width * 1.0, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def unproject(uv: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points with screen position uv [N,2] (pixels) and view depth z [N]."""
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], 1)


def random_scene(seed: int, n_faces: int = 24, width: int = W, height: int = H, kinds: bool = True,
                 opacity_range=(0.3, 0.95), dtype=torch.float64):
    """A triangle soup of n_faces random faces plus (kinds=True) one face of each awkward kind.

    Returns positions [V,3], faces int32 [F,3], colors [V,3], opacities [V], world_to_camera, K (torch, `dtype`).
    Random faces: screen size 3-20 px, depth 1.5-4, partly off-screen allowed. Awkward kinds: huge (covers the image),
    tiny (~0.7 px), degenerate (collinear), behind the camera, crossing the near plane, entirely off-screen.
    """
    rng = np.random.default_rng(seed)
    w2c, K = camera(width, height, dtype)
    Kn = K.numpy()
    tris = []
    for _ in range(n_faces):
        c = rng.uniform([-4, -4], [width + 4, height + 4])
        size = rng.uniform(3, 20)
        uv = c + rng.normal(size=(3, 2)) * size / 2
        z = rng.uniform(1.5, 4.0) + rng.normal(size=3) * 0.2
        tris.append(unproject(uv, z, Kn))
    if kinds:
        tris.append(unproject(np.array([[-30.0, -20.0], [width + 40, -10], [width / 2, height + 40]]),
                              np.array([5.0, 5.5, 6.0]), Kn))  # huge, behind everything else
        tris.append(unproject(np.array([[10.2, 10.1], [11.1, 10.3], [10.5, 11.0]]), np.array([1.2, 1.2, 1.2]), Kn))
        tris.append(unproject(np.array([[5.0, 5.0], [15.0, 10.0], [25.0, 15.0]]), np.array([2.0, 2.0, 2.0]), Kn))
        tris.append(np.array([[0.0, 0.0, -1.0], [1.0, 0.0, -1.2], [0.0, 1.0, -1.1]]))  # behind the camera
        tris.append(np.array([[-0.2, -0.2, -0.5], [0.3, -0.1, 1.5], [0.0, 0.3, 1.5]]))  # crosses the near plane
        tris.append(unproject(np.array([[-30.0, 5.0], [-10.0, 8.0], [-20.0, 20.0]]), np.array([2.0, 2.0, 2.0]), Kn))
    pos = np.concatenate(tris, 0)
    F = len(tris)
    faces = np.arange(3 * F, dtype=np.int32).reshape(F, 3)
    colors = rng.uniform(0, 1, size=(3 * F, 3))
    opac = rng.uniform(*opacity_range, size=3 * F)
    t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    return t(pos), torch.tensor(faces), t(colors), t(opac), w2c, K


def mesh_scene(seed: int, n: int = 5, width: int = W, height: int = H, dtype=torch.float64):
    """A connected, slightly bumpy grid mesh facing the camera (shared vertices), plus a second offset layer."""
    rng = np.random.default_rng(seed)
    w2c, K = camera(width, height, dtype)
    xs = np.linspace(-0.7, 0.7, n)
    gx, gy = np.meshgrid(xs, xs * 0.8)
    # Jitter so that no pixel centre sits on a medial axis (where phi = max_k L_k has a kink).
    gx, gy = gx + rng.normal(size=gx.shape) * 0.03, gy + rng.normal(size=gy.shape) * 0.03
    verts = []
    for depth, shift in ((2.0, 0.0), (2.6, 0.13)):
        z = depth + rng.normal(size=gx.shape) * 0.05
        verts.append(np.stack([gx.ravel() + shift, gy.ravel() + shift, z.ravel()], 1))
    pos = np.concatenate(verts, 0)
    faces = []
    for layer in range(2):
        o = layer * n * n
        for i in range(n - 1):
            for j in range(n - 1):
                a, b, c, d = o + i * n + j, o + i * n + j + 1, o + (i + 1) * n + j, o + (i + 1) * n + j + 1
                faces += [[a, b, d], [a, d, c]]
    V = pos.shape[0]
    colors = rng.uniform(0, 1, size=(V, 3))
    opac = rng.uniform(0.3, 0.95, size=V)
    t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    return t(pos), torch.tensor(np.array(faces, dtype=np.int32)), t(colors), t(opac), w2c, K
