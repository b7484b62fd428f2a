"""Mesh statistics on small hand-built meshes with known answers, and the mesh-stats command."""
import json

import numpy as np
import pytest
import trimesh

from trisplat.mesh.stats import mesh_statistics

TET_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # outward


def test_tetrahedron():
    s = mesh_statistics(TET_V, TET_F)
    assert (s.num_vertices, s.num_faces, s.num_edges) == (4, 4, 6)
    assert s.vertex_face_ratio == 1.0
    assert s.valence_histogram == {3: 4} and s.valence_mean == 3.0
    assert s.boundary_edges == 0 and s.non_manifold_edges == 0
    assert s.watertight and s.consistently_oriented
    assert s.euler_characteristic == 2 and s.genus == 0 and s.connected_components == 1
    assert s.self_intersecting_edges == 0 and s.degenerate_faces == 0 and s.duplicate_faces == 0
    assert s.surface_area == pytest.approx(1.5 + np.sqrt(3) / 2)
    assert s.bbox_diagonal == pytest.approx(np.sqrt(3))
    assert trimesh.Trimesh(TET_V, TET_F).volume > 0


def test_tetrahedron_with_a_flipped_face_is_inconsistent():
    f = TET_F.copy()
    f[0] = f[0, ::-1]
    s = mesh_statistics(TET_V, f)
    assert s.watertight and not s.consistently_oriented and s.genus is None


def test_open_square():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0], [5, 5, 5]])  # one unreferenced vertex
    s = mesh_statistics(v, np.array([[0, 1, 2], [0, 2, 3]]))
    assert (s.num_faces, s.num_edges, s.num_unreferenced_vertices) == (2, 5, 1)
    assert s.boundary_edges == 4 and s.non_manifold_edges == 0
    assert s.valence_histogram == {2: 2, 3: 2} and s.valence_mean == 2.5
    assert not s.watertight and s.consistently_oriented and s.genus is None
    assert s.euler_characteristic == 1 and s.connected_components == 1
    assert s.vertex_face_ratio == 2.5
    assert s.surface_area == pytest.approx(1.0) and s.bbox_diagonal == pytest.approx(np.sqrt(2))


def test_three_faces_on_one_edge_is_non_manifold():
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1.0]])
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    s = mesh_statistics(v, f)
    assert s.num_edges == 7 and s.non_manifold_edges == 1 and s.boundary_edges == 6
    assert s.non_manifold_edge_fraction == pytest.approx(1 / 7)
    assert not s.watertight and s.connected_components == 1


def test_components_degenerate_duplicate_and_self_intersection():
    # two disjoint tetrahedra
    v = np.concatenate([TET_V, TET_V + 5])
    s = mesh_statistics(v, np.concatenate([TET_F, TET_F + 4]))
    assert s.connected_components == 2 and s.euler_characteristic == 4 and s.genus == 0
    # a degenerate and a duplicate face
    s = mesh_statistics(TET_V, np.concatenate([TET_F, [[0, 0, 1]], [TET_F[1, ::-1]]]))
    assert s.degenerate_faces == 1 and s.duplicate_faces == 1
    # two triangles piercing each other: one edge of the vertical one crosses the horizontal one
    v = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0], [0, 0, -1], [0.2, 0, 1], [-0.2, 0, 1.0]])
    s = mesh_statistics(v, np.array([[0, 1, 2], [3, 4, 5]]))
    assert s.self_intersecting_edges == 2  # edges (3,4) and (3,5) both pass through the horizontal triangle
    assert mesh_statistics(v, np.array([[0, 1, 2], [3, 4, 5]]), check_self_intersections=False
                           ).self_intersecting_edges is None


def test_closed_surfaces_known_genus():
    torus = trimesh.creation.torus(1.0, 0.3, major_sections=32, minor_sections=16)
    s = mesh_statistics(torus.vertices, torus.faces)
    assert s.watertight and s.euler_characteristic == 0 and s.genus == 1
    assert s.valence_histogram == {6: len(torus.vertices)}
    assert s.vertex_face_ratio == pytest.approx(0.5)
    assert s.self_intersecting_edges == 0


def test_bad_input():
    with pytest.raises(ValueError, match="out of range"):
        mesh_statistics(TET_V, TET_F + 1)
    with pytest.raises(ValueError, match=r"faces must be \[F,3\]"):
        mesh_statistics(TET_V, np.zeros((2, 4), int))


def test_mesh_stats_command(tmp_path, capsys):
    from trisplat.commands.mesh_stats import main

    sphere = trimesh.creation.icosphere(2)
    sphere.export(tmp_path / "s.ply")
    assert main([str(tmp_path / "s.ply")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["num_faces"] == 320 and out["watertight"] and out["genus"] == 0
    assert out["valence_histogram"] == {"5": 12, "6": 150}
    # an STL stores unwelded triangles: a soup until welded
    sphere.export(tmp_path / "s.stl")
    main([str(tmp_path / "s.stl")])
    soup = json.loads(capsys.readouterr().out)
    main([str(tmp_path / "s.stl"), "--weld-tolerance", "0"])
    welded = json.loads(capsys.readouterr().out)
    assert soup["boundary_edges"] == 3 * 320 and soup["vertex_face_ratio"] == 3.0
    assert welded["watertight"] and welded["num_vertices"] == 162
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        main([str(tmp_path / "missing.ply")])
