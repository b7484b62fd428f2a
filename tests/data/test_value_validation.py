"""Values, not only syntax, are checked when a capture loads: each bad value is refused (or warned about, where the
capture stays usable) with the file and the problem named; a folder holding two captures is read as the one with
points, saying what else is there (captures built in tmp_path, no shared data needed)."""
from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
from PIL import Image

from trisplat.data import load_dataset

W, H = 32, 24


def load(root, tmp_path, **kw):
    return load_dataset(root, cache_dir=tmp_path / "cache", **kw)


def _colmap(root, quats=None, points=None, focal=30.0, text=False):
    """A COLMAP model of 3 PINHOLE views (binary or text) with JPEG images; quats: per view (qw, qx, qy, qz)."""
    quats = quats or [(1.0, 0.0, 0.0, 0.0)] * 3
    points = np.array([[0, 0, 3], [0.5, 0, 3], [0, 0.5, 3.5]], float) if points is None else np.asarray(points)
    model, images = root / "sparse" / "0", root / "images"
    model.mkdir(parents=True)
    images.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(images / f"v{i}.jpg", quality=90)
    ts = [(-0.3 * i, 0.0, 0.0) for i in range(3)]
    if text:
        (model / "cameras.txt").write_text(f"1 PINHOLE {W} {H} {focal} {focal} {W / 2} {H / 2}\n")
        (model / "images.txt").write_text("".join(
            f"{i + 1} {' '.join(map(str, q))} {' '.join(map(str, t))} 1 v{i}.jpg\n\n"
            for i, (q, t) in enumerate(zip(quats, ts))))
        (model / "points3D.txt").write_text("".join(
            f"{k + 1} {x} {y} {z} 128 128 128 0.5\n" for k, (x, y, z) in enumerate(points)))
        return root
    (model / "cameras.bin").write_bytes(struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, W, H)
                                        + struct.pack("<4d", focal, focal, W / 2, H / 2))
    body = struct.pack("<Q", 3)
    for i, (q, t) in enumerate(zip(quats, ts)):
        body += struct.pack("<I7dI", i + 1, *q, *t, 1) + f"v{i}.jpg".encode() + b"\0" + struct.pack("<Q", 0)
    (model / "images.bin").write_bytes(body)
    body = struct.pack("<Q", len(points))
    for k, p in enumerate(points):
        body += struct.pack("<Q3d3Bd", k + 1, *p, 128, 128, 128, 0.5) + struct.pack("<Q", 0)
    (model / "points3D.bin").write_bytes(body)
    return root


def test_a_valid_model_loads(tmp_path):
    data = load(_colmap(tmp_path / "ok"), tmp_path)
    assert len(data.cameras) == 3 and len(data.points) == 3 and not data.warnings


@pytest.mark.parametrize("text", [False, True])
@pytest.mark.parametrize("q", [(math.nan, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), (1.0, math.inf, 0.0, 0.0)])
def test_a_bad_rotation_is_refused_not_made_the_identity(tmp_path, text, q):
    root = _colmap(tmp_path / "c", quats=[(1.0, 0, 0, 0), q, (1.0, 0, 0, 0)], text=text)
    name = "images.txt" if text else "images.bin"
    with pytest.raises(ValueError, match=rf"{name}: .*image 2 \(v1\.jpg\): invalid pose \(quaternion"):
        load(root, tmp_path)


def test_a_bad_focal_length_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"cameras\.bin: camera 1 \(PINHOLE, 32x24\): invalid values"):
        load(_colmap(tmp_path / "c", focal=0.0), tmp_path)


def test_non_finite_points_are_dropped_with_a_warning(tmp_path):
    root = _colmap(tmp_path / "c", points=[[0, 0, 3], [math.nan, 0, 3], [0, 0.5, 3.5]])
    data = load(root, tmp_path)
    assert len(data.points) == 2 and np.isfinite(data.points).all() and np.isfinite(data.bounds).all()
    assert any("points3D.bin: dropped 1 of 3 points with non-finite coordinates" in w for w in data.warnings)


def test_a_model_without_points_says_so(tmp_path):
    data = load(_colmap(tmp_path / "c", points=np.zeros((0, 3))), tmp_path)
    assert data.points is None
    assert any("points3D.bin: the model holds no (usable) 3D points" in w for w in data.warnings)


def test_a_truncated_jpeg_is_refused_at_load_time(tmp_path):
    root = _colmap(tmp_path / "c")
    p = root / "images" / "v2.jpg"
    p.write_bytes(p.read_bytes()[:-200])
    with pytest.raises(ValueError, match=r"v2\.jpg: truncated or damaged JPEG file"):
        load(root, tmp_path, prepare="lazy")  # no image is decoded before training, yet it is found now


# what a Pixel "motion photo" appends after the JPEG's end marker: an MP4 (its ftyp box first); Samsung's trailer
_MP4_TRAILER = (b"\x00\x00\x00\x18ftypmp42\x00\x00\x00\x00isommp42" + bytes(range(256)) * 40
                + b"\xff\xd8\xff\xe0 not a jpeg \x00\x00")
_SAMSUNG_TRAILER = b"\x00\x00\x00\x00SEFH" + bytes(300) + b"SEFT"


@pytest.mark.parametrize("trailer", [_MP4_TRAILER, _SAMSUNG_TRAILER], ids=["motion-photo-mp4", "samsung-sefh"])
def test_a_phone_jpeg_with_a_trailer_after_its_end_marker_loads(tmp_path, trailer):
    from trisplat.data.images import check_image_file, read_image

    root = _colmap(tmp_path / "c")
    p = root / "images" / "v1.jpg"
    clean = read_image(p)
    p.write_bytes(p.read_bytes() + trailer)
    assert check_image_file(p) == (W, H, None)
    np.testing.assert_array_equal(read_image(p), clean)
    data = load(root, tmp_path, prepare="eager")  # checked and decoded (the cache holds it)
    assert len(data.cameras) == 3 and not data.warnings


def test_a_jpeg_cut_in_half_is_refused_even_with_an_end_marker_in_its_metadata(tmp_path):
    """An APP segment holding a whole small JPEG (as an EXIF thumbnail does) has its own end marker: a file cut
    inside its scan data is refused all the same, and one cut in half of a 'motion photo' too."""
    import io

    root = _colmap(tmp_path / "c")
    thumb = io.BytesIO()
    Image.fromarray(np.full((8, 8, 3), 200, np.uint8)).save(thumb, format="JPEG")
    app = b"\xff\xef" + (2 + len(thumb.getvalue())).to_bytes(2, "big") + thumb.getvalue()
    p = root / "images" / "v0.jpg"
    whole = p.read_bytes()
    whole = whole[:2] + app + whole[2:]
    p.write_bytes(whole)
    assert load(root, tmp_path, prepare="lazy").cameras  # complete: loads
    sos = whole.rindex(b"\xff\xda")
    half = (sos + len(whole)) // 2  # half-way through the main image's scan data, after the thumbnail's end marker
    for cut in (whole[:half], (whole + _MP4_TRAILER)[:half], whole[: len(whole) // 2]):
        p.write_bytes(cut)
        with pytest.raises(ValueError, match=r"v0\.jpg: (truncated or damaged JPEG file|unreadable image)"):
            load(root, tmp_path, prepare="lazy")
    p.write_bytes(whole[:half])
    with pytest.raises(ValueError, match=r"v0\.jpg: truncated or damaged JPEG file \(the file ends before"):
        load(root, tmp_path, prepare="lazy")


def test_a_jpeg_with_stray_bytes_between_segments_loads_as_pil_reads_it(tmp_path):
    from trisplat.data.images import read_image

    root = _colmap(tmp_path / "c")
    p = root / "images" / "v1.jpg"
    b = p.read_bytes()
    app0_end = 4 + int.from_bytes(b[4:6], "big")
    p.write_bytes(b[:app0_end] + b"\x00\x00junk" + b[app0_end:])  # libjpeg skips them (a warning), PIL decodes
    assert read_image(p).shape == (H, W, 3)
    assert len(load(root, tmp_path, prepare="lazy").cameras) == 3


def test_a_progressive_jpeg_loads_and_is_refused_when_cut(tmp_path):
    root = _colmap(tmp_path / "c")
    p = root / "images" / "v2.jpg"
    Image.open(p).convert("RGB").save(p, format="JPEG", progressive=True, quality=90)  # several scans
    whole = p.read_bytes()
    assert load(root, tmp_path, prepare="lazy").cameras
    p.write_bytes(whole[: int(len(whole) * 0.7)])
    with pytest.raises(ValueError, match=r"v2\.jpg: truncated or damaged JPEG file"):
        load(root, tmp_path, prepare="lazy")


@pytest.fixture
def blender(tmp_path):
    from trisplat.synth import demo_mesh, write_blender_scene

    return write_blender_scene(tmp_path / "b", demo_mesh(), n_train=3, n_test=1, width=40, height=40,
                               samples_per_pixel=1, n_points=0)


def test_blender_image_of_another_size_is_refused(blender, tmp_path):
    Image.new("RGBA", (20, 30)).save(blender / "train" / "r_1.png")  # focal would silently change with it
    with pytest.raises(ValueError, match=r"train/r_1\.png: image is 20x30, but 3 of the 4 images of this capture "
                                         r"are 40x40"):
        load(blender, tmp_path)


def test_blender_truncated_png_is_refused(blender, tmp_path):
    p = blender / "test" / "r_0.png"
    p.write_bytes(p.read_bytes()[:-30])
    with pytest.raises(ValueError, match=r"test/r_0\.png: truncated or damaged PNG file"):
        load(blender, tmp_path)


def test_blender_png_with_bytes_after_iend_loads(blender, tmp_path):
    from trisplat.data.images import read_image

    p = blender / "train" / "r_1.png"
    clean = read_image(p)
    p.write_bytes(p.read_bytes() + b"trailing bytes some tool appended\x00\x01\x02")  # after IEND: PIL ignores them
    np.testing.assert_array_equal(read_image(p), clean)
    assert len(load(blender, tmp_path).cameras) == 4


def test_a_jpeg_renamed_png_is_warned_about(blender, tmp_path):
    p = blender / "train" / "r_2.png"
    Image.open(p).convert("RGB").save(p, format="JPEG")  # content JPEG, name .png: the alpha is gone
    data = load(blender, tmp_path)
    assert any("train/r_2.png: a JPEG file named .png (it has no alpha channel)" in w for w in data.warnings)


# ------------------------------------------------------------------ a folder holding two captures (fox ships both)


def _with_transforms_json(root):
    frames = [{"file_path": f"images/v{i}.jpg", "transform_matrix": np.linalg.inv(np.array(
        [[1, 0, 0, -0.3 * i], [0, -1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1.0]])).tolist()} for i in range(3)]
    (root / "transforms.json").write_text(json.dumps({"fl_x": 30.0, "fl_y": 30.0, "cx": W / 2, "cy": H / 2, "w": W,
                                                      "h": H, "frames": frames}))
    return root


def test_auto_prefers_the_colmap_model_with_points_and_says_what_else_is_there(tmp_path, capsys):
    from trisplat.cli import main

    root = _with_transforms_json(_colmap(tmp_path / "both"))
    data = load(root, tmp_path)
    assert data.format == "colmap" and len(data.points) == 3
    assert any("also holds transforms.json (ngp); read as colmap for its sparse points; --data-format ngp picks "
               "the other" in w for w in data.warnings)
    # the same option name in info and train picks the other one (info also takes --format)
    assert load(root, tmp_path, format="ngp").format == "ngp"
    for flag in ("--data-format", "--format"):
        assert main(["info", str(root), flag, "ngp"]) == 0
        assert "format      ngp" in capsys.readouterr().out


def test_auto_keeps_transforms_json_before_a_colmap_model_without_points(tmp_path):
    root = _with_transforms_json(_colmap(tmp_path / "both", points=np.zeros((0, 3))))
    data = load(root, tmp_path)
    assert data.format == "ngp"
    assert any("also holds a COLMAP model (colmap); read as ngp; --data-format colmap picks the other" in w
               for w in data.warnings)
