"""`trisplat mesh RUN` on a hand-made run: connected mesh written in the capture frame, statistics printed."""
import json

import numpy as np
import pytest
import trimesh

from trisplat.io import load_mesh, save_model_ply
from trisplat.scene.model import TriangleScene


def _fake_run(tmp_path):
    sphere = trimesh.creation.icosphere(3)
    pts, _ = trimesh.sample.sample_surface_even(sphere, 700, seed=4)
    rng = np.random.default_rng(0)
    n = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    t1 = np.cross(n, rng.normal(size=(len(pts), 3)))
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    r = 0.15
    corners = np.stack([pts + r * t1, pts + r * (-0.5 * t1 + 0.87 * t2), pts + r * (-0.5 * t1 - 0.87 * t2)], 1)
    positions = corners.reshape(-1, 3)
    rgb = np.clip(positions * 0.5 + 0.5, 0, 1)
    scene = TriangleScene.from_rgb(positions, np.arange(len(positions)).reshape(-1, 3), rgb)
    normalization = np.diag([0.5, 0.5, 0.5, 1.0])
    normalization[:3, 3] = [0.1, -0.2, 0.3]  # x_norm = 0.5 x_capture + t
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": str(tmp_path / "nodata")}))
    (run / "state.json").write_text(json.dumps({"finished": True, "step": 1, "total_steps": 1}))
    save_model_ply(run / "model.ply", scene, normalization)
    return run, positions, normalization, rgb


def test_mesh_command_writes_connected_mesh_in_capture_frame(tmp_path, capsys):
    from trisplat.commands.mesh import main

    run, positions, normalization, rgb = _fake_run(tmp_path)
    assert main([str(run)]) == 0
    out = json.loads(capsys.readouterr().out)
    v, f, colors = load_mesh(run / "mesh_connected.ply")
    assert len(f) == out["statistics"]["num_faces"] > 0
    assert out["statistics"]["num_unreferenced_vertices"] == 0
    st = out["statistics"]
    assert st["vertex_face_ratio"] < 0.6 and st["non_manifold_edges"] == 0  # repaired by default
    assert out["cleanup"]["num_non_manifold_faces"] > 0
    # without the repair, the raw triangulation has a few (under 1% of edges)
    assert main([str(run), "--no-repair-non-manifold", "--out", str(tmp_path / "raw.obj")]) == 0
    raw = json.loads(capsys.readouterr().out)["statistics"]
    assert 0 < raw["non_manifold_edges"] <= 0.01 * raw["num_edges"]
    assert len(load_mesh(tmp_path / "raw.obj")[1]) == raw["num_faces"] > st["num_faces"]
    # every written vertex is a model vertex, mapped to the capture frame, with its colour
    capture = (positions - normalization[:3, 3]) / 0.5
    d, idx = __import__("scipy.spatial", fromlist=["cKDTree"]).cKDTree(capture).query(v)
    assert d.max() < 1e-5
    assert np.abs(colors - rgb[idx]).max() <= 1 / 255 + 1e-6
    assert (run / "mesh_connected_stats.json").exists()


def test_mesh_command_errors(tmp_path):
    from trisplat.commands.mesh import main

    with pytest.raises(FileNotFoundError, match="not a trisplat run"):
        main([str(tmp_path)])
