"""Geometry metrics on cases with known answers: identical, offset planes, partial coverage, normals."""
import json

import numpy as np
import pytest
import trimesh

from trisplat.eval.geometry import Surface, compare_surfaces, load_surface

SQUARE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def test_mesh_against_itself_is_zero():
    s = trimesh.creation.icosphere(3)
    m = compare_surfaces(Surface(s.vertices, s.faces), Surface(s.vertices, s.faces), threshold=1e-3, samples=20000)
    assert m.accuracy == 0 and m.completeness == 0 and m.chamfer == 0
    assert m.precision == m.recall == m.fscore == 1.0
    assert m.normal_consistency == pytest.approx(1.0)


@pytest.mark.parametrize("d", [0.01, 0.1])
def test_plane_offset_along_normal_gives_d(d):
    pred = Surface(SQUARE_V, SQUARE_F)
    gt = Surface(SQUARE_V + [0, 0, d], SQUARE_F)
    m = compare_surfaces(pred, gt, threshold=1.5 * d, samples=20000)
    assert m.accuracy == pytest.approx(d, rel=1e-9)
    assert m.completeness == pytest.approx(d, rel=1e-9)
    assert m.chamfer == pytest.approx(d, rel=1e-9)
    assert m.fscore == 1.0
    m = compare_surfaces(pred, gt, threshold=0.5 * d, samples=20000)
    assert m.precision == m.recall == m.fscore == 0.0
    assert m.gt_bbox_diagonal == pytest.approx(np.sqrt(2 + 0 * d))
    assert m.chamfer_over_diagonal == pytest.approx(d / np.sqrt(2), rel=1e-9)


def test_partial_prediction_separates_accuracy_and_completeness():
    # pred covers x in [0, 0.5]; gt the whole unit square. Missing half: mean distance to the cut = 0.25, so
    # completeness = 0.5 * 0.25 = 0.125; accuracy ~ 0 (sample spacing only); recall at 0.05 = 0.55.
    half_v = SQUARE_V * [0.5, 1, 1]
    m = compare_surfaces(Surface(half_v, SQUARE_F), Surface(SQUARE_V, SQUARE_F), threshold=0.05, samples=100_000)
    assert m.accuracy < 0.003
    assert m.completeness == pytest.approx(0.125, abs=0.003)
    assert m.precision == 1.0
    assert m.recall == pytest.approx(0.55, abs=0.01)
    assert m.fscore == pytest.approx(2 * m.precision * m.recall / (m.precision + m.recall))


def test_point_cloud_ground_truth_and_normal_consistency():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.random((5000, 2)), np.zeros(5000)]
    pred = Surface(SQUARE_V + [0, 0, 0.02], SQUARE_F)
    m = compare_surfaces(pred, Surface(pts, None, np.tile([0, 0, -1.0], (5000, 1))), threshold=0.05, samples=5000)
    assert m.normal_consistency == pytest.approx(1.0)  # orientation-agnostic
    assert m.completeness == pytest.approx(0.02, abs=0.004)
    m = compare_surfaces(pred, Surface(pts, None, np.tile([1.0, 0, 0], (5000, 1))), samples=5000)
    assert m.normal_consistency == pytest.approx(0.0, abs=1e-12)
    assert compare_surfaces(pred, Surface(pts), samples=5000).normal_consistency is None
    # default threshold: 1% of the GT diagonal
    assert compare_surfaces(pred, Surface(pts), samples=5000).threshold == pytest.approx(
        0.01 * np.linalg.norm(pts.max(0) - pts.min(0)))


def test_concentric_spheres_chamfer_is_radius_gap():
    gt_pts = trimesh.creation.icosphere(6).vertices  # 40962 points exactly on the unit sphere
    pred = trimesh.creation.icosphere(6, radius=1.1)
    m = compare_surfaces(Surface(pred.vertices, pred.faces), Surface(gt_pts), threshold=0.2, samples=40000)
    # flat facets of the radius-1.1 icosphere sit up to ~0.1% inside the sphere; sample spacing adds ~0.005
    assert m.accuracy == pytest.approx(0.1, abs=0.006)
    assert m.completeness == pytest.approx(0.1, abs=0.006)


def test_load_surface_and_compare_mesh_command(tmp_path, capsys):
    from trisplat.commands.compare_mesh import main

    s = trimesh.creation.icosphere(2)
    s.export(tmp_path / "a.ply")
    trimesh.Trimesh(s.vertices * 1.05, s.faces).export(tmp_path / "b.obj")
    trimesh.PointCloud(s.vertices).export(tmp_path / "c.ply")
    assert load_surface(tmp_path / "c.ply").faces is None
    assert main([str(tmp_path / "a.ply"), str(tmp_path / "b.obj"), "--threshold", "0.1", "--samples", "3000"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) >= {"accuracy", "completeness", "chamfer", "precision", "recall", "fscore", "normal_consistency"}
    assert out["fscore"] == 1.0 and 0.03 < out["chamfer"] < 0.05
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        load_surface(tmp_path / "nope.ply")
    (tmp_path / "bad.ply").write_text("not a ply")
    with pytest.raises(ValueError, match="bad.ply"):
        load_surface(tmp_path / "bad.ply")
