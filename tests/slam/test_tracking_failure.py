"""Tracking failure: a sudden 30 cm jump of the camera, and black frames (a sensor dropout: black picture, no
depth; or a black picture with depth), in the synthetic sequence of tests/slam/rgbd_scene.py. Each is detected
(the log says so) and recovered from: the jump is re-localised by SIFT matches with depth against the keyframes,
the dropout frames are skipped, and every other frame's pose stays on the reference."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from tests.slam.rgbd_scene import N, path_w2c, write_rgbd_sequence
from trisplat.data.rgbd_stream import open_stream
from trisplat.slam.system import SlamConfig, run_slam
from trisplat.slam.track import TrackConfig
from trisplat.slam.trajectory import ate_rmse, read_tum_trajectory

JUMP_AT = 7


def _cfg(**kw) -> SlamConfig:
    args = dict(downscale=1, final_iters=0, checkpoint_every=0, eval_every=3, mesh="delaunay",
                track=TrackConfig(levels=(2, 1), max_iters=(60, 40)))
    return SlamConfig(**{**args, **kw})


def _run(root, out):
    lines: list[str] = []
    m = run_slam(open_stream(root), out, _cfg(), log=lambda *a, **k: lines.append(" ".join(map(str, a))))
    _, est = read_tum_trajectory(out / "trajectory.txt")
    return m, est, lines


@pytest.fixture(scope="module")
def jump_capture(tmp_path_factory):
    """The test path, but from frame JUMP_AT on the camera is 30 cm to the side (along its own x axis)."""
    path = path_w2c(N)
    shift = np.eye(4)
    shift[:3, 3] = [-0.3, 0.0, 0.0]  # w2c' = shift w2c: the camera centre moves +0.3 m along its x axis
    path = [w if k < JUMP_AT else shift @ w for k, w in enumerate(path)]
    return write_rgbd_sequence(tmp_path_factory.mktemp("synth_jump"), path=path)


def test_a_sudden_30cm_jump_is_detected_and_relocalised(jump_capture, tmp_path):
    stream = open_stream(jump_capture)
    ref = np.array([f.reference_c2w for f in stream.frames])
    assert abs(np.linalg.norm(ref[JUMP_AT, :3, 3] - ref[JUMP_AT - 1, :3, 3]) - 0.3) < 0.03
    m, est, lines = _run(jump_capture, tmp_path / "run")
    label = f"frame {JUMP_AT + 1}/{N} (capture frame {JUMP_AT})"
    assert any(line.startswith(f"{label}: tracking lost") for line in lines), lines
    assert any(line.startswith(f"{label}: re-localised") for line in lines), lines
    assert m["lost_frames"] == []
    rmse, err = ate_rmse(est, ref)
    assert rmse < 0.005 and err.max() < 0.01, err


@pytest.fixture(scope="module")
def dropout_capture(tmp_path_factory):
    """The test sequence with frames 5 and 6 black without depth (a dropout) and frame 10 black with its depth."""
    root = write_rgbd_sequence(tmp_path_factory.mktemp("synth_black"))
    for k in (5, 6, 10):
        Image.fromarray(np.zeros((120, 160, 3), np.uint8)).save(root / f"frame-{k:06d}.color.png")
    for k in (5, 6):
        Image.fromarray(np.zeros((120, 160), np.uint16)).save(root / f"frame-{k:06d}.depth.png")
    return root


def test_black_frames_are_detected_and_skipped(dropout_capture, tmp_path):
    stream = open_stream(dropout_capture)
    ref = np.array([f.reference_c2w for f in stream.frames])
    m, est, lines = _run(dropout_capture, tmp_path / "run")
    for k in (5, 6):
        label = f"frame {k + 1}/{N} (capture frame {k})"
        assert any(line.startswith(f"{label}: re-localisation failed") and "skipped" in line for line in lines), lines
    assert m["lost_frames"] == [5, 6]
    assert any(line.startswith(f"frame 11/{N} (capture frame 10): flat picture") for line in lines), lines
    good = [k for k in range(N) if k not in (5, 6)]
    rmse, err = ate_rmse(est[good], ref[good])
    assert rmse < 0.005 and err.max() < 0.01, err  # frame 10 included: tracked on its depth alone
    from trisplat.slam.system import load_checkpoint

    st, _ = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert not {5, 6, 10} & set(st.keyframe_ids)
