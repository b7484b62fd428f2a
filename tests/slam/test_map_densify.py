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


def test_depth_holes_near_measurements_take_the_nearest_depth_where_asked():
    from trisplat.slam.map import fill_depth_holes

    depth = np.zeros((10, 12), np.float32)
    depth[:, :4] = 1.0  # measured on the left, nothing on the right (too near for the sensor, say)
    depth[0, 0] = 0.0  # a single missing pixel inside the measured part
    where = np.ones_like(depth, bool)
    where[5:, :] = False  # the map already covers the lower half
    out = fill_depth_holes(depth, where, max_px=3)
    assert depth[0, 0] == 0.0 and out is not depth  # the input is not changed
    np.testing.assert_array_equal(out[:5, :7], 1.0)  # within 3 px of a measurement, in the upper half: filled
    assert (out[:5, 7:] == 0).all() and (out[5:, 4:] == 0).all()  # farther, or covered by the map: left empty
    assert out[0, 0] == 1.0
    assert fill_depth_holes(np.zeros((4, 4), np.float32), np.ones((4, 4), bool), 3).max() == 0  # nothing measured


def test_spawning_with_filled_holes_covers_pixels_without_depth():
    from trisplat.slam.map import SlamMap, spawn

    H, W = 30, 40
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, 28:] = 0.0  # the right part has no measurement
    rgb = np.full((H, W, 3), 0.5, np.float32)
    K = np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])

    def spawned_x(fill):
        smap = SlamMap.empty()
        n = spawn(smap, rgb, depth, np.eye(4), K, 0, SpawnConfig(stride=3, fill_holes_px=fill), 0.3,
                  np.random.default_rng(0))
        cx = smap.scene.positions.reshape(-1, 3, 3).mean(1)[:, 0].numpy()
        return n, cx / 2.0 * 40.0 + W / 2  # column of each triangle's centre (z = 2)

    n0, col0 = spawned_x(0)
    n6, col6 = spawned_x(6)
    assert col0.max() < 28 and n6 > n0  # without filling, nothing beyond the measured columns
    assert 28 <= col6.max() <= 28 + 6 + 2  # filled up to 6 px beyond them, at the nearest measured depth
