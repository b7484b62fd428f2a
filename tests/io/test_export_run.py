"""`export_run` and `trisplat export`: meshes in the capture frame, the model PLY, no silent overwrites."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from trisplat.commands.export import main as export_main
from trisplat.io import export_run, load_mesh, load_model_ply, save_model_ply
from trisplat.scene.model import TriangleScene
from trisplat.scene.sh import C0


@pytest.fixture
def run_dir(tmp_path):
    """A finished run folder holding only config.json and model.ply (a coloured sphere, normalised frame)."""
    m = trimesh.creation.icosphere(subdivisions=2)
    rgb = np.random.default_rng(0).random((len(m.vertices), 3)).astype(np.float32)
    scene = TriangleScene.from_rgb(m.vertices.astype(np.float32) * 0.5, m.faces, rgb, opacity=0.9, sh_degree=2)
    N = np.eye(4)
    N[:3, :3] *= 0.25
    N[:3, 3] = [0.5, -1.0, 2.0]
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": str(tmp_path / "no_capture_here")}))
    (run / "state.json").write_text(json.dumps({"finished": True, "step": 10, "total_steps": 10}))
    save_model_ply(run / "model.ply", scene, N)
    return run, scene, N, rgb


def test_export_run_writes_capture_frame_meshes(run_dir, tmp_path):
    run, scene, N, rgb = run_dir
    out = tmp_path / "out"
    written = export_run(run, formats=("ply", "obj", "glb", "model"), out_dir=out)
    assert sorted(p.name for p in written) == ["mesh.glb", "mesh.mtl", "mesh.obj", "mesh.ply", "model.ply"]
    capture = (scene.positions.numpy().astype(np.float64) - N[:3, 3]) / N[0, 0]
    expected_rgb = np.clip(C0 * scene.sh[:, 0, :].numpy() + 0.5, 0, 1)
    np.testing.assert_allclose(expected_rgb, rgb, atol=1e-6)
    for name in ("mesh.ply", "mesh.obj", "mesh.glb"):
        p, f, c = load_mesh(out / name)
        # glTF is Y-up by definition: the GLB turns the capture's up (here the default, +Z) to +Y
        expected = capture[:, [0, 2, 1]] * [1, 1, -1] if name == "mesh.glb" else capture
        np.testing.assert_allclose(p, expected, rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(f, scene.faces.numpy())
        assert np.abs(c - rgb).max() <= 0.5 / 255 + 1e-6
    back, N2 = load_model_ply(out / "model.ply")
    assert torch.equal(back.sh, scene.sh) and torch.equal(back.positions, scene.positions)


def test_export_up_without_cameras_warns_and_uses_default(run_dir, tmp_path):
    run, scene, N, _ = run_dir
    with pytest.warns(UserWarning, match="assuming the default up axis"):
        export_run(run, formats=("ply",), up="y", out_dir=tmp_path / "o")
    p, _, _ = load_mesh(tmp_path / "o" / "mesh.ply")
    capture = (scene.positions.numpy().astype(np.float64) - N[:3, 3]) / N[0, 0]
    np.testing.assert_allclose(p, capture[:, [0, 2, 1]] * [1, 1, -1], atol=1e-5)


def test_cli_refuses_to_overwrite_without_force(run_dir, capsys):
    run, *_ = run_dir
    assert export_main([str(run), "--formats", "ply", "glb"]) == 0
    assert (run / "export" / "mesh.ply").is_file() and (run / "export" / "mesh.glb").is_file()
    before = (run / "export" / "mesh.ply").stat().st_mtime_ns
    (run / "export" / "mesh.ply").write_bytes(b"user's own file")
    assert export_main([str(run), "--formats", "ply"]) == 1
    err = capsys.readouterr().err
    assert "would overwrite" in err and "mesh.ply" in err and "--force" in err
    assert (run / "export" / "mesh.ply").read_bytes() == b"user's own file"
    assert export_main([str(run), "--formats", "ply", "--force"]) == 0
    assert (run / "export" / "mesh.ply").stat().st_mtime_ns >= before
    load_mesh(run / "export" / "mesh.ply")


def test_unknown_format_and_missing_run(tmp_path, run_dir):
    run, *_ = run_dir
    with pytest.raises(ValueError, match="unknown export format 'stl'"):
        export_run(run, formats=("stl",))
    with pytest.raises(FileNotFoundError, match="not a trisplat run"):
        export_run(tmp_path / "nothing")
