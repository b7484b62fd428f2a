"""A small RGB-D sequence ray-cast from a known mesh along a known path (trisplat.synth), written in the 7-Scenes
layout (frame-NNNNNN.color.png / .depth.png in millimetres / .pose.txt, camera-intrinsics.txt): the capture of the
SLAM tests (the `rgbd_capture` fixture in tests/conftest.py)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from trisplat.synth.orbit import intrinsics, look_at
from trisplat.synth.rgbd_room import write_noiseless_sequence
from trisplat.synth.scenes import demo_mesh

W, H, N = 160, 120, 14
FOV_DEG = 60.0


def path_w2c(n: int = N) -> list[np.ndarray]:
    """World-to-camera matrices along an arc (6 degrees) that also rises and approaches, looking at the scene."""
    out = []
    for k in range(n):
        s = k / (n - 1)
        th = math.radians(-30 + 6 * s)
        r = 2.3 - 0.1 * s
        out.append(look_at((r * math.cos(th), r * math.sin(th), 1.1 + 0.1 * s), (0.0, 0.0, 0.25)))
    return out


def write_rgbd_sequence(root: Path, width: int = W, height: int = H, n: int = N,
                        path: list[np.ndarray] | None = None) -> Path:
    """Ray-cast `n` frames of demo_mesh(seed=0) along path_w2c (or the given world-to-camera path) into `root`
    (7-Scenes layout); returns `root`."""
    return write_noiseless_sequence(root, demo_mesh(seed=0), path_w2c(n) if path is None else path,
                                    intrinsics(width, height, FOV_DEG), width, height)


def loop_path_w2c(n: int = 25) -> list[np.ndarray]:
    """World-to-camera matrices once around the scene (360 degrees in n - 1 equal steps, radius 2.3 m, height
    1.1 m, looking at its centre): the last frame is back at the first one's pose."""
    out = []
    for k in range(n):
        th = math.radians(-30 + 360 * k / (n - 1))
        out.append(look_at((2.3 * math.cos(th), 2.3 * math.sin(th), 1.1), (0.0, 0.0, 0.25)))
    return out


def write_loop_sequence(root: Path, width: int = W, height: int = H, n: int = 25) -> Path:
    """Ray-cast the closed path loop_path_w2c(n) into `root` (7-Scenes layout), as write_rgbd_sequence."""
    return write_rgbd_sequence(root, width, height, n, path=loop_path_w2c(n))


def black_background_copy(src: Path, dst: Path, gains=None) -> Path:
    """The capture at `src` copied to `dst` with black where the depth camera saw nothing (the white synthetic
    background: a map or mesh renders black there, so PSNRs then measure the scene), and frame k's colour multiplied
    by gains[k] when given (an auto-exposing camera)."""
    import shutil

    from PIL import Image

    shutil.copytree(src, dst)
    files = sorted(dst.glob("frame-*.color.png"))
    gains = np.ones(len(files)) if gains is None else np.asarray(gains, np.float64)
    assert len(files) == len(gains)
    for f, g in zip(files, gains):
        a = np.asarray(Image.open(f)).astype(np.float64) * g
        depth = np.asarray(Image.open(str(f).replace(".color.png", ".depth.png")))
        a[depth == 0] = 0
        Image.fromarray(np.clip(np.round(a), 0, 255).astype(np.uint8)).save(f)
    return dst
