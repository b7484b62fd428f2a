"""`trisplat slam --slam.start K`: a later stretch of a capture, tracked from its own first frame and scored against
those frames' reference poses; a start outside the capture is refused, and a resume may not change it (it numbers
the frames)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from trisplat.data.rgbd_stream import open_stream
from trisplat.slam.system import SlamConfig, run_slam
from trisplat.slam.track import TrackConfig
from trisplat.slam.trajectory import ate_rmse, read_tum_trajectory


def _cfg(**kw) -> SlamConfig:
    args = dict(downscale=2, final_iters=5, checkpoint_every=2, eval_every=2, mesh_resolution=64,
                track=TrackConfig(levels=(2, 1), max_iters=(40, 30)))
    return SlamConfig(**{**args, **kw})


def test_slam_runs_a_later_stretch(rgbd_capture, tmp_path):
    stream = open_stream(rgbd_capture)
    out = tmp_path / "run"
    m = run_slam(stream, out, _cfg(start=8, max_frames=5), log=lambda *a, **k: None)
    stamps, est = read_tum_trajectory(out / "trajectory.txt")
    assert stamps.tolist() == [8.0, 9.0, 10.0, 11.0, 12.0]  # capture frame numbers (no timestamps in the capture)
    assert np.allclose(est[0], np.eye(4))  # the stretch's first frame is its world
    ref = np.array([stream.frames[i].reference_c2w for i in range(8, 13)])
    rmse, _ = ate_rmse(est, ref)
    assert rmse < 0.01 and m["ate"]["rmse_m"] == pytest.approx(rmse) and m["frames"] == 5
    assert json.loads((out / "config.json").read_text())["start"] == 8
    with pytest.raises(ValueError, match=r"--resume continues the saved run and cannot change --slam.start"):
        run_slam(stream, out, _cfg(start=4, max_frames=5), resume=True, log=lambda *a, **k: None)


def test_slam_refuses_a_start_outside_the_capture(rgbd_capture, tmp_path):
    with pytest.raises(ValueError, match=r"--slam.start 14 is outside the capture's 14 frames \(0 to 13\)"):
        run_slam(open_stream(rgbd_capture), tmp_path / "run", _cfg(start=14), log=lambda *a, **k: None)
    with pytest.raises(ValueError, match=r"--slam.start -1 is outside"):
        run_slam(open_stream(rgbd_capture), tmp_path / "run2", _cfg(start=-1), log=lambda *a, **k: None)
