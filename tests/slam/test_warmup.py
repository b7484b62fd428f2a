"""The kernel warm-up before a SLAM run (trisplat.slam.warmup): it runs every stage of `run_slam` on a tiny synthetic
capture, never fails the user's run, and its seconds are reported apart from the run's frames/s."""
from __future__ import annotations

import json
import time

import numpy as np

import trisplat.slam.system as system
import trisplat.slam.warmup as warmup
from trisplat.data.rgbd_stream import open_stream
from trisplat.slam.system import SlamConfig


def test_warm_up_runs_every_stage_of_a_slam_run(monkeypatch, tmp_path):
    stages: list[str] = []
    real = {name: getattr(system, name) for name in ("track_with_relocalisation", "refine", "write_outputs")}
    for name, fn in real.items():
        def spy(*a, _name=name, _fn=fn, **k):
            stages.append(_name)
            return _fn(*a, **k)
        monkeypatch.setattr(system, name, spy)
    said: list[str] = []
    seconds = warmup.warm_up(SlamConfig(), log=lambda *a, **k: said.append(" ".join(map(str, a))))
    assert not said, said  # no warning: the tiny run went through
    assert seconds > 0
    assert {"track_with_relocalisation", "refine", "write_outputs"} <= set(stages)
    assert stages.count("track_with_relocalisation") == warmup.FRAMES - 1  # every frame after the first tracked


def test_warm_up_ignores_the_runs_start_frame():
    """--slam.start names a frame of the user's capture, not of the warm-up's 8 frames: the warm-up starts at 0."""
    said: list[str] = []
    warmup.warm_up(SlamConfig(start=200, max_frames=50), log=lambda *a, **k: said.append(" ".join(map(str, a))))
    assert not said, said


def test_warm_up_capture_is_a_valid_capture_with_poses(tmp_path):
    root = warmup.write_capture(tmp_path / "cap")
    s = open_stream(root)
    assert len(s) == warmup.FRAMES and (s.width, s.height) == (warmup.WIDTH, warmup.HEIGHT)
    first, last = s.frames[0].reference_c2w, s.frames[-1].reference_c2w
    assert np.allclose(first, last, atol=1e-6)  # out and back: a revisit for loop detection
    assert np.linalg.norm(s.frames[warmup.FRAMES // 2].reference_c2w[:3, 3] - first[:3, 3]) > 0.2


def test_a_failing_warm_up_does_not_fail_the_run(monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("no kernels today")

    monkeypatch.setattr(system, "run_slam", boom)
    said: list[str] = []
    seconds = warmup.warm_up(SlamConfig(), log=lambda *a, **k: said.append(" ".join(map(str, a))))
    assert seconds >= 0 and len(said) == 1
    assert "warm-up failed (RuntimeError: no kernels today)" in said[0] and "frames/s" in said[0]


def test_slam_command_reports_compile_seconds_apart_from_its_frames_per_second(monkeypatch, rgbd_capture, tmp_path):
    from trisplat.commands.slam import main

    def slow_warm_up(cfg, log=print):
        time.sleep(1.5)
        return 1.5

    monkeypatch.setattr(warmup, "warm_up", slow_warm_up)
    t0 = time.perf_counter()
    assert main([str(rgbd_capture), "--out", str(tmp_path / "run"), "--slam.max-frames", "4", "--slam.mesh",
                 "delaunay", "--slam.final-iters", "2"]) == 0
    total = time.perf_counter() - t0
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["compile_seconds"] == 1.5
    assert m["slam_seconds"] < total - 1.5  # the warm-up is not in the run's own clock
    assert m["fps"] == 4 / m["slam_seconds"]
