"""Fixtures of the SfM tests: one small synthetic capture (textured scene, known cameras along an arc), made once."""
from __future__ import annotations

import pytest
from sfm_scene import path_cameras, render_frames, textured_scene

N_FRAMES = 16


@pytest.fixture(scope="session")
def synthetic_frames(tmp_path_factory):
    """(folder of N_FRAMES PNG photos 320x240, their Cameras): a 120-degree arc around textured boxes."""
    folder = tmp_path_factory.mktemp("sfm_photos")
    cams = path_cameras(N_FRAMES)
    render_frames(textured_scene(), cams, folder)
    return folder, cams


@pytest.fixture(scope="session")
def synthetic_capture(synthetic_frames, tmp_path_factory):
    """`run_poses` on the synthetic photos: (report, capture folder)."""
    from trisplat.sfm import run_poses

    out = tmp_path_factory.mktemp("sfm_capture") / "capture"
    report = run_poses(synthetic_frames[0], out, progress=False, log=lambda m: None)
    return report, out
