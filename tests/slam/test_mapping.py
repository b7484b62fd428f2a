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
