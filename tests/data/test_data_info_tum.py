"""`trisplat info` output, and the TUM RGB-D reader against the Redwood reader on the same frames."""
from __future__ import annotations

import numpy as np
from conftest import shared_data

from trisplat.cli import main as cli_main
from trisplat.data import load_dataset


def test_info_fox_colmap(capsys):
    assert cli_main(["info", str(shared_data("fox") / "sparse" / "0"), "--downscale", "2"]) == 0
    out = capsys.readouterr().out
    assert "format      colmap" in out
    assert "cameras     50 (OPENCV x50; 50 undistorted to pinhole)" in out
    assert "resolution  531x947 x50" in out and "source      1080x1920 x50" in out
    assert "split       43 train, 7 test" in out and "points      13540" in out


def test_info_ngp_warns_and_bad_path_fails(capsys, tmp_path):
    assert cli_main(["info", str(shared_data("fox")), "--data-format", "ngp"]) == 0
    out = capsys.readouterr().out
    assert "format      ngp" in out and "warning     skipped 17 of 67 frames" in out
    # by default fox is read as its COLMAP model (13,540 points), saying that a transforms.json is there too
    assert cli_main(["info", str(shared_data("fox"))]) == 0
    out = capsys.readouterr().out
    assert "format      colmap" in out and "also holds transforms.json (ngp)" in out
    assert cli_main(["info", str(tmp_path / "nothing")]) == 1
    assert "nothing: capture folder does not exist" in capsys.readouterr().err


def _quat_xyzw(R):
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()  # x, y, z, w


def test_tum_layout_matches_redwood(tmp_path):
    src = shared_data("icl_rgbd")
    red = load_dataset(src, cache_dir=tmp_path / "c", normalize="none")
    root = tmp_path / "tum"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, depth, gt = ["# rgb"], ["# depth"], ["# ground truth"]
    for k, cam in enumerate(red.cameras):
        t = 100.0 + 0.1 * k
        (root / "rgb" / cam.name).symlink_to(src / "color" / cam.name)
        dname = cam.depth_path.name
        (root / "depth" / dname).symlink_to(cam.depth_path)
        rgb.append(f"{t:.4f} rgb/{cam.name}")
        depth.append(f"{t + 0.005:.4f} depth/{dname}")
        c2w = cam.camera_to_world
        q = _quat_xyzw(c2w[:3, :3])
        gt.append(f"{t - 0.003:.4f} " + " ".join(f"{v:.12f}" for v in (*c2w[:3, 3], *q)))
    rgb.append("200.0 rgb/unmatched.png")  # no depth or pose near this stamp: dropped and reported
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(depth) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    (root / "camera.json").symlink_to(src / "camera.json")
    tum = load_dataset(root, cache_dir=tmp_path / "c", normalize="none", depth_scale=1 / 1000)
    assert tum.format == "rgbd" and len(tum.cameras) == 5
    assert any("dropped 1 colour frame" in w for w in tum.warnings)
    for a, b in zip(red.cameras, tum.cameras):
        np.testing.assert_allclose(b.world_to_camera, a.world_to_camera, atol=1e-9)
        np.testing.assert_array_equal(b.K, a.K)
    np.testing.assert_array_equal(tum.load_depth(2), red.load_depth(2))
    default = load_dataset(root, cache_dir=tmp_path / "c", normalize="none")
    assert default.cameras[0].depth_scale == 1 / 5000  # TUM's own depth unit
