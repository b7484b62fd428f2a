"""Spawning densifies where the map renders the photo's colours wrong, not only where it is thin."""
from __future__ import annotations

import numpy as np

from trisplat.slam.map import SpawnConfig, thin_mask


def test_thin_mask_adds_pixels_with_a_high_photometric_error():
    H, W = 24, 32
    depth = np.full((H, W), 2.0, np.float32)
    alpha = np.ones((H, W), np.float32)  # the map covers everything, at the observed depth
    surf = depth.copy()
    photo = np.full((H, W, 3), 0.5, np.float32)
    photo[8:16, 8:16] = [0.9, 0.1, 0.1]  # a red patch the map does not have
    rendered = np.full((H, W, 3), 0.5, np.float32)
    cfg = SpawnConfig(stride=3)
    assert not thin_mask(photo, depth, alpha, surf, cfg).any()  # depth and alpha alone: nothing to spawn
    m = thin_mask(photo, depth, alpha, surf, cfg, rendered)
    assert m[10:14, 10:14].all() and not m[:4].any() and not m[:, 24:].any()
    assert not thin_mask(photo, depth, alpha, surf, SpawnConfig(stride=3, color_error=0.0), rendered).any()
    # where the map's surface is elsewhere (behind), a colour error is no reason: that is the depth test's business
    behind = thin_mask(photo, depth, alpha, surf + 0.5, cfg, rendered)
    assert behind.all()  # observed in front of the map: thin by the depth test, colour or not
