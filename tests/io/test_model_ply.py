"""The full model PLY: every SH band, opacity logit and floor, faces; capture frame on disk; exact reload."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData

from trisplat.io import load_model_ply, save_model_ply
from trisplat.scene.model import TriangleScene


def _scene(degree: int, V: int = 500, F: int = 800, seed: int = 0) -> TriangleScene:
    g = torch.Generator().manual_seed(seed)
    return TriangleScene(
        positions=torch.randn(V, 3, generator=g) * 1.7,
        sh=torch.randn(V, (degree + 1) ** 2, 3, generator=g),
        opacity_logit=torch.randn(V, generator=g) * 3,
        faces=torch.randint(0, V, (F, 3), generator=g, dtype=torch.int32),
        opacity_floor=0.1234567890123,
    )


def _normalization(s=0.37119, t=(1.3, -2.7, 0.44)) -> np.ndarray:
    N = np.eye(4)
    N[:3, :3] *= s
    N[:3, 3] = t
    return N


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_exact_float32_round_trip(tmp_path, degree):
    scene, N = _scene(degree), _normalization()
    save_model_ply(tmp_path / "model.ply", scene, N)
    back, N2 = load_model_ply(tmp_path / "model.ply")
    assert back.positions.dtype == torch.float32 and back.sh.dtype == torch.float32
    assert torch.equal(back.positions, scene.positions)
    assert torch.equal(back.sh, scene.sh)
    assert torch.equal(back.opacity_logit, scene.opacity_logit)
    assert torch.equal(back.faces, scene.faces)
    assert back.opacity_floor == scene.opacity_floor
    assert back.linear_light is False
    np.testing.assert_array_equal(N2, N)


def test_linear_light_round_trips_and_a_bad_value_is_named(tmp_path):
    import dataclasses

    scene, N = dataclasses.replace(_scene(1), linear_light=True), _normalization()
    save_model_ply(tmp_path / "model.ply", scene, N)
    assert load_model_ply(tmp_path / "model.ply")[0].linear_light is True
    raw = (tmp_path / "model.ply").read_bytes().replace(b"comment linear_light 1", b"comment linear_light 7")
    (tmp_path / "bad.ply").write_bytes(raw)
    with pytest.raises(ValueError, match="bad.ply: malformed header comment .*linear_light must be 0 or 1"):
        load_model_ply(tmp_path / "bad.ply")


def test_file_holds_capture_frame_and_3dgs_property_layout(tmp_path):
    scene, N = _scene(3), _normalization()
    save_model_ply(tmp_path / "model.ply", scene, N)
    v = PlyData.read(str(tmp_path / "model.ply"))["vertex"].data
    names = v.dtype.names
    assert names[:6] == ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2")
    assert sum(n.startswith("f_rest_") for n in names) == 45 and "opacity" in names
    xyz = np.column_stack([v["x"], v["y"], v["z"]])
    expected = (scene.positions.numpy().astype(np.float64) - N[:3, 3]) / N[0, 0]
    np.testing.assert_allclose(xyz, expected, rtol=1e-12, atol=1e-12)
    sh = scene.sh.numpy()
    # 3DGS order: f_rest is channel-major, f_rest_{c*(K-1) + k-1} = sh[:, k, c]
    np.testing.assert_array_equal(v["f_rest_0"], sh[:, 1, 0])
    np.testing.assert_array_equal(v["f_rest_15"], sh[:, 1, 1])
    np.testing.assert_array_equal(v["f_rest_31"], sh[:, 2, 2])
    np.testing.assert_array_equal(v["opacity"], scene.opacity_logit.numpy())


def test_rejects_rotating_normalization_and_foreign_files(tmp_path):
    scene = _scene(0)
    R = np.eye(4)
    R[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    with pytest.raises(ValueError, match="translation and one positive uniform scale"):
        save_model_ply(tmp_path / "m.ply", scene, R)
    from trisplat.io import export_mesh

    export_mesh(tmp_path / "mesh.ply", scene.positions.numpy(), scene.faces.numpy())
    with pytest.raises(ValueError, match="mesh.ply: not a trisplat model PLY"):
        load_model_ply(tmp_path / "mesh.ply")
    with pytest.raises(FileNotFoundError, match="absent.ply: no such model file"):
        load_model_ply(tmp_path / "absent.ply")


def test_truncated_sh_properties_are_reported(tmp_path):
    scene, N = _scene(1), _normalization()
    save_model_ply(tmp_path / "m.ply", scene, N)
    data = (tmp_path / "m.ply").read_bytes().replace(b"comment sh_degree 1", b"comment sh_degree 2")
    (tmp_path / "m2.ply").write_bytes(data)
    with pytest.raises(ValueError, match="m2.ply: vertex properties missing for SH degree 2: f_rest_9"):
        load_model_ply(tmp_path / "m2.ply")
