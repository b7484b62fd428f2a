"""The synthetic RGB-D room (trisplat.synth.rgbd_room): the written frames agree with the true mesh and poses through
the SLAM's own reader, the walk is small-stepped and closed, the sensor model is what it says, bad arguments fail."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
from PIL import Image

from trisplat.data.rgbd_stream import load_frame, open_stream
from trisplat.synth.orbit import intrinsics
from trisplat.synth.rgbd_room import SensorModel, room_walk_c2w, write_rgbd_room

N, W, H = 24, 80, 60


@pytest.fixture(scope="module")
def exact_room(tmp_path_factory):
    root = tmp_path_factory.mktemp("rgbd_room_exact")
    return root, write_rgbd_room(root, n_frames=N, width=W, height=H, sensor=False, color_samples=1, seed=3)


@pytest.fixture(scope="module")
def noisy_room(tmp_path_factory):
    root = tmp_path_factory.mktemp("rgbd_room_noisy")
    return root, write_rgbd_room(root, n_frames=N, width=W, height=H, sensor=True, color_samples=1, seed=3)


def _depth_mm(root, k):
    return np.asarray(Image.open(root / f"frame-{k:06d}.depth.png")).astype(np.int64)


def _rot_deg(Ra, Rb):
    return math.degrees(math.acos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1)))


def test_reader_gives_back_the_poses_and_intrinsics(exact_room):
    root, info = exact_room
    s = open_stream(root)
    assert s.format == "7scenes" and len(s) == N and (s.width, s.height) == (W, H)
    np.testing.assert_allclose(s.K, intrinsics(W, H, 60.0), atol=1e-9)  # the file's -0.5 undone by the reader
    for f, c2w in zip(s.frames, room_walk_c2w(N, seed=3)):
        np.testing.assert_allclose(f.reference_c2w, c2w, atol=1e-12)
    assert json.loads((root / "synth.json").read_text())["n_frames"] == N == info.n_frames


def test_depth_back_projects_onto_the_true_mesh(exact_room):
    """Depth read by the SLAM's loader, lifted with the written K and pose, lies on gt_mesh.ply within the
    millimetre quantisation; a principal point off by half a pixel would miss by centimetres at depth edges."""
    root, _ = exact_room
    s = open_stream(root)
    mesh = trimesh.load(root / "gt_mesh.ply", process=False)
    rng = np.random.default_rng(0)
    Kinv = np.linalg.inv(s.K)
    for k in (0, N // 2, N - 1):
        _, depth = load_frame(s, k)
        assert (depth > 0).all()  # no sensor model: every pixel measured
        v, u = np.nonzero(depth > 0)
        pick = rng.choice(len(u), 600, replace=False)
        u, v = u[pick], v[pick]
        rays = np.stack([u + 0.5, v + 0.5, np.ones(len(u))], 1) @ Kinv.T
        cam = rays * depth[v, u][:, None]
        c2w = s.frames[k].reference_c2w
        world = cam @ c2w[:3, :3].T + c2w[:3, 3]
        _, dist, _ = trimesh.proximity.closest_point(mesh, world)
        assert dist.max() < 1.5e-3, (k, dist.max())


def test_walk_takes_small_steps_and_closes():
    for n, step_cm in ((300, (2.5, 3.7)), (40, (19.0, 28.0))):
        c2w = room_walk_c2w(n, seed=1)
        c = np.array([m[:3, 3] for m in c2w])
        steps = np.linalg.norm(np.diff(np.concatenate([c, c[:1]]), axis=0), axis=1)  # closing step included
        assert step_cm[0] < 100 * steps.mean() < step_cm[1]
        assert steps.max() < 1.4 * steps.mean() and steps.min() > 0.6 * steps.mean()  # smooth, evenly timed
        rots = [_rot_deg(c2w[k][:3, :3], c2w[(k + 1) % n][:3, :3]) for k in range(n)]
        if n == 300:  # a hand-held camera at 30 frames/s: about a degree a frame
            assert 0.8 < np.mean(rots) < 1.8 and max(rots) < 3.0
        # closed: the last frame is one ordinary step from the first
        assert np.linalg.norm(c[-1] - c[0]) < 1.4 * steps[:-1].mean()
        assert rots[-1] < 1.5 * np.mean(rots[:-1]) + 1e-9
        # inside the room, at eye height, upright (image y points down the world z; pitch <= 26 deg, roll <= 3)
        assert np.abs(c[:, :2]).max() < 1.9 and np.all(np.abs(c[:, 2] - 1.4) < 0.1)
        assert all(m[2, 1] < -0.85 for m in c2w)
        for m in c2w:
            R = m[:3, :3]
            np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
            assert np.isclose(np.linalg.det(R), 1.0)


def test_no_surface_closer_than_half_a_metre(exact_room):
    root, _ = exact_room
    assert min(_depth_mm(root, k).min() for k in range(N)) > 500


def test_sensor_model_noise_and_dropouts(exact_room, noisy_room):
    (er, _), (nr, info) = exact_room, noisy_room
    model = SensorModel()
    assert info.sensor and info.sensor_model["depth_sigma"] == model.depth_sigma
    resid, far_dropped, far = [], 0, 0
    for k in range(N):
        exact, noisy = _depth_mm(er, k), _depth_mm(nr, k)
        ok = noisy > 0
        z = exact[ok] / 1000.0
        resid.append((noisy[ok] - exact[ok]) / 1000.0 / (z * z))  # noise in units of z^2
        beyond = exact > 1000 * model.max_depth + 1
        far += beyond.sum()
        far_dropped += (noisy[beyond] == 0).sum()
    r = np.concatenate(resid)
    assert far > 0 and far_dropped == far  # nothing measured beyond 4 m
    assert abs(np.median(r)) < 2e-4
    assert 0.8 * model.depth_sigma < r.std() < 1.25 * model.depth_sigma  # sigma = 1.5 mm * z^2 (mm rounding included)
    assert 0.0 < info.missing_depth_fraction < 0.5
    c_exact = np.asarray(Image.open(er / "frame-000000.color.png")).astype(float)
    c_noisy = np.asarray(Image.open(nr / "frame-000000.color.png")).astype(float)
    assert 1.5 < (c_noisy - c_exact).std() < 4.0  # sigma 0.01 = 2.55 levels


def test_noise_free_depth_is_exact_and_runs_repeat(exact_room, tmp_path):
    """sensor=False: depth equals the true view depth rounded to the millimetre (re-cast here); the same seed gives
    the same bytes, also with two worker processes."""
    from trisplat.cameras import Camera
    from trisplat.synth.raycast import raycast_view
    from trisplat.synth.rgbd_room import rgbd_room_mesh

    root, _ = exact_room
    k = 5
    c2w = room_walk_c2w(N, seed=3)[k]
    v = raycast_view(rgbd_room_mesh(3), Camera(np.linalg.inv(c2w), intrinsics(W, H, 60.0), W, H))
    np.testing.assert_array_equal(_depth_mm(root, k), np.round(v.depth.astype(np.float64) * 1000))
    again = write_rgbd_room(tmp_path / "again", n_frames=N, width=W, height=H, sensor=False, color_samples=1, seed=3,
                            workers=2)
    assert again.workers == 2
    for k in (0, N - 1):
        for kind in ("depth", "color"):
            name = f"frame-{k:06d}.{kind}.png"
            np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "again" / name)),
                                          np.asarray(Image.open(root / name)))


@pytest.mark.parametrize("kwargs, match", [
    ({"n_frames": 1}, "n_frames"),
    ({"n_frames": 2.5}, "n_frames"),
    ({"width": 0}, "width"),
    ({"height": -4}, "height"),
    ({"fov_deg": 0.0}, "fov_deg"),
    ({"color_samples": 0}, "color_samples"),
    ({"workers": 0}, "workers"),
])
def test_bad_arguments_are_named(tmp_path, kwargs, match):
    args = {"n_frames": 4, "width": 16, "height": 12} | kwargs
    with pytest.raises(ValueError, match=match):
        write_rgbd_room(tmp_path / "x", **args)
    assert not any((tmp_path / "x").glob("frame-*"))


def test_refuses_to_overwrite_another_capture(tmp_path):
    (tmp_path / "frame-000000.color.png").write_bytes(b"real data")
    with pytest.raises(FileExistsError, match="not an rgbd-room capture"):
        write_rgbd_room(tmp_path, n_frames=3, width=16, height=12)
    assert (tmp_path / "frame-000000.color.png").read_bytes() == b"real data"


def test_cli_writes_the_capture(tmp_path, capsys):
    from trisplat.synth.__main__ import main

    out = tmp_path / "cli"
    assert main(["rgbd-room", str(out), "--frames", "5", "--width", "32", "--height", "24", "--workers", "1"]) == 0
    assert "5 frames" in capsys.readouterr().out
    assert len(open_stream(out)) == 5
    # a second, shorter run replaces the first one's frames
    assert main(["rgbd-room", str(out), "--frames", "3", "--width", "32", "--height", "24", "--workers", "1",
                 "--no-sensor"]) == 0
    assert len(open_stream(out)) == 3
