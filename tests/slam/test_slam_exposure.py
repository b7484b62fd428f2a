"""Per-keyframe exposure (trisplat.slam.exposure): the closed-form fit recovers a known gain and bias and ignores
clipped pixels; held-out frames get the exposure interpolated between keyframes; moving the gauge leaves what each
photo sees unchanged; and end to end, a capture whose colour stream changes its exposure from frame to frame is
mapped better with the exposures than without, and the fitted gains follow the true ones."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from trisplat.data.rgbd_stream import open_stream
from trisplat.slam.exposure import (apply_exposure, fit_exposure, identity, interpolate_exposure, regauge,
                                    regauge_map, undo_exposure)
from trisplat.slam.map import SlamMap
from trisplat.slam.mapping import Keyframe
from trisplat.slam.system import SlamConfig, run_slam
from trisplat.slam.track import TrackConfig
from trisplat.scene.model import TriangleScene
from tests.slam.rgbd_scene import black_background_copy


def _render_and_photo(gain, bias, seed=0, shape=(60, 80)):
    rng = np.random.default_rng(seed)
    render = rng.uniform(0.05, 0.95, shape + (3,)).astype(np.float32)
    photo = np.clip(render * np.asarray(gain) + np.asarray(bias), 0, 1).astype(np.float32)
    return render, photo


def test_fit_recovers_gain_and_bias():
    g, b = [0.8, 1.1, 0.95], [0.05, 0.03, 0.0]
    render, photo = _render_and_photo(g, b)
    covered = np.ones(render.shape[:2], bool)
    e = fit_exposure(torch.from_numpy(render), torch.from_numpy(photo), torch.from_numpy(covered), ridge=1e-6)
    assert e.shape == (2, 3)
    # the photo saturates where 1.1 x render + bias > 0.98: those pixels are left out, so the fit stays exact
    np.testing.assert_allclose(e[0], g, atol=2e-3)
    np.testing.assert_allclose(e[1], b, atol=2e-3)
    # were the clipped pixels used, the green gain would come out low: check they matter here
    x, y = render[..., 1].ravel(), photo[..., 1].ravel()
    naive = np.polyfit(x, y, 1)[0]
    assert naive < 1.09


def test_fit_only_uses_covered_pixels_and_falls_back_to_identity():
    render, photo = _render_and_photo([0.7, 0.7, 0.7], [0.0, 0.0, 0.0])
    covered = np.zeros(render.shape[:2], bool)
    covered[:, :40] = True
    photo[:, 40:] = 0.5  # what an uncovered pixel shows does not count
    e = fit_exposure(render, photo, covered, ridge=1e-6)
    np.testing.assert_allclose(e[0], 0.7, atol=2e-3)
    few = np.zeros_like(covered)
    few[0, :10] = True
    np.testing.assert_array_equal(fit_exposure(render, photo, few, ridge=1e-6), identity())
    # the ridge pulls a fit towards the identity
    strong = fit_exposure(render, photo, covered, ridge=10.0)
    assert 0.7 + 1e-3 < strong[0][0] < 1.0


def test_apply_and_undo_are_inverse_and_empty_pixels_stay_black():
    e = np.array([[0.8, 1.1, 0.9], [0.05, -0.02, 0.01]])
    rgb = np.random.default_rng(1).uniform(0.1, 0.8, (5, 4, 3)).astype(np.float32)
    seen = apply_exposure(torch.from_numpy(rgb), e).numpy()
    np.testing.assert_allclose(undo_exposure(seen, e), rgb, atol=1e-6)
    alpha = torch.zeros(5, 4)
    alpha[0] = 1.0
    black = torch.zeros(5, 4, 3)
    out = apply_exposure(black, e, alpha).numpy()
    assert np.all(out[1:] == 0) and np.allclose(out[0], np.clip(e[1], 0, 1))
    assert apply_exposure(torch.from_numpy(rgb), None) is not None and undo_exposure(rgb, None) is rgb


def test_interpolation_between_keyframes():
    es = [np.full((2, 3), v) for v in (1.0, 2.0, 4.0)]
    frames = [0, 10, 20]
    np.testing.assert_allclose(interpolate_exposure(frames, es, 5), 1.5)
    np.testing.assert_allclose(interpolate_exposure(frames, es, 10), 2.0)
    np.testing.assert_allclose(interpolate_exposure(frames, es, 15), 3.0)
    np.testing.assert_allclose(interpolate_exposure(frames, es, 25), 4.0)  # after the last: the last's
    np.testing.assert_allclose(interpolate_exposure([3, 8], es[:2], 1), 1.0)


def test_regauge_keeps_what_each_photo_sees():
    rng = np.random.default_rng(2)
    exposures = [np.stack([rng.uniform(0.7, 1.2, 3), rng.uniform(-0.05, 0.05, 3)]) for _ in range(4)]
    m, new = regauge(exposures)
    np.testing.assert_allclose(np.mean(np.stack(new), 0), identity(), atol=1e-12)
    # and on a map: colours move to the mean, each keyframe's view of them does not change
    V = 30
    rgb = torch.from_numpy(rng.uniform(0.2, 0.7, (V, 3)).astype(np.float32))
    scene = TriangleScene.from_rgb(torch.randn(V, 3), torch.arange(V, dtype=torch.int32).reshape(-1, 3), rgb, 0.5, 0)
    smap = SlamMap(scene, torch.ones(V // 3), torch.zeros(V // 3, dtype=torch.int64))
    kfs = [Keyframe(k, torch.zeros(1), torch.zeros(1), np.eye(4), exposure=e) for k, e in enumerate(exposures)]
    before = [apply_exposure(smap.colors(), e) for e in exposures]
    regauge_map(smap, kfs)
    np.testing.assert_allclose(smap.colors().numpy(), np.clip(rgb.numpy() * m[0] + m[1], 0, 1), atol=1e-5)
    for kf, b in zip(kfs, before):
        np.testing.assert_allclose(apply_exposure(smap.colors(), kf.exposure).numpy(), b.numpy(), atol=1e-5)


@pytest.mark.slow
def test_slam_with_exposure_maps_an_auto_exposing_camera(rgbd_capture, tmp_path):
    n = len(sorted(rgbd_capture.glob("frame-*.color.png")))
    gains = 0.85 + 0.15 * np.cos(np.linspace(0, 2 * np.pi, n))  # 1.0 -> 0.7 -> 1.0
    cap = black_background_copy(rgbd_capture, tmp_path / "cap", gains)
    base = dict(downscale=1, final_iters=40, checkpoint_every=0, eval_every=1, mesh_resolution=128,
                keyframe_every=2, track=TrackConfig(levels=(2, 1), max_iters=(60, 40)))
    runs = {}
    for on in (True, False):
        runs[on] = run_slam(open_stream(cap), tmp_path / f"run_{on}", SlamConfig(exposure=on, **base),
                            log=lambda *a, **k: None)
    on, off = runs[True], runs[False]
    assert off["exposure"] is None and off["held_out"]["psnr_without_exposure"] is None
    ex = on["exposure"]
    kf = ex["keyframes"]
    # what each keyframe's exposure makes of a mid-grey map colour follows the camera's gain, up to the gauge (the map
    # ends at the keyframes' mean exposure)
    est = (0.5 * np.array(ex["gain"]) + np.array(ex["bias"])).mean(1)
    true = gains[kf]
    np.testing.assert_allclose(est / est.mean(), true / true.mean(), atol=0.07)
    assert np.corrcoef(est, true)[0, 1] > 0.97
    # held-out frames: interpolated exposure beats the photos taken as they are, on the map and on the mesh
    assert on["held_out"]["psnr"] > off["held_out"]["psnr"] + 1.0  # 23.5 against 21.9 dB
    assert on["held_out_mesh"]["psnr"] > off["held_out_mesh"]["psnr"] + 0.7  # 23.7 against 22.2 dB
    assert on["held_out"]["psnr_without_exposure"] < on["held_out"]["psnr"]
