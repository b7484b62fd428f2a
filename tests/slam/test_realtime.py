"""--slam.realtime: frames that arrive while the previous is still processed are tracked in a hurry, frames whose
successor has already arrived are dropped, and the run says how many."""
from __future__ import annotations

import numpy as np

from trisplat.data.rgbd_stream import open_stream
from trisplat.slam.system import SlamConfig, run_slam
from trisplat.slam.track import TrackConfig
from trisplat.slam.trajectory import read_tum_trajectory
from tests.slam.rgbd_scene import N


def _cfg(**kw) -> SlamConfig:
    args = dict(downscale=1, final_iters=0, checkpoint_every=0, eval_every=3, mesh="delaunay", max_frames=8,
                track=TrackConfig(levels=(2, 1), max_iters=(60, 40)))
    return SlamConfig(**{**args, **kw})


def test_realtime_drops_frames_it_cannot_keep_up_with(rgbd_capture, tmp_path):
    stream = open_stream(rgbd_capture)
    assert len(stream) == N
    lines: list[str] = []
    # a stream far faster than this machine: after the first frame nearly every frame is late by more than one
    m = run_slam(stream, tmp_path / "fast", _cfg(realtime=True, input_fps=1000.0),
                 log=lambda *a, **k: lines.append(" ".join(map(str, a))))
    rt = m["realtime"]
    assert rt["input_fps"] == 1000.0 and rt["dropped_frames"] >= 5 and rt["dropped_frames"] == len(rt["dropped"])
    assert any(line.startswith(f"realtime at 1000 frames/s: dropped {rt['dropped_frames']} of 8 frames")
               for line in lines), lines
    _, est = read_tum_trajectory(tmp_path / "fast" / "trajectory.txt")
    assert len(est) == 8 and np.isfinite(est).all()  # a dropped frame still has a pose (the motion guess)
    # a slow stream: nothing dropped or hurried
    m = run_slam(stream, tmp_path / "slow", _cfg(realtime=True, input_fps=0.001), log=lambda *a, **k: None)
    assert m["realtime"] == {"input_fps": 0.001, "dropped_frames": 0, "dropped": [], "hurried_frames": 0}
    assert run_slam(stream, tmp_path / "off", _cfg(), log=lambda *a, **k: None)["realtime"] is None
