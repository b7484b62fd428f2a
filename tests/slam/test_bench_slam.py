"""`trisplat bench slam` on the SLAM tests' sequence ray-cast from a known mesh (the `rgbd_capture` fixture,
tests/slam/rgbd_scene.py; its first 10 frames at 1/2: 80x60): the table has both methods' ATE and the Chamfer
columns; without open3d the suite stops at once with an error naming `pip install open3d-cpu`."""
from __future__ import annotations

import json
import re
import sys

import numpy as np
import pytest

from tests.slam.rgbd_scene import H as FULL_H
from tests.slam.rgbd_scene import W as FULL_W
from tests.slam.rgbd_scene import path_w2c

DOWNSCALE, N = 2, 10
W, H = FULL_W // DOWNSCALE, FULL_H // DOWNSCALE
# tiny trisplat slam settings (passed through after `--`): two pyramid levels, a short final refinement
SLAM_EXTRA = ["--", "--slam.final-iters", "5", "--slam.checkpoint-every", "0", "--slam.eval-every", "2",
              "--slam.track.levels", "2", "1", "--slam.track.max-iters", "40", "30"]


def test_bench_slam_reports_both_methods(rgbd_capture, tmp_path):
    pytest.importorskip("open3d", reason="the SLAM benchmark's baseline needs open3d: pip install open3d-cpu")
    from trisplat.bench.slam import COLUMNS, main

    out = tmp_path / "bench"
    rc = main(["--capture", str(rgbd_capture), "--out", str(out), "--downscale", str(DOWNSCALE), "--max-frames",
               str(N), "--chamfer-samples", "4000", "--tsdf-voxel", "0.02",
               "--fps", "3",  # no timestamps: 10 frames over 3 s, so the RPE over 1 s has pairs
               "--open3d-slam-downscale", "1",  # Open3D's dense SLAM hangs below 160x120 (it refuses them now)
               *SLAM_EXTRA])
    assert rc == 0
    data = json.loads((out / "slam.json").read_text())
    assert data["columns"] == COLUMNS and "commit" in data["machine"] and "cores" in data["machine"]
    rows = {r[0]: dict(zip(COLUMNS, r)) for r in data["rows"]}
    assert set(rows) == {"trisplat", "open3d", "open3d-slam"}
    for name, r in rows.items():
        assert r["frames"] == N
        assert r["resolution"] == (f"{FULL_W}x{FULL_H}" if name == "open3d-slam" else f"{W}x{H}")
        assert r["ATE RMSE m"] is not None and 0 <= r["ATE RMSE m"] < 0.1, (name, r)  # a 0.2 m path
        assert r["wall s"] > 0 and r["frames/s"] > 0
        assert r["RPE m/s"] is not None and 0 <= r["RPE m/s"] < 0.2 and r["RPE deg/s"] is not None, (name, r)
        assert r["mesh faces"] > 0 and 0 < r["largest component"] <= 1
        assert r["Chamfer m"] is not None and 0 <= r["Chamfer m"] < 0.1, (name, r)
        assert r["load before"] is not None
    assert rows["trisplat"]["ATE RMSE m"] < 0.03  # ~1 cm: the noiseless sequence at 80x60
    assert rows["trisplat"]["held-out PSNR"] is not None and rows["trisplat"]["held-out depth L1 m"] < 0.05
    assert rows["open3d"]["held-out PSNR"] is None and rows["open3d-slam"]["held-out PSNR"] is None
    # both meshes scored as a viewer shows them at trisplat's held-out frames (the synthetic background is white and
    # what the meshes leave empty renders black, so the PSNRs are low); the same mesh at poses moved 30 cm scores
    # lower: the score sees the mesh where the photos are
    import shutil

    from trisplat.bench.slam import mesh_psnr
    from trisplat.data.rgbd_stream import open_stream
    from trisplat.slam.trajectory import read_tum_trajectory, write_tum_trajectory

    run = out / "slam_trisplat"
    frames = json.loads((run / "metrics.json").read_text())["held_out"]["frame_numbers"]
    stream = open_stream(rgbd_capture)
    good = mesh_psnr(run, stream, list(range(N)), frames, DOWNSCALE)
    assert good["frames"] == len(frames) >= 2 and good["psnr"] == pytest.approx(rows["trisplat"]["held-out PSNR of mesh.ply"])
    moved = tmp_path / "moved"
    moved.mkdir()
    shutil.copy(run / "mesh.ply", moved / "mesh.ply")
    stamps, est = read_tum_trajectory(run / "trajectory.txt")
    est[:, :3, 3] += [0.3, 0.0, 0.0]
    write_tum_trajectory(moved / "trajectory.txt", stamps, est)
    assert mesh_psnr(moved, stream, list(range(N)), frames, DOWNSCALE)["psnr"] < good["psnr"] - 0.5
    assert rows["open3d"]["held-out PSNR of mesh.ply"] is not None
    assert rows["open3d-slam"]["held-out PSNR of mesh.ply"] is not None
    # the file as it is, scored by the bench, is what the run scored without its exposures (8-bit colours in the file)
    saved = json.loads((run / "metrics.json").read_text())
    assert saved["held_out_mesh"]["psnr_without_exposure"] == pytest.approx(good["psnr"], abs=0.05)
    t = rows["trisplat"]
    assert t["held-out PSNR without exposure"] == pytest.approx(saved["held_out"]["psnr_without_exposure"])
    assert t["held-out PSNR of mesh.ply at the frames' exposure"] == pytest.approx(saved["held_out_mesh"]["psnr"])
    assert rows["open3d"]["held-out PSNR of mesh.ply at the frames' exposure"] is None
    # trisplat's own held-out scoring is inside its wall, reported apart; Open3D's wall has none
    assert 0 < rows["trisplat"]["scoring s"] < rows["trisplat"]["wall s"] and rows["open3d"]["scoring s"] == 0
    # so is its kernel warm-up (trisplat.slam.warmup), which a fresh install spends compiling
    assert 0 < rows["trisplat"]["compile s"] < rows["trisplat"]["wall s"] and rows["open3d"]["compile s"] == 0
    assert rows["trisplat"]["frames/s without scoring or compiling"] > rows["trisplat"]["frames/s"]
    assert rows["trisplat"]["compile s"] == pytest.approx(json.loads((run / "metrics.json").read_text())["compile_seconds"])
    md = (out / "slam.md").read_text()
    assert "| method |" in md and "Chamfer m" in md and "ATE RMSE m" in md and "| open3d |" in md
    details = json.loads((out / "slam_details.json").read_text())
    assert details["reference_tsdf_mesh"]["faces"] > 0 and details["trisplat_slam_extra_args"] == SLAM_EXTRA[1:]
    assert (out / "slam_trisplat" / "trajectory.txt").is_file() and (out / "slam_open3d" / "mesh.ply").is_file()
    assert (out / "slam_open3d-slam" / "mesh.ply").is_file() and "| open3d-slam |" in md


def test_bench_slam_scores_a_later_stretch(rgbd_capture, tmp_path):
    """--start: every method runs on the same later stretch (capture frames 6 to 11), scored against those frames'
    reference poses; an unknown method or a start outside the capture is refused before anything runs."""
    pytest.importorskip("open3d", reason="the SLAM benchmark's baselines need open3d: pip install open3d-cpu")
    from trisplat.bench.slam import main
    from trisplat.slam.trajectory import read_tum_trajectory

    out = tmp_path / "bench"
    rc = main(["--capture", str(rgbd_capture), "--out", str(out), "--downscale", str(DOWNSCALE), "--start", "6",
               "--max-frames", "6", "--chamfer-samples", "2000", "--tsdf-voxel", "0.02", "--methods", "open3d",
               "open3d-slam", "--open3d-slam-downscale", "1"])
    assert rc == 0
    data = json.loads((out / "slam.json").read_text())
    rows = {r[0]: dict(zip(data["columns"], r)) for r in data["rows"]}
    assert set(rows) == {"open3d", "open3d-slam"}
    assert rows["open3d-slam"]["resolution"] == f"{FULL_W}x{FULL_H}" and rows["open3d"]["resolution"] == f"{W}x{H}"
    for name in rows:
        stamps, _ = read_tum_trajectory(out / f"slam_{name}" / "trajectory.txt")
        assert stamps.tolist() == [6.0, 7.0, 8.0, 9.0, 10.0, 11.0]  # 7-Scenes has no timestamps: capture frame numbers
        assert rows[name]["ATE RMSE m"] < 0.03, rows[name]
    details = json.loads((out / "slam_details.json").read_text())
    assert details["start"] == 6 and details["frames"] == 6 and "capture frames 6 to 11" in data["notes"][0]
    with pytest.raises(ValueError, match="start frame 14 is outside the capture's 14 frames"):
        main(["--capture", str(rgbd_capture), "--out", str(tmp_path / "b2"), "--start", "14", "--methods", "open3d"])
    with pytest.raises(ValueError, match="--methods: \\['orb'\\]"):
        main(["--capture", str(rgbd_capture), "--out", str(tmp_path / "b3"), "--methods", "orb"])


def test_bench_slam_without_open3d_names_the_package(rgbd_capture, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "open3d", None)  # `import open3d` raises ImportError
    from trisplat.bench.slam import main
    from trisplat.slam import open3d_baseline

    rc = main(["--capture", str(rgbd_capture), "--out", str(tmp_path / "bench")])
    assert rc == 2
    assert "pip install open3d-cpu" in capsys.readouterr().err
    assert not (tmp_path / "bench" / "slam_trisplat").exists()  # stopped before the (long) trisplat run
    with pytest.raises(ImportError, match="pip install open3d-cpu"):
        open3d_baseline.run(rgbd_capture, tmp_path / "o3d")


def test_pose_alignment_recovers_a_rigid_motion():
    """The whole-pose alignment the benchmark moves meshes with (trisplat.sfm.align.align_poses)."""
    from scipy.spatial.transform import Rotation

    from trisplat.sfm.align import align_poses

    est = np.array([np.linalg.inv(w2c) for w2c in path_w2c()[:5]])  # a short, nearly straight path
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    G[:3, 3] = [1.0, -2.0, 0.5]
    R, t = align_poses(est, G @ est)
    assert np.allclose(R, G[:3, :3], atol=1e-9) and np.allclose(t, G[:3, 3], atol=1e-9)


def test_bench_command_runs_slam_by_name_only(monkeypatch, capsys):
    import types

    from trisplat.commands import bench

    assert "slam" in bench.LONG_SUITES and "slam" not in bench.SUITES  # `all` (tens of minutes more) skips it
    calls = []
    fake = types.ModuleType("trisplat.bench.slam")
    fake.main = lambda argv: calls.append(list(argv)) or 0
    monkeypatch.setitem(sys.modules, "trisplat.bench.slam", fake)
    assert bench.main(["slam", "--max-frames", "3"]) == 0 and calls == [["--max-frames", "3"]]
    assert bench.main([]) == 0
    usage = capsys.readouterr().out
    assert "  slam " in usage and re.search(r"except [a-z, ]*slam", usage)
