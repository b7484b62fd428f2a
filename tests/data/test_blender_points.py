"""Optional points3d.ply beside a Blender capture becomes SceneData.points (normalised like the cameras)."""
import numpy as np
import pytest
import trimesh

from trisplat.data import load_dataset


@pytest.fixture(scope="module")
def scene_with_points(tmp_path_factory):
    from trisplat.synth import demo_mesh, write_blender_scene

    out = tmp_path_factory.mktemp("pts") / "scene"
    return write_blender_scene(out, demo_mesh(), n_train=3, n_test=1, width=24, height=24, samples_per_pixel=1,
                               n_points=500)


def test_points_loaded_and_normalised(scene_with_points):
    data = load_dataset(scene_with_points)
    cloud = trimesh.load(scene_with_points / "points3d.ply", process=False)
    raw = np.asarray(cloud.vertices)
    assert data.points.shape == (500, 3)
    expected = (np.c_[raw, np.ones(len(raw))] @ data.normalization.T)[:, :3]
    np.testing.assert_allclose(data.points, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(data.point_colors, np.asarray(cloud.colors)[:, :3] / 255.0, atol=1e-6)


def test_corrupt_points_file_is_named(scene_with_points, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(scene_with_points, bad)
    (bad / "points3d.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    with pytest.raises(ValueError, match="points3d.ply"):
        load_dataset(bad)
