"""Bad input gives errors naming the files: too few images, blank images, mixed sizes, unreadable files."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from trisplat.sfm import find_images, run_poses
from trisplat.sfm.inputs import check_images


def _noise(path, w=64, h=48, seed=0):
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)).save(path)


def test_find_images_natural_order_and_suffixes(tmp_path):
    for n in ("f10.png", "f2.JPG", "f1.jpeg", "notes.txt", ".hidden.png"):
        (tmp_path / n).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "f0.png").write_bytes(b"x")
    assert [p.name for p in find_images(tmp_path)] == ["f1.jpeg", "f2.JPG", "f10.png"]


def test_two_images_are_too_few(tmp_path):
    _noise(tmp_path / "a.png")
    _noise(tmp_path / "b.png", seed=1)
    with pytest.raises(ValueError, match=r"at least 3 images, found 2: a\.png, b\.png"):
        run_poses(tmp_path, tmp_path.parent / "out_two", progress=False, log=lambda m: None)


def test_all_black_images_are_named(tmp_path):
    for i in range(4):
        Image.new("RGB", (64, 48)).save(tmp_path / f"black_{i}.png")
    with pytest.raises(ValueError) as err:
        run_poses(tmp_path, tmp_path.parent / "out_black", progress=False, log=lambda m: None)
    msg = str(err.value)
    assert "4 blank image(s)" in msg and "black_0.png, black_1.png, black_2.png, black_3.png" in msg
    assert "only 0 usable" in msg


def test_some_blank_images_are_skipped_with_a_warning(tmp_path):
    files = []
    for i in range(3):
        _noise(tmp_path / f"n{i}.png", seed=i)
        files.append(tmp_path / f"n{i}.png")
    Image.new("RGB", (64, 48), (200, 10, 10)).save(tmp_path / "red.png")
    check = check_images(files + [tmp_path / "red.png"])
    assert [p.name for p in check.images] == ["n0.png", "n1.png", "n2.png"]
    assert [p.name for p in check.blank] == ["red.png"] and "red.png" in check.warnings[0]


def test_mixed_sizes_name_the_odd_files(tmp_path):
    for i in range(3):
        _noise(tmp_path / f"big_{i}.png", 64, 48, seed=i)
    _noise(tmp_path / "small.png", 32, 24)
    with pytest.raises(ValueError) as err:
        run_poses(tmp_path, tmp_path.parent / "out_mixed", progress=False, log=lambda m: None)
    msg = str(err.value)
    assert "2 different sizes" in msg and "64x48: big_0.png, big_1.png, big_2.png" in msg and "32x24: small.png" in msg
    assert "--camera-mode per-image" in msg


def test_unreadable_image_is_named(tmp_path):
    for i in range(3):
        _noise(tmp_path / f"ok_{i}.png", seed=i)
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(ValueError, match=r"unreadable image\(s\): broken\.jpg"):
        run_poses(tmp_path, tmp_path.parent / "out_broken", progress=False, log=lambda m: None)


def test_out_inside_the_photo_folder_is_refused(tmp_path):
    for i in range(3):
        _noise(tmp_path / f"ok_{i}.png", seed=i)
    with pytest.raises(ValueError, match="inside the input folder"):
        run_poses(tmp_path, tmp_path / "capture", progress=False, log=lambda m: None)


def test_cli_reports_bad_input_in_one_line(tmp_path, capsys):
    from trisplat.cli import main as cli_main

    photos = tmp_path / "photos"
    photos.mkdir()
    _noise(photos / "only.png")
    assert cli_main(["poses", str(photos), "--out", str(tmp_path / "cap"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("trisplat poses: error: ") and "found 1: only.png" in err
    assert not (tmp_path / "cap").exists()  # nothing written for rejected input


def test_non_empty_out_is_refused_without_force(tmp_path, capsys):
    from trisplat.cli import main as cli_main

    for i in range(3):
        _noise(tmp_path / f"ok_{i}.png", seed=i)
    out = tmp_path.parent / f"{tmp_path.name}_out"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    assert cli_main(["poses", str(tmp_path), "--out", str(out), "--quiet"]) == 1
    assert "is not empty; pass --force" in capsys.readouterr().err
    assert cli_main(["poses", str(tmp_path), "--out", str(out), "--quiet", "--force"]) == 1
    assert "not from `trisplat poses` (mine.txt)" in capsys.readouterr().err
    assert (out / "mine.txt").read_text() == "keep me"


def test_folder_without_images_says_subfolders_are_not_searched(tmp_path):
    (tmp_path / "photos" / "day1").mkdir(parents=True)
    _noise(tmp_path / "photos" / "day1" / "a.png")
    with pytest.raises(ValueError, match=r"no image files .* \(subfolders are not searched\)"):
        run_poses(tmp_path / "photos", tmp_path / "out", progress=False, log=lambda m: None)
