"""Bad input: every broken capture raises a precise error naming the file (corrupted copies built in tmp_path)."""
from __future__ import annotations

import json
import shutil
import struct

import numpy as np
import pytest
from conftest import shared_data
from PIL import Image

from trisplat.data import load_dataset


def load(path, tmp_path, **kw):
    return load_dataset(path, cache_dir=tmp_path / "cache", prepare="lazy", **kw)


# ---------------------------------------------------------------- COLMAP


@pytest.fixture
def fox_copy(tmp_path):
    """fox's COLMAP model copied (a few MB), images as symlinks to the shared files."""
    src = shared_data("fox")
    root = tmp_path / "fox"
    shutil.copytree(src / "sparse", root / "sparse")
    (root / "images").mkdir()
    for f in (src / "images").iterdir():
        (root / "images" / f.name).symlink_to(f)
    return root


def test_colmap_missing_image(fox_copy, tmp_path):
    (fox_copy / "images" / "0007.jpg").unlink()
    with pytest.raises(FileNotFoundError, match=r"images/0007\.jpg: image file does not exist"):
        load(fox_copy, tmp_path)


def test_colmap_unreadable_image(fox_copy, tmp_path):
    p = fox_copy / "images" / "0007.jpg"
    p.unlink()
    p.write_bytes(b"this is not a jpeg")
    with pytest.raises(ValueError, match=r"0007\.jpg: unreadable image"):
        load(fox_copy, tmp_path)


def test_colmap_image_size_disagrees_with_camera(fox_copy, tmp_path):
    p = fox_copy / "images" / "0007.jpg"
    p.unlink()
    Image.new("RGB", (540, 960)).save(p)
    with pytest.raises(ValueError, match=r"0007\.jpg: image is 540x960 but its camera \(OPENCV\) expects 1080x1920"):
        load(fox_copy, tmp_path)


@pytest.mark.parametrize(
    "name,cut,message",
    [
        ("images.bin", 0.5, r"images\.bin: malformed COLMAP binary file: truncated"),
        ("points3D.bin", 0.9, r"points3D\.bin: malformed COLMAP binary file: truncated"),
        ("cameras.bin", 0.7, r"cameras\.bin: malformed COLMAP binary file: truncated"),
        ("points3D.bin", 1.001, r"points3D\.bin: malformed COLMAP binary file: \d+ unexpected trailing bytes"),
    ],
)
def test_colmap_malformed_binary(fox_copy, tmp_path, name, cut, message):
    p = fox_copy / "sparse" / "0" / name
    data = p.read_bytes()
    p.write_bytes(data[: int(len(data) * cut)] if cut < 1 else data + b"\0" * 7)
    with pytest.raises(ValueError, match=message):
        load(fox_copy, tmp_path)


def test_colmap_huge_count_is_caught_before_pycolmap(fox_copy, tmp_path):
    p = fox_copy / "sparse" / "0" / "points3D.bin"
    data = bytearray(p.read_bytes())
    data[:8] = struct.pack("<Q", 2**60)
    p.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"points3D\.bin: malformed COLMAP binary file: claims \d+ points"):
        load(fox_copy, tmp_path)


def test_colmap_unknown_model_id_in_binary(fox_copy, tmp_path):
    p = fox_copy / "sparse" / "0" / "cameras.bin"
    data = bytearray(p.read_bytes())
    data[12:16] = struct.pack("<i", 42)  # model id of the first camera (after count u64 and camera id i32)
    p.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"cameras\.bin: unknown camera model id 42"):
        load(fox_copy, tmp_path)


def _text_model(root, camera_line, images="1 1 0 0 0 0 0 0 1 a.png\n\n"):
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (root / "images").mkdir()
    Image.new("RGB", (64, 48)).save(root / "images" / "a.png")
    (sparse / "cameras.txt").write_text(camera_line + "\n")
    (sparse / "images.txt").write_text(images)
    (sparse / "points3D.txt").write_text("")


@pytest.mark.parametrize(
    "line,message",
    [
        ("1 BOGUS 64 48 50 32 24", r"cameras\.txt:1: unknown camera model 'BOGUS'"),
        ("1 FOV 64 48 50 50 32 24 0.1", r"cameras\.txt:1: unsupported camera model FOV"),
        ("1 PINHOLE 64 48 50 50 32", r"cameras\.txt:1: camera model PINHOLE takes 4 parameters, got 3"),
        ("1 PINHOLE 64 48 50 fifty 32 24", r"cameras\.txt:1: malformed COLMAP text file: non-numeric"),
    ],
)
def test_colmap_text_camera_errors(tmp_path, line, message):
    _text_model(tmp_path / "cap", line)
    with pytest.raises(ValueError, match=message):
        load(tmp_path / "cap", tmp_path)


def test_colmap_text_image_line_malformed(tmp_path):
    _text_model(tmp_path / "cap", "1 PINHOLE 64 48 50 50 32 24", images="1 1 0 0 0 0 0 a.png\n\n")
    with pytest.raises(ValueError, match=r"images\.txt:1: malformed COLMAP text file: image line needs 10 fields"):
        load(tmp_path / "cap", tmp_path)


def test_colmap_empty_scene(tmp_path):
    _text_model(tmp_path / "cap", "1 PINHOLE 64 48 50 50 32 24", images="# nothing\n")
    with pytest.raises(ValueError, match=r"sparse/0: empty scene: the COLMAP model has no posed images"):
        load(tmp_path / "cap", tmp_path)


def test_text_model_loads(tmp_path):
    _text_model(tmp_path / "cap", "1 PINHOLE 64 48 50 50 32 24")
    data = load(tmp_path / "cap", tmp_path)
    np.testing.assert_allclose(data.cameras[0].K, [[50, 0, 32], [0, 50, 24], [0, 0, 1]])


# ---------------------------------------------------------------- Blender / instant-ngp JSON


@pytest.fixture
def lego_copy(tmp_path):
    src = shared_data("lego")
    root = tmp_path / "lego"
    root.mkdir()
    for name in ("transforms_train.json", "transforms_test.json"):
        shutil.copy(src / name, root / name)
    for split in ("train", "test"):
        (root / split).symlink_to(src / split)
    return root


def test_blender_malformed_json(lego_copy, tmp_path):
    p = lego_copy / "transforms_test.json"
    p.write_text(p.read_text()[:500])
    with pytest.raises(ValueError, match=r"transforms_test\.json: malformed JSON: .* at line \d+ column \d+"):
        load(lego_copy, tmp_path)


def test_blender_missing_image(lego_copy, tmp_path):
    meta = json.loads((lego_copy / "transforms_train.json").read_text())
    meta["frames"][3]["file_path"] = "./train/r_missing"
    (lego_copy / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(FileNotFoundError, match=r"train/r_missing\.png: image listed in .*transforms_train\.json"):
        load(lego_copy, tmp_path)


def test_blender_bad_matrix_and_empty(lego_copy, tmp_path):
    meta = json.loads((lego_copy / "transforms_train.json").read_text())
    meta["frames"][2]["transform_matrix"] = [[1, 0], [0, 1]]
    (lego_copy / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"transforms_train\.json: frame 2 .*'transform_matrix' must be a finite 4x4"):
        load(lego_copy, tmp_path)
    meta["frames"] = []
    (lego_copy / "transforms_train.json").write_text(json.dumps(meta))
    (lego_copy / "transforms_test.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"empty scene"):
        load(lego_copy, tmp_path)


def _ngp(tmp_path, **top):
    root = tmp_path / "ngp"
    (root / "images").mkdir(parents=True)
    Image.new("RGB", (64, 48)).save(root / "images" / "a.png")
    frame = {"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}
    meta = {"fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48, "frames": [frame], **top}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def test_ngp_unknown_camera_model(tmp_path):
    root = _ngp(tmp_path, camera_model="EQUIRECTANGULAR")
    with pytest.raises(ValueError, match=r"transforms\.json: frame 0 .*unknown camera model 'EQUIRECTANGULAR'"):
        load(root, tmp_path)


def test_ngp_size_mismatch_and_per_frame_intrinsics(tmp_path):
    root = _ngp(tmp_path, w=100, h=48)
    with pytest.raises(ValueError, match=r"a\.png: image is 64x48 but its camera \(PINHOLE\) expects 100x48"):
        load(root, tmp_path)
    meta = json.loads((root / "transforms.json").read_text())
    meta["w"] = 64
    meta["frames"][0]["fl_x"] = 70.0  # per-frame value wins over the file-level one
    (root / "transforms.json").write_text(json.dumps(meta))
    data = load(root, tmp_path)
    np.testing.assert_allclose(data.cameras[0].K[:2], [[70, 0, 32], [0, 50, 24]])
    # identity OpenGL camera-to-world: OpenCV world-to-camera flips y and z
    np.testing.assert_allclose(data.cameras[0].world_to_camera[:3, :3], np.diag([1.0, -1.0, -1.0]))


def test_ngp_all_images_missing_is_an_empty_scene(tmp_path):
    root = _ngp(tmp_path)
    (root / "images" / "a.png").unlink()
    with pytest.raises(ValueError, match=r"transforms\.json: empty scene: none of its 1 frames has an existing image"):
        load(root, tmp_path)


# ---------------------------------------------------------------- RGB-D and general


@pytest.fixture
def icl_copy(tmp_path):
    src = shared_data("icl_rgbd")
    root = tmp_path / "icl"
    root.mkdir()
    for name in ("camera.json", "trajectory.log"):
        shutil.copy(src / name, root / name)
    for d in ("color", "depth"):
        (root / d).mkdir()
        for f in (src / d).iterdir():
            (root / d / f.name).symlink_to(f)
    return root


def test_rgbd_trajectory_count_and_malformed(icl_copy, tmp_path):
    log = icl_copy / "trajectory.log"
    lines = log.read_text().splitlines()
    log.write_text("\n".join(lines[:20]) + "\n")
    with pytest.raises(ValueError, match=r"trajectory\.log: 4 poses for 5 colour images"):
        load(icl_copy, tmp_path)
    log.write_text("\n".join(lines[:7]) + "\n")
    with pytest.raises(ValueError, match=r"trajectory\.log: malformed trajectory: expected blocks of 5 lines"):
        load(icl_copy, tmp_path)


def test_rgbd_malformed_intrinsics(icl_copy, tmp_path):
    (icl_copy / "camera.json").write_text('{"width": 640, "height": 480}')
    with pytest.raises(ValueError, match=r"camera\.json: malformed intrinsics"):
        load(icl_copy, tmp_path)


def test_unknown_folder_and_bad_options(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"empty: no known capture format"):
        load(tmp_path / "empty", tmp_path)
    with pytest.raises(FileNotFoundError, match=r"nowhere: capture folder does not exist"):
        load(tmp_path / "nowhere", tmp_path)
    with pytest.raises(ValueError, match=r"downscale must be one of"):
        load_dataset(shared_data("lego"), downscale=3)
    with pytest.raises(ValueError, match=r"unknown load_dataset option\(s\) \['bogus'\]"):
        load_dataset(shared_data("lego"), bogus=1)


def test_cache_inside_capture_is_refused(lego_copy):
    with pytest.raises(ValueError, match=r"lies inside the capture folder"):
        load_dataset(lego_copy, downscale=2, cache_dir=lego_copy / "cache")
