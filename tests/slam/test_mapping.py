"""How mapping spends its iterations (trisplat.slam.mapping.refine): over every keyframe (window 0, the final
refinement) each keyframe gets the same share; in a window, the newest keyframe gets half."""
from __future__ import annotations

from collections import Counter

import numpy as np
import torch

import trisplat.slam.mapping as mapping
from trisplat.scene.model import TriangleScene
from trisplat.slam.map import SlamMap
from trisplat.slam.mapping import Keyframe, MapConfig, refine


def _visits(monkeypatch, n_kf: int, iters: int, window: int | None) -> Counter:
    seen: list[int] = []

    def fake_loss(smap, kf, K, sigma, cfg):
        seen.append(kf.frame)
        return (smap.scene.positions ** 2).sum() * 0.0 + smap.scene.sh.sum() * 0.0

    monkeypatch.setattr(mapping, "keyframe_loss", fake_loss)
    g = torch.Generator().manual_seed(0)
    sc = TriangleScene.from_rgb(torch.rand(6, 3, generator=g), torch.arange(6, dtype=torch.int32).reshape(2, 3),
                                torch.rand(6, 3, generator=g), 0.5, 0)
    smap = SlamMap(sc, torch.ones(2), torch.zeros(2, dtype=torch.int64))
    kfs = [Keyframe(10 * k, torch.zeros(4, 4, 3), torch.zeros(4, 4), np.eye(4)) for k in range(n_kf)]
    refine(smap, kfs, np.eye(3), 0.3, iters, MapConfig(w_equiangular=0.0), np.random.default_rng(1), window=window)
    assert len(seen) == iters
    return Counter(seen)


def test_final_refinement_visits_every_keyframe_alike(monkeypatch):
    c = _visits(monkeypatch, n_kf=7, iters=21, window=0)
    assert sorted(c) == [10 * k for k in range(7)]
    assert set(c.values()) == {3}, c  # shuffled rounds: once each before twice each


def test_final_refinement_partial_round_visits_distinct_keyframes(monkeypatch):
    c = _visits(monkeypatch, n_kf=9, iters=13, window=0)
    assert max(c.values()) == 2 and sum(v == 2 for v in c.values()) == 4 and len(c) == 9, c


def test_window_gives_the_newest_keyframe_half(monkeypatch):
    c = _visits(monkeypatch, n_kf=8, iters=40, window=4)
    assert set(c) <= {40, 50, 60, 70}  # only the window's keyframes
    assert c[70] >= 20, c  # every even iteration, plus its share of the odd ones


def _sizes(monkeypatch, width: int, window: int | None, cfg: MapConfig) -> set:
    seen: set = set()

    def fake_loss(smap, kf, K, sigma, cfg):
        seen.add((tuple(kf.rgb.shape), tuple(kf.depth.shape), float(K[0, 0]), float(K[0, 2])))
        return (smap.scene.positions ** 2).sum() * 0.0 + smap.scene.sh.sum() * 0.0

    monkeypatch.setattr(mapping, "keyframe_loss", fake_loss)
    sc = TriangleScene.from_rgb(torch.rand(3, 3), torch.arange(3, dtype=torch.int32).reshape(1, 3), torch.rand(3, 3),
                                0.5, 0)
    smap = SlamMap(sc, torch.ones(1), torch.zeros(1, dtype=torch.int64))
    h = width * 3 // 4
    kfs = [Keyframe(k, torch.rand(h, width, 3), torch.full((h, width), 2.0), np.eye(4)) for k in range(3)]
    K = np.array([[width * 0.8, 0, width / 2], [0, width * 0.8, h / 2], [0, 0, 1.0]])
    refine(smap, kfs, K, 0.3, 6, cfg, np.random.default_rng(1), window=window)
    return seen


def test_mapping_while_tracking_runs_at_half_resolution(monkeypatch):
    """--slam.mapping.downscale 2 (the default): the window's keyframes at 160x120 for 320x240 frames, K scaled alike;
    the final refinement (window 0) at full size; frames that would fall below 160 px wide map at their own size."""
    assert MapConfig().downscale == 2
    assert _sizes(monkeypatch, 320, None, MapConfig(w_equiangular=0.0)) == {((120, 160, 3), (120, 160), 128.0, 80.0)}
    assert _sizes(monkeypatch, 320, 0, MapConfig(w_equiangular=0.0)) == {((240, 320, 3), (240, 320), 256.0, 160.0)}
    assert _sizes(monkeypatch, 160, None, MapConfig(w_equiangular=0.0)) == {((120, 160, 3), (120, 160), 128.0, 80.0)}
    assert _sizes(monkeypatch, 320, None, MapConfig(w_equiangular=0.0, downscale=1)) == {
        ((240, 320, 3), (240, 320), 256.0, 160.0)}


def test_a_keyframe_at_half_resolution_follows_its_pose():
    """at_scale: the photo box-filtered, the depth averaged but not across a depth edge; made once and cached; the pose
    and exposure are the keyframe's at each call (a loop closure moves keyframes)."""
    from trisplat.slam.mapping import at_scale

    rgb = torch.rand(8, 8, 3)
    depth = torch.full((8, 8), 2.0)
    depth[:, 4:] = 3.0  # an edge between blocks: kept sharp
    depth[0, 0] = 2.1  # within 10%: averaged
    kf = Keyframe(5, rgb, depth, np.eye(4))
    assert at_scale(kf, 1) is kf
    s = at_scale(kf, 2)
    assert s.rgb.shape == (4, 4, 3) and s.depth.shape == (4, 4) and s.frame == 5
    assert torch.allclose(s.rgb[1, 2], rgb[2:4, 4:6].mean((0, 1)))
    assert abs(float(s.depth[0, 0]) - 2.025) < 1e-6
    assert torch.all(s.depth[:, 2:] == 3.0) and torch.all(s.depth[1:, :2] == 2.0)
    moved = np.eye(4)
    moved[0, 3] = 0.5
    kf.c2w, kf.exposure = moved, np.ones((2, 3))
    s2 = at_scale(kf, 2)
    assert s2 is s and np.array_equal(s2.c2w, moved) and s2.exposure is kf.exposure
