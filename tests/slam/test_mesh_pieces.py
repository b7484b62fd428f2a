"""SLAM's mesh keeps a room's separate pieces down to --slam.mesh-min-piece of the largest (chairs standing apart
from the floor in the fused surface), where the training switch drops pieces below 2% as floaters."""
from __future__ import annotations

import numpy as np
import pytest

import trisplat.train.switch as switch
from trisplat.slam.system import SlamConfig


def _strip(n: int, x0: float) -> tuple[np.ndarray, np.ndarray]:
    """A strip of 2n triangles (one connected piece) starting at x = x0."""
    xs = x0 + np.arange(n + 1, dtype=np.float64)
    v = np.concatenate([np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], 1),
                        np.stack([xs, np.ones_like(xs), np.zeros_like(xs)], 1)])
    i = np.arange(n)
    f = np.concatenate([np.stack([i, i + 1, n + 1 + i], 1), np.stack([i + 1, n + 2 + i, n + 1 + i], 1)])
    return v, f


def _two_pieces():
    va, fa = _strip(500, 0.0)  # 1,000 faces
    vb, fb = _strip(7, 1000.0)  # 14 faces: 1.4% of the largest
    return np.concatenate([va, vb]), np.concatenate([fa, fb + len(va)])


@pytest.mark.parametrize("fraction, kept", [(0.01, 2), (0.02, 1)])
def test_pieces_below_the_fraction_are_dropped(fraction, kept):
    v, f = _two_pieces()
    v2, f2, pieces, dropped = switch._drop_small_pieces(v, f, fraction)
    assert pieces == 2 and dropped == 2 - kept
    assert len(f2) == (1014 if kept == 2 else 1000) and f2.max() == len(v2) - 1  # unused vertices gone


def test_slam_mesh_uses_its_own_piece_fraction(monkeypatch, rgbd_capture):
    import torch

    from trisplat.data.rgbd_stream import load_frame, open_stream
    from trisplat.slam.map import SlamMap
    from trisplat.slam.mapping import Keyframe
    from trisplat.slam.system import map_surface

    seen = {}

    def fake_soup_to_surface(scene, cams, render, bounds, config, progress=None, images=None):
        seen["config"] = config
        raise RuntimeError("stop here")

    monkeypatch.setattr(switch, "soup_to_surface", fake_soup_to_surface)
    stream = open_stream(rgbd_capture)
    rgb, depth = load_frame(stream, 0, 1)
    kf = Keyframe(0, torch.from_numpy(rgb), torch.from_numpy(depth), np.eye(4))
    for frac in (0.01, 0.005):
        with pytest.raises(RuntimeError, match="stop here"):
            map_surface(SlamMap.empty(), [kf], stream, SlamConfig(downscale=1, mesh_min_piece=frac), lambda *a, **k: None)
        assert seen["config"].min_component_fraction == frac and seen["config"].unseen_faces == "drop"
    assert SlamConfig().mesh_min_piece == 0.01 < switch.SurfaceConfig().min_component_fraction
