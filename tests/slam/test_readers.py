"""RGB-D stream readers (TUM, 7-Scenes, Redwood): association, intrinsics, invalid depth, and precise errors."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_data
from PIL import Image

from trisplat.data.rgbd_stream import (
    FramePrefetch,
    detect_stream_format,
    downscale_depth,
    load_frame,
    open_stream,
    read_sevenscenes,
    read_tum,
)


def _write_pair(color_path, depth_path, w=8, h=6, depth_raw=1000, depth_shape=None):
    color_path.parent.mkdir(parents=True, exist_ok=True)
    depth_path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((h, w, 3), 128, np.uint8)).save(color_path)
    dh, dw = depth_shape or (h, w)
    d = np.full((dh, dw), depth_raw, np.uint16)
    d[0, 0] = 0
    d[0, 1] = 65535
    Image.fromarray(d).save(depth_path)


def _tum(root, rgb_stamps, depth_stamps, gt=True, name="rgbd_dataset_freiburg1_test"):
    root = root / name
    rgb, depth, poses = ["# rgb"], ["# depth"], ["# gt"]
    for t in rgb_stamps:
        _write_pair(root / "rgb" / f"{t:.6f}.png", root / "depth" / "unused.png")
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
    for t in depth_stamps:
        _write_pair(root / "rgb" / "unused.png", root / "depth" / f"{t:.6f}.png", depth_raw=5000)
        depth.append(f"{t:.6f} depth/{t:.6f}.png")
        poses.append(f"{t:.6f} 1 2 3 0 0 0.7071067811865476 0.7071067811865476")
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(depth) + "\n")
    if gt:
        (root / "groundtruth.txt").write_text("\n".join(poses) + "\n")
    return root


def test_tum_associates_by_time_and_reads_poses(tmp_path):
    root = _tum(tmp_path, [1.0, 1.1, 1.2, 5.0], [1.005, 1.095, 1.219])
    s = open_stream(root)
    assert s.format == "tum" and len(s) == 3  # 5.0 has no depth within 0.02 s: dropped with a warning
    assert "dropped 1 colour frame" in s.warnings[0]
    assert [f.depth_path.name for f in s.frames] == ["1.005000.png", "1.095000.png", "1.219000.png"]
    assert [f.stamp for f in s.frames] == [1.0, 1.1, 1.2]
    c2w = s.frames[0].reference_c2w
    np.testing.assert_allclose(c2w[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(c2w[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)  # 90 deg about z
    np.testing.assert_allclose(s.K[0], [517.3, 0, 319.1])  # freiburg1, principal point shifted to +0.5
    rgb, depth = load_frame(s, 0)
    assert rgb.shape == (6, 8, 3) and depth.dtype == np.float32
    assert depth[0, 0] == 0 and depth[0, 1] == 0 and depth[1, 1] == pytest.approx(1.0)  # 5000 / 5000 m


def test_tum_errors_name_files(tmp_path):
    root = _tum(tmp_path, [1.0, 1.1], [3.0, 3.1], name="a_freiburg2_x")
    with pytest.raises(ValueError, match=r"depth\.txt: unmatched timestamps: no depth stamp within 0\.02 s"):
        open_stream(root)
    root = _tum(tmp_path, [1.0], [1.0], name="b_freiburg2_x")
    (root / "depth" / "1.000000.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"depth/1\.000000\.png: listed in .*depth\.txt but does not exist"):
        read_tum(root)
    root = _tum(tmp_path, [1.0], [1.0], name="no_intrinsics")
    with pytest.raises(FileNotFoundError, match="needs intrinsics"):
        read_tum(root)


def _sevenscenes(root, n=3, poses=True):
    root.mkdir(parents=True, exist_ok=True)
    (root / "camera-intrinsics.txt").write_text("585 0 4\n0 585 3\n0 0 1\n")
    for i in range(n):
        _write_pair(root / f"frame-{i:06d}.color.png", root / f"frame-{i:06d}.depth.png")
        if poses:
            m = np.eye(4)
            m[0, 3] = 0.1 * i
            np.savetxt(root / f"frame-{i:06d}.pose.txt", m)
    return root


def test_sevenscenes_layout(tmp_path):
    s = open_stream(_sevenscenes(tmp_path / "s"))
    assert s.format == "7scenes" and len(s) == 3 and (s.width, s.height) == (8, 6)
    np.testing.assert_allclose(s.K, [[585, 0, 4.5], [0, 585, 3.5], [0, 0, 1]])
    assert s.frames[2].reference_c2w[0, 3] == pytest.approx(0.2) and s.frames[1].stamp is None
    rgb, depth = load_frame(s, 1)
    assert depth[0, 0] == 0 and depth[0, 1] == 0  # 0 and 65535 are invalid
    assert depth[2, 2] == pytest.approx(1.0)  # 1000 mm
    s2 = open_stream(_sevenscenes(tmp_path / "np", poses=False), depth_scale=0.002)
    assert not s2.has_reference and load_frame(s2, 0)[1][2, 2] == pytest.approx(2.0)


def test_sevenscenes_errors_name_files(tmp_path):
    root = _sevenscenes(tmp_path / "m")
    (root / "frame-000001.depth.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"frame-000001\.depth\.png: depth file of frame-000001\.color\.png"):
        read_sevenscenes(root)
    root = _sevenscenes(tmp_path / "sz")
    _write_pair(root / "frame-000002.color.png", root / "frame-000002.depth.png", depth_shape=(3, 4))
    s = open_stream(root)
    with pytest.raises(ValueError, match=r"frame-000002\.depth\.png: depth is 4x3 but the colour image"):
        load_frame(s, 2)
    root = _sevenscenes(tmp_path / "k")
    (root / "camera-intrinsics.txt").write_text("585 0 4\n0 585\n")
    with pytest.raises(ValueError, match=r"camera-intrinsics\.txt: malformed intrinsics"):
        open_stream(root)
    with pytest.raises(FileNotFoundError, match="capture folder does not exist"):
        open_stream(tmp_path / "nothing")


def test_prefetched_frames_are_load_frames(tmp_path):
    root = _sevenscenes(tmp_path / "p", n=5)
    rng = np.random.default_rng(0)
    for i in range(5):  # each frame its own pixels, so a frame handed out of turn would show
        Image.fromarray(rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)).save(root / f"frame-{i:06d}.color.png")
        Image.fromarray(rng.integers(1, 5000, (6, 8), dtype=np.uint16)).save(root / f"frame-{i:06d}.depth.png")
    s = open_stream(root)
    ids = [0, 2, 3, 4]
    with FramePrefetch(s, ids, downscale=2) as frames:
        for n in (0, 1, 3, 2):  # in order, then one skipped and one asked for after it
            rgb, depth = frames.get(n)
            want_rgb, want_depth = load_frame(s, ids[n], 2)
            np.testing.assert_array_equal(rgb, want_rgb)
            np.testing.assert_array_equal(depth, want_depth)
    (root / "frame-000003.color.png").write_bytes(b"not a png")  # corrupt: its own get() names the file
    with FramePrefetch(s, ids) as frames:
        frames.get(0)
        frames.get(1)
        with pytest.raises(ValueError, match=r"frame-000003\.color\.png"):
            frames.get(2)


def test_downscale_depth_keeps_edges_invalid():
    d = np.array([[1.0, 1.0, 2.0, 2.0], [1.0, 1.0, 2.0, 0.0], [1.0, 3.0, 0.0, 0.0], [1.0, 1.0, 0.0, 0.0]], np.float32)
    out = downscale_depth(d, 2)
    np.testing.assert_allclose(out, [[1.0, 2.0], [0.0, 0.0]])  # edge block (1..3) and mostly-invalid block -> 0


@pytest.mark.parametrize("f", [2, 3])
def test_downscaling_matches_a_per_block_reference(f):
    """The strided-slice box filter and edge-aware depth downscale agree with a readable loop over the blocks."""
    from trisplat.data.rgbd_stream import _box_down

    rng = np.random.default_rng(f)
    H, W = 7 * f + f - 1, 5 * f + f - 1  # rows / columns beyond the last whole block are dropped
    rgb = rng.random((H, W, 3)).astype(np.float32)
    depth = np.repeat(np.repeat(rng.uniform(1.0, 3.0, (7, 5)), f, 0), f, 1).astype(np.float32)
    depth = np.pad(depth, ((0, f - 1), (0, f - 1)), constant_values=1.0)
    depth[rng.random(depth.shape) < 0.3] = 0.0
    depth[0:f, 0:f] = 1.0
    depth[0, 0] = 1.5  # a block spanning a depth edge (max / min > 1.1)
    want_rgb = np.zeros((7, 5, 3))
    want_d = np.zeros((7, 5))
    for i in range(7):
        for j in range(5):
            want_rgb[i, j] = rgb[i * f:(i + 1) * f, j * f:(j + 1) * f].mean(axis=(0, 1))
            b = depth[i * f:(i + 1) * f, j * f:(j + 1) * f]
            v = b[b > 0]
            if 2 * len(v) >= f * f and v.max() <= 1.1 * v.min():
                want_d[i, j] = v.mean()
    np.testing.assert_allclose(_box_down(rgb, f), want_rgb, rtol=1e-5, atol=1e-6)
    got = downscale_depth(depth, f)
    assert got[0, 0] == 0.0 and (got > 0).sum() >= 3
    np.testing.assert_allclose(got, want_d, rtol=1e-5)


def test_real_sevenscenes_and_redwood():
    s = open_stream(shared_data("sevenscenes_rgbd"))
    assert s.format == "7scenes" and len(s) == 400 and s.has_reference
    np.testing.assert_allclose(s.K_at(2), [[292.5, 0, 160.25], [0, 292.5, 120.25], [0, 0, 1]])
    rgb, depth = load_frame(s, 0, downscale=2)
    assert rgb.shape == (240, 320, 3) and depth.shape == (240, 320)
    assert 0.3 < np.median(depth[depth > 0]) < 4.0
    r = open_stream(shared_data("icl_rgbd"))
    assert r.format == "redwood" and r.has_reference and len(r) > 1


def test_eth3d_slam_layout_reads_calibration_and_poses(tmp_path):
    root = _tum(tmp_path, [1.0, 1.1, 1.2], [1.0, 1.1, 1.2], name="eth3d_table_3")
    assert detect_stream_format(root) == "tum"  # without calibration.txt (and then without intrinsics)
    (root / "calibration.txt").write_text("726.2 726.3 354.6 186.5\n")
    s = open_stream(root)
    assert s.format == "eth3d" and len(s) == 3
    np.testing.assert_allclose(s.K, [[726.2, 0, 354.6], [0, 726.3, 186.5], [0, 0, 1]])  # COLMAP centres: no shift
    np.testing.assert_allclose(s.frames[0].reference_c2w[:3, 3], [1, 2, 3])
    _, depth = load_frame(s, 0)
    assert depth[1, 1] == pytest.approx(1.0)  # 5000 raw / 5000 per metre
    (root / "calibration.txt").write_text("726.2 726.3 354.6\n")
    with pytest.raises(ValueError, match=r"calibration\.txt: malformed calibration: expected 'fx fy cx cy'"):
        open_stream(root)


def _scannet(root, n=3, color=(16, 12), depth=(8, 6)):
    for d in ("color", "depth", "pose", "intrinsic"):
        (root / d).mkdir(parents=True, exist_ok=True)
    for k in range(n):
        Image.fromarray(np.full((color[1], color[0], 3), 40 * k, np.uint8)).save(root / "color" / f"{k}.jpg")
        Image.fromarray(np.full((depth[1], depth[0]), 1500, np.uint16)).save(root / "depth" / f"{k}.png")
        T = np.eye(4)
        T[:3, 3] = [k, 0, 0]
        np.savetxt(root / "pose" / f"{k}.txt", T if k != 1 else np.full((4, 4), -np.inf))
    M = np.eye(4)
    M[:3, :3] = [[5.0, 0, 3.5], [0, 5.0, 2.5], [0, 0, 1]]
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", M)
    return root


def test_scannet_layout_resamples_colour_to_depth(tmp_path):
    root = _scannet(tmp_path / "scene0000_00")
    s = open_stream(root)
    assert s.format == "scannet" and len(s) == 3 and (s.width, s.height) == (8, 6)
    np.testing.assert_allclose(s.K, [[5, 0, 4], [0, 5, 3], [0, 0, 1]])  # integer-centred file, +0.5
    assert s.frames[1].reference_c2w is None and s.frames[2].reference_c2w[0, 3] == 2
    assert any("resampled" in w for w in s.warnings) and any("no (valid) reference pose" in w for w in s.warnings)
    rgb, depth = load_frame(s, 2)
    assert rgb.shape == (6, 8, 3) and depth.shape == (6, 8) and depth[2, 2] == pytest.approx(1.5)
    assert rgb[3, 3, 0] == pytest.approx(80 / 255, abs=0.02)
    (root / "depth" / "2.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"depth/2\.png: depth file of 2\.jpg does not exist"):
        open_stream(root)
    (root / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(FileNotFoundError, match="intrinsic_depth.txt: ScanNet capture needs"):
        open_stream(root)
