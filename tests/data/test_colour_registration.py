"""Colour-to-depth registration (trisplat.data.colour_registration): a colour camera with another focal length and
principal point than the depth camera's is measured from the frames alone and resampled onto the depth camera; a
registered capture is left as it is."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from trisplat.cameras import Camera
from trisplat.data.colour_registration import (
    ColourRegistration,
    estimate_colour_registration,
    outline_points,
    parse_registration,
    register_colour,
)
from trisplat.data.rgbd_stream import load_frame, open_stream
from trisplat.synth.orbit import intrinsics
from trisplat.synth.raycast import raycast_view
from trisplat.synth.rgbd_room import write_noiseless_sequence
from trisplat.synth.scenes import demo_mesh

W, H = 320, 240
SCALE, SHIFT = 0.9, (5.0, -3.0)  # the colour camera: focal 0.9x the depth's, principal point moved by SHIFT


def _psnr(a, b):
    return float(-10 * np.log10(np.mean((np.asarray(a, np.float64) - b) ** 2)))


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """(registered, misregistered) 7-Scenes-layout captures of the same 5 frames: the second's colour is ray-cast by
    a colour camera with focal SCALE x the depth camera's and principal point + SHIFT."""
    from tests.slam.rgbd_scene import path_w2c

    root = tmp_path_factory.mktemp("reg")
    K = intrinsics(W, H, 60.0)
    path = path_w2c(5)
    mesh = demo_mesh(seed=0)
    good = write_noiseless_sequence(root / "good", mesh, path, K, W, H)
    bad = write_noiseless_sequence(root / "bad", mesh, path, K, W, H)
    Kc = K.copy()
    Kc[0, 0] *= SCALE
    Kc[1, 1] *= SCALE
    Kc[0, 2] += SHIFT[0]
    Kc[1, 2] += SHIFT[1]
    for k, w2c in enumerate(path):
        v = raycast_view(mesh, Camera(w2c, Kc, W, H), background=(1.0, 1.0, 1.0))
        Image.fromarray((v.rgba[..., :3] * 255 + 0.5).astype(np.uint8)).save(bad / f"frame-{k:06d}.color.png")
    return good, bad


def test_a_zoomed_and_shifted_colour_camera_is_measured(captures):
    _, bad = captures
    reg = estimate_colour_registration(open_stream(bad))
    assert reg.applied, reg
    assert abs(reg.scale - SCALE) < 0.005
    np.testing.assert_allclose(reg.shift, SHIFT, atol=0.6)
    assert reg.gain > 1.5


def test_registered_colour_is_what_the_depth_camera_sees(captures):
    good, bad = captures
    truth = [load_frame(open_stream(good), k)[0] for k in range(5)]
    stream = open_stream(bad)
    raw = [load_frame(stream, k)[0] for k in range(5)]
    stream.colour_registration = ColourRegistration(scale=SCALE, shift=SHIFT, applied=True)
    registered = [load_frame(stream, k) for k in range(5)]
    before = np.mean([_psnr(r, t) for r, t in zip(raw, truth)])
    after = np.mean([_psnr(r[0], t) for r, t in zip(registered, truth)])
    assert after > before + 8.0 and after > 24.0, (before, after)
    # depth is untouched
    np.testing.assert_array_equal(registered[0][1], load_frame(open_stream(good), 0)[1])


def test_a_registered_capture_is_left_alone(captures):
    good, _ = captures
    stream = open_stream(good)
    reg = estimate_colour_registration(stream)
    assert not reg.applied and reg.reason, reg
    np.testing.assert_array_equal(load_frame(stream, 2)[0], load_frame(open_stream(good), 2)[0])


def test_resampling_follows_the_formula():
    """Linear interpolation reproduces a linear image exactly; on a random image it agrees with scipy's."""
    from scipy.ndimage import map_coordinates

    h, w = 30, 40
    K = np.array([[50.0, 0, 21.5], [0, 50.0, 14.0], [0, 0, 1]])
    reg = ColourRegistration(scale=0.9, shift=(1.25, -0.75), applied=True)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    ramp = np.stack([2 * x + 3 * y, x - y, 0.5 * x], -1)
    out = register_colour(ramp, reg, K)
    xs = 0.9 * (x + 0.5 - 21.5) + 21.5 + 1.25 - 0.5  # source array coordinates
    ys = 0.9 * (y + 0.5 - 14.0) + 14.0 - 0.75 - 0.5
    inside = (xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1)
    np.testing.assert_allclose(out[..., 0][inside], (2 * xs + 3 * ys)[inside], atol=1e-4)
    np.testing.assert_allclose(out[..., 1][inside], (xs - ys)[inside], atol=1e-4)
    img = np.random.default_rng(0).random((h, w, 3))
    ref = np.stack([map_coordinates(img[..., c], [ys, xs], order=1, mode="nearest") for c in range(3)], -1)
    np.testing.assert_allclose(register_colour(img, reg, K), ref, atol=1e-5)
    np.testing.assert_array_equal(register_colour(img, ColourRegistration(), K), img.astype(np.float32))


def test_outline_points_sit_between_the_pixels_of_a_depth_jump():
    d = np.ones((6, 8))
    d[:, 5:] = 2.0  # a vertical outline between columns 4 and 5
    d[0, 0] = 0.0  # invalid depth beside a valid one is no outline
    p = outline_points(d, np.random.default_rng(0))
    np.testing.assert_allclose(sorted(p[:, 0]), [5.0] * 6)
    np.testing.assert_allclose(sorted(p[:, 1]), np.arange(6) + 0.5)


def test_the_option_is_parsed_strictly():
    assert parse_registration("auto") is None
    assert not parse_registration("off").applied
    reg = parse_registration("0.9, 1.5,-2")
    assert reg.applied and reg.scale == 0.9 and reg.shift == (1.5, -2.0)
    for bad in ("zoom", "0.9,1", "0.1,0,0", "nan,0,0"):
        with pytest.raises(ValueError, match="--colour-registration"):
            parse_registration(bad)


def test_slam_measures_and_records_the_registration(captures, tmp_path, monkeypatch, capsys):
    import json

    from trisplat.commands.slam import main
    from trisplat.slam import warmup

    monkeypatch.setattr(warmup, "warm_up", lambda cfg, log=print: 0.0)
    _, bad = captures
    assert main([str(bad), "--out", str(tmp_path / "run"), "--slam.max-frames", "3", "--slam.mesh", "delaunay",
                 "--slam.final-iters", "2"]) == 0
    assert "colour and depth are not registered" in capsys.readouterr().out
    reg = json.loads((tmp_path / "run" / "metrics.json").read_text())["colour_registration"]
    assert reg["applied"] and abs(reg["scale"] - SCALE) < 0.005
    # a resume reads the frames as the saved run did, or refuses
    with pytest.raises(ValueError, match="--colour-registration"):
        main([str(bad), "--out", str(tmp_path / "run"), "--resume", "--colour-registration", "off",
              "--slam.max-frames", "4"])


def test_info_describes_a_slam_stream_and_its_colour(captures, capsys):
    from trisplat.cli import main as cli_main

    good, bad = captures
    assert cli_main(["info", str(bad)]) == 0
    out = capsys.readouterr().out
    assert "7scenes RGB-D stream" in out and "frames      5 (5 with a reference pose)" in out
    assert "colour and depth are not registered: the colour camera's focal length is 0.90" in out
    assert cli_main(["info", str(good)]) == 0
    assert "colour and depth line up" in capsys.readouterr().out
