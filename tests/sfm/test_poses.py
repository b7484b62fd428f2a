"""run_poses end to end on a small synthetic capture with known cameras: photos, a video of them, failures."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image, ImageFilter

from trisplat.sfm import camera_centre_error, run_poses
from trisplat.sfm.align import centres_from_model

MAX_CENTRE_ERROR = 0.01  # of the camera-path extent, after a similarity alignment


def test_photos_register_and_cameras_match_the_truth(synthetic_frames, synthetic_capture):
    folder, cams = synthetic_frames
    report, out = synthetic_capture
    names = [f"{c.name}.png" for c in cams]
    assert report.registered == names and report.unregistered == [] and report.n_input == len(cams)
    assert report.matcher == "exhaustive" and report.pairs == len(cams) * (len(cams) - 1) // 2
    assert report.points > 500 and 0 < report.mean_reprojection_error_px < 1.0
    est = centres_from_model(out / "sparse" / "0")
    err = camera_centre_error(est, {f"{c.name}.png": c.center for c in cams})
    assert err.n == len(cams)
    assert err.max_fraction < MAX_CENTRE_ERROR, err.as_dict()
    # camera model 'auto': square pixels first (RADIAL: one focal length, k1, k2), in one mapping; OPENCV's free fy
    # came out wrong on this one-height arc. Its focal length matches the renderer's
    assert report.camera_model == "RADIAL" and not any("mapped again" in w for w in report.warnings), report.warnings
    assert report.camera_params[0] == pytest.approx(cams[0].K[0, 0], rel=0.02)
    saved = json.loads((out / "poses.json").read_text())
    assert saved["registered"] == names and saved["registered_fraction"] == 1.0
    # nothing was written into the photo folder
    assert sorted(p.name for p in folder.iterdir()) == names


def test_the_capture_loads_as_an_undistorted_colmap_capture(synthetic_frames, synthetic_capture):
    from trisplat.data import load_dataset

    _, cams = synthetic_frames
    _, out = synthetic_capture
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"{c.name}.png" for c in cams]
    data = load_dataset(out, prepare="lazy", test_every=0)
    assert data.format == "colmap" and len(data.cameras) == len(cams)
    assert all(c.extras.get("source_model", "PINHOLE") == "PINHOLE" for c in data.cameras)
    assert data.points is not None and len(data.points) > 500
    # pinhole after undistortion; a crop of at most a few pixels
    c0 = data.cameras[0]
    assert abs(c0.width - 320) <= 4 and abs(c0.height - 240) <= 4


def _blurred(img: Image.Image) -> Image.Image:
    return img.filter(ImageFilter.GaussianBlur(2.5))


def test_video_frames_sharpest_per_interval_and_poses(synthetic_frames, tmp_path):
    """A 6 fps video in which each rendered view is shown three times, blurred, sharp, blurred: sampling 2 frames a
    second must keep exactly the sharp middle frames, and their poses must match the cameras."""
    import imageio.v2 as iio

    folder, cams = synthetic_frames
    video = tmp_path / "walk.mp4"
    with iio.get_writer(video, format="ffmpeg", fps=6, codec="libx264", quality=9, macro_block_size=16) as w:
        for c in cams:
            sharp = Image.open(folder / f"{c.name}.png").convert("RGB")
            for frame in (_blurred(sharp), sharp, _blurred(sharp)):
                w.append_data(np.asarray(frame))
    out = tmp_path / "capture"
    report = run_poses(video, out, progress=False, log=lambda m: None)
    assert report.video["frames_read"] == 3 * len(cams)
    assert report.video["frame_indices"] == [3 * i + 1 for i in range(len(cams))]
    assert report.matcher == "sequential"
    assert len(report.registered) == len(cams)
    est = centres_from_model(out / "sparse" / "0")
    ref = {f"frame_{3 * i + 1:06d}.jpg": c.center for i, c in enumerate(cams)}
    err = camera_centre_error(est, ref)
    assert err.n == len(cams) and err.max_fraction < MAX_CENTRE_ERROR, err.as_dict()
    # frames live in the capture's work folder, never next to the video
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture", "walk.mp4"]


def test_too_few_registered_names_the_images(synthetic_frames, tmp_path):
    """Five views of the scene plus three photos of unrelated noise: with 90% required, the error names the noise."""
    folder, cams = synthetic_frames
    photos = tmp_path / "photos"
    photos.mkdir()
    for c in cams[:10:2]:
        (photos / f"{c.name}.png").write_bytes((folder / f"{c.name}.png").read_bytes())
    rng = np.random.default_rng(5)
    for i in range(3):
        Image.fromarray(rng.integers(0, 256, size=(240, 320, 3), dtype=np.uint8)).save(photos / f"noise_{i}.png")
    from trisplat.sfm import PosesOptions

    with pytest.raises(ValueError) as err:
        run_poses(photos, tmp_path / "capture", PosesOptions(min_registered=0.9), progress=False, log=lambda m: None)
    msg = str(err.value)
    need = math.ceil(0.9 * 8)
    assert f"of 8 images registered (need at least {need})" in msg
    for i in range(3):
        assert f"noise_{i}.png (" in msg and "0 verified pairs" in msg
    assert not any(f"{c.name}.png (" in msg for c in cams[:10:2])


def test_distorted_copy_loads_and_is_undistorted_by_the_loader(synthetic_frames, synthetic_capture, tmp_path):
    """--no-undistort: the original photos with the RADIAL model; trisplat's loader undistorts them."""
    from trisplat.data import load_dataset
    from trisplat.sfm.pipeline import WORK, _copy_distorted

    folder, cams = synthetic_frames
    report, out = synthetic_capture
    copy = tmp_path / "distorted_capture"
    _copy_distorted(out / WORK / "sparse" / "0", folder, report.registered, copy)
    data = load_dataset(copy, prepare="lazy", test_every=0)
    assert len(data.cameras) == len(cams)
    assert {c.extras.get("source_model") for c in data.cameras} == {"RADIAL"}
    assert (copy / "images" / "frame_000.png").read_bytes() == (folder / "frame_000.png").read_bytes()
