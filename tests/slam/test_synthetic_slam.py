"""End to end: `trisplat slam` on a sequence ray-cast from a known mesh along a known path (the `rgbd_capture`
fixture, tests/slam/rgbd_scene.py); the recovered trajectory must match the path; the run rules of training (no
overwrite without --force, resume refuses settings that re-index the frames), a run killed mid-way resumes to what
the uninterrupted run gives, a frame tracked from a far-off guess is re-localised or skipped, and a meshing failure
after the final refinement does not make --resume refine again."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trisplat.data.rgbd_stream import open_stream
from trisplat.slam import system
from trisplat.slam.system import SlamConfig, run_slam
from trisplat.slam.track import TrackConfig
from trisplat.slam.trajectory import ate_rmse, read_tum_trajectory
from tests.slam.rgbd_scene import N


def _cfg(**kw) -> SlamConfig:
    args = dict(downscale=1, final_iters=10, checkpoint_every=0, eval_every=3, mesh_resolution=128,
                track=TrackConfig(levels=(2, 1), max_iters=(60, 40)))
    return SlamConfig(**{**args, **kw})


def _quiet(*a, **k):
    pass


@pytest.fixture(scope="module")
def full_run(rgbd_capture, tmp_path_factory):
    """The whole sequence in one uninterrupted run: (run folder, metrics, log lines)."""
    out = tmp_path_factory.mktemp("slam_full") / "run"
    lines: list[str] = []
    m = run_slam(open_stream(rgbd_capture), out, _cfg(), log=lambda *a, **k: lines.append(" ".join(map(str, a))))
    return out, m, lines


def test_slam_recovers_the_known_path(rgbd_capture, full_run):
    stream = open_stream(rgbd_capture)
    assert stream.format == "7scenes" and len(stream) == N
    out, m, lines = full_run
    stamps, est = read_tum_trajectory(out / "trajectory.txt")
    assert len(est) == N and np.array_equal(stamps, np.arange(N, dtype=float))  # no timestamps: frame index
    ref = np.array([f.reference_c2w for f in stream.frames])
    rmse, _ = ate_rmse(est, ref)
    path_len = float(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1).sum())
    assert path_len > 0.25
    assert rmse < 0.003, f"ATE {rmse:.4f} m over a {path_len:.2f} m path"
    # relative motion: the first-to-last displacement is recovered (same frame-0 origin, so compare lengths)
    d_est = np.linalg.norm(est[-1, :3, 3] - est[0, :3, 3])
    d_ref = np.linalg.norm(ref[-1, :3, 3] - ref[0, :3, 3])
    assert abs(d_est - d_ref) < 0.005
    assert m["ate"]["rmse_m"] == pytest.approx(rmse) and "alignment" in m["ate"]
    assert (out / "model.ply").is_file() and (out / "mesh.ply").is_file()
    assert m["mesh"]["faces"] > 100 and m["triangles"] > 100 and m["lost_frames"] == []
    saved = json.loads((out / "metrics.json").read_text())
    # held-out frames: the map renders the geometry at the tracked poses (PSNR is low here: the synthetic
    # background is white, the map has nothing there and renders black)
    # 2 cm at ~2.3 m; a misplaced map is off by decimetres
    assert saved["frames"] == N and saved["held_out"]["frames"] >= 2 and saved["held_out"]["depth_l1_m"] < 0.02
    assert any(line.startswith(f"frame {N}/{N}") and "fps" in line and "triangles" in line for line in lines)
    assert not any("tracking lost" in line for line in lines)
    assert json.loads((out / "state.json").read_text())["finished"] is True


def test_slam_mesh_is_one_surface_on_the_true_one(rgbd_capture, tmp_path):
    """mesh.ply is the map fused into one connected surface (not the map's triangles, not Delaunay pieces) and it
    lies on the mesh the frames were ray-cast from (brought into the SLAM frame by the first reference pose)."""
    import trimesh

    from trisplat.synth.scenes import demo_mesh

    stream = open_stream(rgbd_capture)
    out = tmp_path / "run"
    m = run_slam(stream, out, _cfg(max_frames=6), log=_quiet)
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert m["mesh"]["method"].startswith("the map's depth") and len(mesh.faces) == m["mesh"]["faces"]
    from trisplat.io.gltf import read_glb

    glb = read_glb(out / "mesh.glb")  # the same surface for engines: Y-up (so the extents move), linear colours
    assert sum(len(p.faces) for p in glb.primitives) == len(mesh.faces)
    assert sorted(np.ptp(glb.primitives[0].positions, axis=0).round(4)) == sorted(np.ptp(mesh.vertices, axis=0).round(4))
    assert glb.primitives[0].material.unlit
    from trisplat.io.colour import srgb_to_linear

    ply_linear = srgb_to_linear(np.asarray(mesh.visual.vertex_colors, np.float64)[:, :3] / 255.0)
    np.testing.assert_allclose(np.sort(glb.primitives[0].color[:, :3].ravel()), np.sort(ply_linear.ravel()), atol=3e-3)
    assert m["mesh"]["largest_component_fraction"] >= 0.9
    assert len(mesh.vertices) / len(mesh.faces) < 0.6  # welded: a soup has 3 vertices per face
    _, est = read_tum_trajectory(out / "trajectory.txt")
    to_world = stream.frames[0].reference_c2w @ np.linalg.inv(est[0])
    v = mesh.vertices @ to_world[:3, :3].T + to_world[:3, 3]
    _, dist, _ = trimesh.proximity.closest_point(demo_mesh(seed=0), v[:: max(1, len(v) // 3000)])
    # metres, seen from ~2.3 m on a 128-voxel grid (~2 cm voxels); a mesh in the wrong frame is off by decimetres.
    # The tail is the edges of what the frames saw (shadows behind the objects, the disc's rim), ~2 voxels thick.
    assert np.median(dist) < 0.012 and np.percentile(dist, 75) < 0.05
    # the Delaunay mesh is still there as an option
    m2 = run_slam(stream, tmp_path / "run2", _cfg(max_frames=6, mesh="delaunay"), log=_quiet)
    assert m2["mesh"]["method"].startswith("restricted Delaunay")


class Killed(Exception):
    """Stands for the process being killed in the middle of a frame."""


def test_slam_killed_mid_way_resumes_to_the_uninterrupted_result(rgbd_capture, full_run, tmp_path, monkeypatch):
    """Checkpoints every 4 frames; the run dies while loading frame 11 (10 frames done, last checkpoint at 8).
    --resume redoes frames 9.. from the checkpoint, the random generator included, and ends where the uninterrupted
    run ended: same trajectory, same map size."""
    stream = open_stream(rgbd_capture)
    out = tmp_path / "run"
    real = system.load_frame

    def dies_at_frame_10(stream, i, downscale):
        if i == 10:
            raise Killed
        return real(stream, i, downscale)

    monkeypatch.setattr(system, "load_frame", dies_at_frame_10)
    with pytest.raises(Killed):
        run_slam(stream, out, _cfg(checkpoint_every=4), log=_quiet)
    monkeypatch.setattr(system, "load_frame", real)
    assert json.loads((out / "state.json").read_text()) == {"finished": False, "step": 8, "total_steps": N,
                                                            "refined": False}
    assert not (out / "trajectory.txt").exists()
    lines: list[str] = []
    m = run_slam(stream, out, _cfg(checkpoint_every=4), resume=True,
                 log=lambda *a, **k: lines.append(" ".join(map(str, a))))
    assert any("resumed from" in line and "8 frames done" in line for line in lines)
    assert not any(line.startswith("frame 8/") for line in lines)  # frames 1..8 are not tracked again
    full_out, full_m, _ = full_run
    _, est = read_tum_trajectory(out / "trajectory.txt")
    _, ref = read_tum_trajectory(full_out / "trajectory.txt")
    assert len(est) == N
    np.testing.assert_allclose(est[:, :3, 3], ref[:, :3, 3], atol=1e-5)
    np.testing.assert_allclose(est[:, :3, :3], ref[:, :3, :3], atol=1e-5)
    assert m["keyframes"] == full_m["keyframes"] and m["triangles"] == full_m["triangles"]
    assert m["ate"]["rmse_m"] == pytest.approx(full_m["ate"]["rmse_m"], abs=1e-5)


def test_slam_refuses_a_non_empty_out_and_a_resume_that_re_indexes_the_frames(rgbd_capture, tmp_path, capsys):
    from trisplat.cli import main

    out = tmp_path / "run"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    base = ["slam", str(rgbd_capture), "--out", str(out), "--slam.downscale", "2", "--slam.max-frames", "3",
            "--slam.final-iters", "0", "--slam.mesh", "delaunay"]
    assert main(base) == 1
    err = capsys.readouterr().err
    assert str(out) in err and "--force" in err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]  # nothing written
    assert main([*base, "--force"]) == 0  # the old contents are moved aside, never deleted
    backups = list(tmp_path.glob("run.old-*"))
    assert len(backups) == 1 and (backups[0] / "notes.txt").read_text() == "mine"
    assert (out / "trajectory.txt").is_file() and json.loads((out / "config.json").read_text())["stride"] == 1
    assert main(base) == 1 and "a finished run" in capsys.readouterr().err
    config = (out / "config.json").read_text()
    for option, value in (("--slam.stride", "2"), ("--slam.downscale", "1")):
        argv = [*base, "--resume"]
        if option in argv:
            argv[argv.index(option) + 1] = value
        else:
            argv += [option, value]
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert option in err and "cannot change" in err, err
        assert (out / "config.json").read_text() == config  # refused before anything changed
    with pytest.raises(ValueError, match="--depth-scale"):
        run_slam(open_stream(rgbd_capture, depth_scale=0.002), out, _cfg(downscale=2, max_frames=3), resume=True)


def _far_off(w2c: np.ndarray) -> np.ndarray:
    """The guess moved 0.3 m and turned 20 degrees: far outside the tracker's basin."""
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec(np.radians(20) * np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
                                     ).as_matrix()
    G[:3, 3] = [0.2, -0.15, 0.15]
    return G @ w2c


def _wrong_guess_at(monkeypatch, frame: int, every_try: bool) -> list[int]:
    """Wrap the tracker so that frame `frame` (number in the run) starts from a far-off guess: its first attempt
    only, or every attempt (then re-localisation cannot succeed either). Returns the list of frames tracked."""
    real = system.track_frame
    seen: list[int] = []
    last = {"pyramid": None, "frame": 0}

    def tracker(positions, faces, colors, opacities, sigma, pyramid, w2c_init, cfg):
        first = pyramid is not last["pyramid"]
        if first:  # a new frame (each frame's pyramid is built once)
            last["pyramid"], last["frame"] = pyramid, last["frame"] + 1
            seen.append(last["frame"])
        if last["frame"] == frame and (first or every_try):
            w2c_init = _far_off(np.asarray(w2c_init))
        return real(positions, faces, colors, opacities, sigma, pyramid, w2c_init, cfg)

    monkeypatch.setattr(system, "track_frame", tracker)
    return seen


def test_slam_relocalises_a_frame_tracked_from_a_far_off_guess(rgbd_capture, tmp_path, monkeypatch):
    stream = open_stream(rgbd_capture)
    seen = _wrong_guess_at(monkeypatch, 5, every_try=False)
    lines: list[str] = []
    m = run_slam(stream, tmp_path / "run", _cfg(max_frames=8, final_iters=0), log=lambda *a, **k:
                 lines.append(" ".join(map(str, a))))
    assert seen == list(range(1, 8))
    assert any(line.startswith("frame 6/8 (capture frame 5): tracking lost") for line in lines), lines
    assert any(line.startswith("frame 6/8 (capture frame 5): re-localised") for line in lines), lines
    _, est = read_tum_trajectory(tmp_path / "run" / "trajectory.txt")
    rmse, err = ate_rmse(est, np.array([f.reference_c2w for f in stream.frames[:8]]))
    assert err[5] < 0.005 and rmse < 0.003, err
    assert m["lost_frames"] == []


def test_slam_skips_a_frame_that_cannot_be_relocalised(rgbd_capture, tmp_path, monkeypatch):
    """Every attempt at frame 5 starts far off: it is skipped with a message (no keyframe, no map from it, its pose
    not the next frame's guess) and the frames after it are tracked from the last good pose."""
    stream = open_stream(rgbd_capture)
    _wrong_guess_at(monkeypatch, 5, every_try=True)
    spawned: list[np.ndarray] = []
    real_spawn = system.spawn
    monkeypatch.setattr(system, "spawn", lambda smap, rgb, depth, c2w, *a: spawned.append(c2w) or
                        real_spawn(smap, rgb, depth, c2w, *a))
    lines: list[str] = []
    m = run_slam(stream, tmp_path / "run", _cfg(max_frames=8, final_iters=0, keyframe_every=1),
                 log=lambda *a, **k: lines.append(" ".join(map(str, a))))
    assert any(line.startswith("frame 6/8 (capture frame 5): re-localisation failed") and "skipped" in line
               for line in lines), lines
    assert m["lost_frames"] == [5] and m["keyframes"] == 7  # every frame a keyframe (keyframe_every 1) but frame 5
    ref = np.array([f.reference_c2w for f in stream.frames[:8]])
    _, est = read_tum_trajectory(tmp_path / "run" / "trajectory.txt")
    good = [k for k in range(8) if k != 5]
    rmse, err = ate_rmse(est[good], ref[good])
    assert rmse < 0.003, err
    R, t = _rigid(est[good], ref[good])
    assert np.linalg.norm(est[5, :3, 3] @ R.T + t - ref[5, :3, 3]) > 0.05  # its pose was indeed wrong ...
    assert len(spawned) == 7 and not any(np.allclose(c, est[5]) for c in spawned)  # ... and made no map


def _rigid(est, ref):
    from trisplat.sfm.align import umeyama

    _, R, t = umeyama(est[:, :3, 3], ref[:, :3, 3], scale=False)
    return R, t


def test_slam_meshing_failure_then_resume_does_not_refine_twice(rgbd_capture, tmp_path, monkeypatch):
    stream = open_stream(rgbd_capture)
    out = tmp_path / "run"
    cfg = _cfg(max_frames=3, final_iters=5)
    finals: list[int] = []
    real_refine = system.refine

    def counting(*a, sigma_end=None, **k):
        if sigma_end is not None:
            finals.append(1)
        return real_refine(*a, sigma_end=sigma_end, **k)

    def mesh_fails(*a, **k):
        raise MemoryError("meshing ran out of memory")

    monkeypatch.setattr(system, "refine", counting)
    monkeypatch.setattr(system, "map_surface", mesh_fails)
    with pytest.raises(MemoryError):
        run_slam(stream, out, cfg, log=_quiet)
    assert len(finals) == 1 and not (out / "metrics.json").exists()
    monkeypatch.undo()
    monkeypatch.setattr(system, "refine", counting)
    lines: list[str] = []
    m = run_slam(stream, out, cfg, resume=True, log=lambda *a, **k: lines.append(" ".join(map(str, a))))
    assert len(finals) == 1, "the final refinement ran again on --resume"
    assert any("final refinement: already done" in line for line in lines)
    assert m["frames"] == 3 and (out / "mesh.ply").is_file() and m["mesh"]["faces"] > 0
