"""run_poses end to end on a small synthetic capture with known cameras: photos, a video of them, failures, and
photos through a known lens (camera model auto's RADIAL fit, undistortion by the pipeline and by the loader)."""
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
    # came out wrong on this one-height arc. Its focal length matches the renderer's (a real lens: below)
    assert report.camera_model == "RADIAL" and not any("mapped again" in w for w in report.warnings), report.warnings
    assert report.camera_params[0] == pytest.approx(cams[0].K[0, 0], rel=0.02)
    saved = json.loads((out / "poses.json").read_text())
    assert saved["registered"] == names and saved["registered_fraction"] == 1.0
    # nothing was written into the photo folder
    assert sorted(p.name for p in folder.iterdir()) == names


def test_the_global_mapper_is_the_default_and_the_incremental_one_maps_when_it_registers_too_few(
        synthetic_frames, synthetic_capture, tmp_path, monkeypatch):
    """The default capture (synthetic_capture) came from COLMAP's global mapper alone; when the global mapper
    registers fewer than min_registered of the photos, the incremental mapper maps the same matches again and says so.
    The mapper is part of the cache fingerprint; a bad name is refused."""
    from trisplat.sfm import PosesOptions
    from trisplat.sfm.cache import fingerprint

    import pycolmap

    report, _ = synthetic_capture
    assert PosesOptions().mapper == "global"
    assert not any("incremental" in w for w in report.warnings), report.warnings
    calls = []
    real_incremental = pycolmap.incremental_mapping

    def no_model(*args, **kwargs):
        calls.append("global")
        return {}

    def incremental(*args, **kwargs):
        calls.append("incremental")
        return real_incremental(*args, **kwargs)

    monkeypatch.setattr(pycolmap, "global_mapping", no_model)
    monkeypatch.setattr(pycolmap, "incremental_mapping", incremental)
    folder, cams = synthetic_frames
    out = tmp_path / "capture"
    said = []
    report = run_poses(folder, out, PosesOptions(camera_model="RADIAL"), progress=False, log=said.append)
    assert calls == ["global", "incremental"]
    assert any("the global mapper registered 0 of" in w and "incremental" in w for w in report.warnings)
    assert any("global mapping" in m for m in said)
    assert report.registered == [f"{c.name}.png" for c in cams]
    err = camera_centre_error(centres_from_model(out / "sparse" / "0"), {f"{c.name}.png": c.center for c in cams})
    assert err.n == len(cams) and err.max_fraction < MAX_CENTRE_ERROR, err.as_dict()
    assert fingerprint(folder, PosesOptions(mapper="incremental")) != fingerprint(folder, PosesOptions())
    with pytest.raises(ValueError, match="mapper must be one of"):
        PosesOptions(mapper="glomap")


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


# The lens of the distorted captures: COLMAP RADIAL (x (1 + k1 r^2 + k2 r^4)), barrel, ~20 px at the corners of
# 320x240 at a 60 degree field of view
K1, K2 = -0.12, 0.02
DISTORTED_FRAMES = 12


@pytest.fixture(scope="module")
def distorted_frames(tmp_path_factory):
    """(folder of DISTORTED_FRAMES photos 320x240 through the K1, K2 lens, their pinhole Cameras, the scene)."""
    from tests.sfm.sfm_scene import path_cameras, render_distorted_frames, textured_scene

    folder = tmp_path_factory.mktemp("distorted_photos")
    mesh = textured_scene()
    cams = path_cameras(DISTORTED_FRAMES)
    render_distorted_frames(mesh, cams, K1, K2, folder)
    return folder, cams, mesh


def _blurred_difference(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two float RGB images after a 1.5 px Gaussian blur (sub-pixel resampling noise of
    the fine texture is not what is measured: a misplaced point moves a whole blob)."""
    from scipy import ndimage

    return float(np.abs(ndimage.gaussian_filter(a, (1.5, 1.5, 0)) - ndimage.gaussian_filter(b, (1.5, 1.5, 0))).mean())


def _pinhole_photo(mesh, w2c, K, width, height) -> np.ndarray:
    from trisplat.cameras import Camera
    from trisplat.synth import raycast_view

    return raycast_view(mesh, Camera(w2c, K, width, height), background=(1.0, 1.0, 1.0)).rgba[..., :3]


def _photo(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255


def _write_colmap_text_model(folder, cams, params) -> None:
    """A COLMAP text model (one RADIAL camera with `params`, the cameras' true poses, no points)."""
    from scipy.spatial.transform import Rotation

    folder.mkdir(parents=True)
    c0 = cams[0]
    (folder / "cameras.txt").write_text(f"1 RADIAL {c0.width} {c0.height} " + " ".join(repr(float(v)) for v in params) + "\n")
    lines = []
    for i, c in enumerate(cams, 1):
        R, t = c.world_to_camera[:3, :3], c.world_to_camera[:3, 3]
        q = Rotation.from_matrix(R).as_quat(scalar_first=True)  # COLMAP: QW QX QY QZ of world-to-camera
        lines += [f"{i} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" 1 {c.name}.png", ""]
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    (folder / "points3D.txt").write_text("")


def test_loader_undistorts_a_known_radial_lens(distorted_frames, tmp_path):
    """Photos through a known RADIAL lens in a COLMAP capture (the true camera and poses as a text model): the
    loader's pinhole images are what a pinhole camera with the loader's K sees from the true pose; the photos as
    they are (the lens ignored) are not."""
    from trisplat.data import load_dataset

    folder, cams, mesh = distorted_frames
    picked = cams[::4]
    capture = tmp_path / "capture"
    (capture / "images").mkdir(parents=True)
    for c in picked:
        (capture / "images" / f"{c.name}.png").write_bytes((folder / f"{c.name}.png").read_bytes())
    K = picked[0].K
    _write_colmap_text_model(capture / "sparse" / "0", picked, [K[0, 0], K[0, 2], K[1, 2], K1, K2])
    data = load_dataset(capture, prepare="lazy", test_every=0, normalize="none", cache_dir=str(tmp_path / "cache"))
    assert [c.name for c in data.cameras] == [f"{c.name}.png" for c in picked]
    for i, (cam, true) in enumerate(zip(data.cameras, picked)):
        assert cam.extras["source_model"] == "RADIAL" and cam.extras["undistorted"]
        assert (cam.width, cam.height) != (true.width, true.height)  # the undistorted view is not the photo's
        undistorted = np.asarray(data.load_image(i), dtype=np.float64)
        err = _blurred_difference(undistorted, _pinhole_photo(mesh, true.world_to_camera, cam.K, cam.width,
                                                              cam.height))
        as_is = _blurred_difference(_photo(folder / f"{true.name}.png"), _pinhole_photo(
            mesh, true.world_to_camera, true.K, true.width, true.height))
        assert err < 0.2 * as_is, (err, as_is)  # measured: 0.0013 against 0.015


def test_camera_model_auto_fits_and_removes_a_radial_lens(distorted_frames, tmp_path):
    """Camera model 'auto' (its first branch, RADIAL: one focal length, k1, k2) on photos through a real lens: the
    fitted lens matches the true one, the cameras match the truth, and the capture's undistorted photos are pinhole
    photos of the scene."""
    import pycolmap

    folder, cams, mesh = distorted_frames
    out = tmp_path / "capture"
    report = run_poses(folder, out, progress=False, log=lambda m: None)
    assert report.camera_model == "RADIAL" and not any("mapped again" in w for w in report.warnings)
    assert len(report.registered) == len(cams)
    f, cx, cy, k1, k2 = report.camera_params
    f_true = cams[0].K[0, 0]
    assert f == pytest.approx(f_true, rel=0.02)
    # the radial factor over the whole image (r up to the corner): a pinhole fit would be off by 0.07 at the corner
    r = np.linspace(0, np.hypot(160, 120) / f_true * 1.1, 50)
    factor = lambda a, b: 1 + a * r**2 + b * r**4  # noqa: E731
    assert np.abs(factor(k1, k2) - factor(K1, K2)).max() < 0.015, (k1, k2)
    est = centres_from_model(out / "sparse" / "0")
    err = camera_centre_error(est, {f"{c.name}.png": c.center for c in cams})
    assert err.max_fraction < MAX_CENTRE_ERROR, err.as_dict()
    # the undistorted photos: pinhole photos from the true poses (the focal length as estimated, relative to the true
    # one: the photos are undistorted with the estimate)
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    cam = next(iter(rec.cameras.values()))
    assert cam.model.name == "PINHOLE"
    K = np.asarray(cam.calibration_matrix(), dtype=np.float64)
    K[0, 0] *= f_true / f
    K[1, 1] *= f_true / f
    for c in cams[::5]:
        undistorted = _photo(out / "images" / f"{c.name}.png")
        e = _blurred_difference(undistorted, _pinhole_photo(mesh, c.world_to_camera, K, cam.width, cam.height))
        as_is = _blurred_difference(_photo(folder / f"{c.name}.png"), _pinhole_photo(mesh, c.world_to_camera, c.K,
                                                                                     c.width, c.height))
        assert e < 0.4 * as_is, (c.name, e, as_is)  # measured: 0.004 against 0.015
