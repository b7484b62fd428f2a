"""Shared test fixtures: the location of ../shared/data and a skip-with-message when it is absent."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _choose_cuda_simulator() -> None:
    """Without a GPU torch can see, the CUDA backend's tests (tests/render/test_render_cuda.py) run its kernels
    through numba's CUDA simulator. numba reads NUMBA_ENABLE_CUDASIM when numba.cuda is first imported, so the choice
    is made here, before any test imports it (an explicit NUMBA_ENABLE_CUDASIM is left as it is)."""
    if "NUMBA_ENABLE_CUDASIM" in os.environ:
        return
    import torch

    if not torch.cuda.is_available():
        os.environ["NUMBA_ENABLE_CUDASIM"] = "1"
        if "numba" in sys.modules:
            from numba.core import config

            config.reload_config()


_choose_cuda_simulator()

DATA_DIR = Path(os.environ.get("TRISPLAT_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def shared_data(name: str) -> Path:
    """Path of ../shared/data/<name>; skips the test with a clear message when it is not there."""
    p = DATA_DIR / name
    if not p.exists():
        pytest.skip(f"shared test data {p} is absent (set TRISPLAT_SHARED_DATA or put ../shared/data beside the repo)")
    return p


@pytest.fixture
def data_dir():
    return shared_data("")


# Fixtures of the SfM tests (tests/sfm): one small synthetic capture, textured scene with known cameras along an arc,
# made once. They live here, not in tests/sfm/conftest.py: a second module named `conftest` would shadow this one for
# the test modules that import `shared_data` from it.
SFM_FRAMES = 16


@pytest.fixture(scope="session")
def synthetic_frames(tmp_path_factory):
    """(folder of SFM_FRAMES PNG photos 320x240, their Cameras): a 120-degree arc around textured boxes."""
    from tests.sfm.sfm_scene import path_cameras, render_frames, textured_scene

    folder = tmp_path_factory.mktemp("sfm_photos")
    cams = path_cameras(SFM_FRAMES)
    render_frames(textured_scene(), cams, folder)
    return folder, cams


@pytest.fixture(scope="session")
def synthetic_capture(synthetic_frames, tmp_path_factory):
    """`run_poses` on the synthetic photos: (report, capture folder)."""
    from trisplat.sfm import run_poses

    out = tmp_path_factory.mktemp("sfm_capture") / "capture"
    report = run_poses(synthetic_frames[0], out, progress=False, log=lambda m: None)
    return report, out


# Fixture of the SLAM tests (tests/slam): one RGB-D sequence ray-cast from a known mesh along a known path, made once.
@pytest.fixture(scope="session")
def rgbd_capture(tmp_path_factory):
    """Folder of a 14-frame 160x120 RGB-D sequence in the 7-Scenes layout (tests/slam/rgbd_scene.py)."""
    from tests.slam.rgbd_scene import write_rgbd_sequence

    return write_rgbd_sequence(tmp_path_factory.mktemp("synth_rgbd"))
