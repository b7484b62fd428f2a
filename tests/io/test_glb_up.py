"""GLB files are Y-up by default (glTF defines +Y as up; engines showed Z-up captures on their side); PLY and OBJ
keep the capture's frame; --up overrides either way."""
from __future__ import annotations

import json

import numpy as np
import pytest

from trisplat.io import export_mesh, load_mesh

TRI = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], np.float32)  # spans x and z (z up)
FACES = np.array([[0, 1, 2]], np.int32)


def test_glb_is_y_up_by_default_and_other_formats_keep_the_frame(tmp_path):
    export_mesh(tmp_path / "m.glb", TRI, FACES)
    export_mesh(tmp_path / "m.ply", TRI, FACES)
    glb, _, _ = load_mesh(tmp_path / "m.glb")
    np.testing.assert_allclose(glb[2], [0, 1, 0], atol=1e-6)  # the capture's +Z (up) is glTF's +Y
    np.testing.assert_allclose(load_mesh(tmp_path / "m.ply")[0], TRI)
    # a known capture up (here +Y already) is used instead of the Z-up assumption
    export_mesh(tmp_path / "y.glb", TRI, FACES, capture_up=np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(load_mesh(tmp_path / "y.glb")[0], TRI, atol=1e-6)
    # overrides: the capture's own axes, or +Z
    export_mesh(tmp_path / "keep.glb", TRI, FACES, up=None)
    np.testing.assert_allclose(load_mesh(tmp_path / "keep.glb")[0], TRI)
    export_mesh(tmp_path / "z.ply", TRI, FACES, up="z", capture_up=np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(load_mesh(tmp_path / "z.ply")[0], TRI, atol=1e-6)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A Blender capture (Z-up, cameras upright) and a 'finished' run whose model is the true mesh."""
    from trisplat.data import load_dataset
    from trisplat.io import save_model_ply
    from trisplat.scene.model import TriangleScene
    from trisplat.synth import demo_mesh, write_blender_scene

    root = tmp_path_factory.mktemp("glb")
    mesh = demo_mesh()
    capture = write_blender_scene(root / "capture", mesh, n_train=4, n_test=1, width=16, height=16,
                                  samples_per_pixel=1, n_points=0, elevation_deg=(10, 30))
    data = load_dataset(capture)
    run = root / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": str(capture), "data_options": {}}))
    (run / "state.json").write_text(json.dumps({"finished": True, "step": 1, "total_steps": 1}))
    N = data.normalization
    save_model_ply(run / "model.ply", TriangleScene.from_rgb(mesh.vertices @ N[:3, :3].T + N[:3, 3], mesh.faces,
                                                             np.full((len(mesh.vertices), 3), 0.5)), N)
    return run, data


def _y_up(p):
    return p[:, [0, 2, 1]] * [1, 1, -1]  # Z-up -> Y-up: (x, y, z) -> (x, z, -y)


def test_export_and_mesh_commands_write_y_up_glb(run, tmp_path):
    from trisplat.cli import main

    run_dir, data = run
    assert main(["export", str(run_dir), "--formats", "ply", "glb", "--out", str(tmp_path / "a")]) == 0
    ply, glb = load_mesh(tmp_path / "a" / "mesh.ply")[0], load_mesh(tmp_path / "a" / "mesh.glb")[0]
    np.testing.assert_allclose(glb, _y_up(ply), atol=1e-5)
    assert main(["export", str(run_dir), "--formats", "glb", "--up", "capture", "--out", str(tmp_path / "b")]) == 0
    np.testing.assert_allclose(load_mesh(tmp_path / "b" / "mesh.glb")[0], ply, atol=1e-5)
    assert main(["mesh", str(run_dir), "--out", str(tmp_path / "g.glb")]) == 0
    assert main(["mesh", str(run_dir), "--out", str(tmp_path / "p.ply")]) == 0
    np.testing.assert_allclose(load_mesh(tmp_path / "g.glb")[0], _y_up(load_mesh(tmp_path / "p.ply")[0]), atol=1e-5)


def test_a_trained_runs_mesh_glb_is_y_up(run, tmp_path):
    from trisplat.io import estimate_capture_up
    from trisplat.run import open_run
    from trisplat.train.outputs import write_model_files

    run_dir, data = run
    scene, N = open_run(run_dir).load_model()
    up = estimate_capture_up([data.cameras[int(i)] for i in data.train_indices])
    np.testing.assert_allclose(up, [0, 0, 1])  # Blender captures are Z-up
    write_model_files(tmp_path, scene, N, up)
    np.testing.assert_allclose(load_mesh(tmp_path / "mesh.glb")[0], _y_up(load_mesh(tmp_path / "mesh.ply")[0]),
                               atol=1e-5)
