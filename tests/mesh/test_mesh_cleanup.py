"""Cleanup steps with index maps; connect_scene keeps vertices and attributes and replaces faces."""
import numpy as np
import pytest
import torch
import trimesh

from trisplat.mesh.cleanup import CleanupConfig, clean_mesh, weld_vertices
from trisplat.mesh.stats import mesh_statistics


def test_weld_exact_and_with_tolerance():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 1e-7], [1, 1, 0.0]])
    assert weld_vertices(v).tolist() == [0, 1, 2, 1, 4, 5]
    assert weld_vertices(v, 1e-6).tolist() == [0, 1, 2, 1, 2, 5]
    # an unwelded square (two triangles, six vertices) becomes 4 vertices sharing an edge
    f = np.array([[0, 1, 2], [3, 5, 4]])
    attr = np.arange(6) * 10.0
    r = clean_mesh(v, f, CleanupConfig(weld_tolerance=1e-6))
    assert len(r.vertices) == 4 and r.num_welded == 2
    assert r.vertex_source.tolist() == [0, 1, 2, 5]
    assert r.vertex_map.tolist() == [0, 1, 2, 1, 2, 3]
    assert np.array_equal(r.vertices, v[r.vertex_source])
    assert attr[r.vertex_source].tolist() == [0, 10, 20, 50]
    s = mesh_statistics(r.vertices, r.faces)
    assert s.num_edges == 5 and s.boundary_edges == 4 and s.consistently_oriented
    with pytest.raises(ValueError, match="weld_tolerance"):
        weld_vertices(v, -1.0)


def test_degenerate_duplicate_and_face_source():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [1, 1, 0.0]])
    f = np.array([[0, 1, 2], [0, 0, 1], [0, 1, 3], [2, 1, 0], [1, 4, 2], [1, 4, 2]])
    r = clean_mesh(v, f, CleanupConfig(orient=False))
    assert r.num_degenerate_faces == 2  # repeated vertex; collinear (zero area)
    assert r.num_duplicate_faces == 2  # reversed copy of face 0; exact copy of face 4
    assert r.face_source.tolist() == [0, 4]
    assert np.array_equal(r.vertices[r.faces], v[f[r.face_source]])
    assert r.num_unreferenced_vertices == 1 and len(r.vertices) == 4
    kept_all = clean_mesh(v, f, CleanupConfig(orient=False, drop_unreferenced_vertices=False))
    assert len(kept_all.vertices) == 5 and kept_all.vertex_source.tolist() == [0, 1, 2, 3, 4]


def test_small_fragments_removed_by_count_and_area():
    big = trimesh.creation.icosphere(2)  # 320 faces, area ~12.5
    small = trimesh.creation.icosphere(0, radius=0.1)  # 20 faces, area ~0.12
    v = np.concatenate([big.vertices, small.vertices + 5])
    f = np.concatenate([big.faces, small.faces + len(big.vertices)])
    r = clean_mesh(v, f, CleanupConfig(min_component_faces=21))
    assert len(r.faces) == 320 and r.num_fragments == 1 and r.num_fragment_faces == 20
    assert r.vertex_source.max() < len(big.vertices)
    r = clean_mesh(v, f, CleanupConfig(min_component_area_fraction=0.02))
    assert len(r.faces) == 320
    r = clean_mesh(v, f, CleanupConfig(min_component_area_fraction=0.005))
    assert len(r.faces) == 340


def test_orientation_repaired_outward():
    s = trimesh.creation.icosphere(3)
    rng = np.random.default_rng(1)
    f = s.faces.copy()
    flip = rng.random(len(f)) < 0.3
    f[flip] = f[flip][:, ::-1]
    assert not mesh_statistics(s.vertices, f).consistently_oriented
    r = clean_mesh(s.vertices, f)
    assert r.num_flipped == flip.sum()
    assert np.array_equal(r.faces, s.faces)  # exactly the outward original
    # fully inverted sphere: every face flipped back
    r = clean_mesh(s.vertices, s.faces[:, ::-1])
    assert r.num_flipped == len(s.faces) and np.array_equal(r.faces, s.faces)


def test_orientation_by_winding_keeps_a_room_facing_into_itself():
    """A room seen from inside (a box with its normals into it, as the fusion makes them: towards the free space the
    cameras looked through), a third of its faces flipped at random: orient_by='winding' repairs it into the room,
    closed or open (without its ceiling), where the volume rule turns it out of the room, away from every camera.
    (Bonsai's final surface pass flipped 316k of 387k faces that way: the room faced away from the test views.)"""
    box = trimesh.creation.box((6.0, 6.0, 2.4))
    box = trimesh.Trimesh(box.vertices, box.faces, process=False).subdivide().subdivide()
    inward = box.faces[:, ::-1].copy()
    centroid = box.triangles_center
    ceiling = centroid[:, 2] > 1.19
    rng = np.random.default_rng(0)
    for faces in (inward, inward[~ceiling]):
        noisy = faces.copy()
        flip = rng.random(len(noisy)) < 0.33
        noisy[flip] = noisy[flip][:, ::-1]
        r = clean_mesh(box.vertices, noisy, CleanupConfig(orient_by="winding", drop_unreferenced_vertices=False))
        assert r.num_flipped == flip.sum() and np.array_equal(r.faces, faces)
        t = box.vertices[r.faces]
        normals = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        assert np.all(np.einsum("ij,ij->i", normals, -t.mean(1)) > 0)  # every face towards the room's centre
        # the volume rule (the default) turns the room out of itself
        r = clean_mesh(box.vertices, noisy, CleanupConfig(drop_unreferenced_vertices=False))
        assert np.array_equal(r.faces, faces[:, ::-1])


def test_connect_scene_keeps_vertices_and_replaces_faces():
    from trisplat.mesh.connect import ConnectConfig, connect_scene
    from trisplat.scene.model import TriangleScene

    sphere = trimesh.creation.icosphere(3)
    pts, _ = trimesh.sample.sample_surface_even(sphere, 800, seed=0)
    # a soup: one small triangle around each point, lying in the tangent plane, as a trained soup would be
    rng = np.random.default_rng(0)
    n = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    t1 = np.cross(n, rng.normal(size=(len(pts), 3)))
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    r = 0.12
    corners = np.stack([pts + r * t1, pts + r * (-0.5 * t1 + 0.87 * t2), pts + r * (-0.5 * t1 - 0.87 * t2)], 1)
    positions = corners.reshape(-1, 3)
    faces = np.arange(len(positions)).reshape(-1, 3)
    scene = TriangleScene.from_rgb(positions, faces, rng.random((len(positions), 3)), sh_degree=1)
    scene.opacity_logit.uniform_(-2, 2)
    out, rep = connect_scene(scene)
    assert out.positions is scene.positions and out.sh is scene.sh and out.opacity_logit is scene.opacity_logit
    assert out.faces.dtype == torch.int32 and out.num_faces == rep.num_faces > 0
    s = mesh_statistics(positions, out.faces.numpy())
    assert s.non_manifold_edges <= 0.01 * s.num_edges and s.consistently_oriented
    assert s.vertex_face_ratio < 1.0  # connected: far below a soup's 3.0
    compact, rep2 = connect_scene(scene, ConnectConfig(drop_unreferenced_vertices=True))
    assert compact.num_vertices == len(np.unique(out.faces.numpy()))
    assert torch.equal(compact.sh, scene.sh[torch.as_tensor(rep2.vertex_source)])
    assert torch.equal(compact.positions[compact.faces.long()], scene.positions[out.faces.long()])


def test_repair_non_manifold_edges_keeps_the_two_best_faces():
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0.87, 0], [0.5, -0.87, 0], [0.5, 0.05, 0.1], [0.5, -0.1, 2.0]])
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [0, 1, 5]])  # four faces on edge (0,1); face 2 a sliver
    assert mesh_statistics(v, f).non_manifold_edges == 1
    r = clean_mesh(v, f, CleanupConfig(repair_non_manifold_edges=True, orient=False))
    assert r.num_non_manifold_faces == 2
    assert sorted(r.face_source.tolist()) == [0, 1]  # the two equilateral faces
    assert mesh_statistics(r.vertices, r.faces).non_manifold_edges == 0


def test_oriented_repair_keeps_one_face_each_way_and_the_orientation():
    """Two closed, outward boxes touching along one edge (4 faces on it, two traversing it each way): the oriented
    repair keeps the best face in each direction, so every remaining two-face edge is traversed once each way; the
    switch's _manifold also drops both faces of a fold (two faces on the same three vertices)."""
    from trisplat.mesh.cleanup import non_manifold_excess_faces
    from trisplat.mesh.orient import edge_table
    from trisplat.train.switch import _manifold

    a = trimesh.creation.box(extents=(1, 1, 1))
    b = a.copy()
    b.apply_translation((1.0, 1.0, 0.0))  # shares the vertical edge x = y = 0.5
    v = np.vstack([a.vertices, b.vertices])
    f = np.vstack([a.faces, b.faces + len(a.vertices)])
    uniq, w = np.unique(v.round(9), axis=0, return_inverse=True)
    v, f = uniq, w.reshape(-1)[f]
    t = edge_table(f)
    assert t.edge_face_count.max() == 4
    drop = non_manifold_excess_faces(v, f, oriented=True)
    kept = f[~drop]
    assert edge_table(kept).edge_face_count.max() <= 2 and drop.sum() == 2
    assert mesh_statistics(v, kept).consistently_oriented
    # a fold on top: the same triangle twice, opposite windings, glued to the first box's top
    top = a.faces[np.argmax(a.triangles_center[:, 2])]
    fold = np.array([w.reshape(-1)[top], w.reshape(-1)[top][::-1]])
    v2, f2 = _manifold(v, np.vstack([f, fold]))
    st = mesh_statistics(v2, f2)
    assert st.non_manifold_edges == 0 and st.consistently_oriented
    assert len(f2) <= len(f) - 2  # the fold is gone, with the face it doubled


def test_closest_points_on_triangles_match_trimesh():
    import trimesh

    from trisplat.mesh.cleanup import closest_points_on_triangles

    rng = np.random.default_rng(0)
    tri = rng.normal(size=(300, 3, 3))
    p = rng.normal(size=(300, 3)) * 2
    q, d = closest_points_on_triangles(p, tri)
    for k in range(300):  # every Voronoi region of a triangle comes up among random points
        cp, dd, _ = trimesh.proximity.closest_point(trimesh.Trimesh(tri[k], [[0, 1, 2]], process=False), p[k:k + 1])
        np.testing.assert_allclose(q[k], cp[0], atol=1e-9)
        assert d[k] == pytest.approx(dd[0], abs=1e-9)


def test_weld_near_pieces_joins_what_nearly_touches_and_nothing_else():
    import trimesh

    from trisplat.mesh.cleanup import face_components, weld_near_pieces

    floor = trimesh.creation.box(extents=[2.0, 2.0, 0.2])
    box = trimesh.creation.box(extents=[0.3, 0.3, 0.3])
    box.apply_translation([0.1, 0.2, 0.1 + 0.15 + 0.01])  # 0.01 above the floor's top, over its face's interior
    lid = trimesh.creation.box(extents=[0.2, 0.2, 0.05])
    lid.apply_translation([0.1, 0.2, 0.41 + 0.025 + 0.005])  # 0.005 above the box: a chain, joined through the box
    far = trimesh.creation.box(extents=[0.3, 0.3, 0.3])
    far.apply_translation([0.0, 0.0, 3.0])
    m = trimesh.util.concatenate([floor, box, lid, far])
    v, f, joins = weld_near_pieces(m.vertices, m.faces, 0.02)
    n, label = face_components(f, len(v))
    assert n == 2 and joins == 2
    moved = np.linalg.norm(v[: len(m.vertices)] - m.vertices, axis=1)
    assert np.count_nonzero(moved) == 0  # positions unchanged: joins re-index a vertex onto a (new) split point
    assert len(v) - len(m.vertices) <= 2 and len(f) <= len(m.faces) + 4
    # nothing within reach: nothing changes
    v2, f2, joins2 = weld_near_pieces(m.vertices, m.faces, 0.001)
    assert joins2 == 0 and np.array_equal(f2, m.faces)


def test_simplify_parts_decimates_one_part_and_keeps_the_border_joined():
    from trisplat.mesh.cleanup import face_components, simplify_parts

    # a 40 x 40 grid of a gently curved sheet (2 x 1600 faces): the left half one part, the right half another
    n = 40
    ys, xs = np.mgrid[0:n + 1, 0:n + 1].astype(np.float64) / n
    v = np.stack([xs, ys, 0.05 * np.sin(3 * xs) * np.cos(2 * ys)], -1).reshape(-1, 3)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    f = np.concatenate([np.stack([i, i + 1, i + n + 1], -1).reshape(-1, 3),
                        np.stack([i + 1, i + n + 2, i + n + 1], -1).reshape(-1, 3)])
    part = (v[f].mean(1)[:, 0] > 0.5).astype(np.int64)
    v2, f2 = simplify_parts(v, f, part, [int((part == 0).sum()), 100])
    right = v2[f2].mean(1)[:, 0] > 0.5
    assert (~right).sum() == (part == 0).sum()  # the left part as it was
    assert 60 <= right.sum() <= 200  # the right part decimated (1,600 faces; its 41 locked border vertices hold ~2x)
    n_pieces, _ = face_components(f2, len(v2))
    assert n_pieces == 1  # joined again along the locked border
    # the border's vertices (x = 0.5) are all still there, at their positions
    border = v[np.abs(v[:, 0] - 0.5) < 1e-9]
    assert len(border) == n + 1 and all(np.isclose(v2, b).all(1).any() for b in border)
    # a part with a budget over its faces is left alone; faces of parts without a budget are dropped
    v3, f3 = simplify_parts(v, f, part, [10_000])
    assert len(f3) == (part == 0).sum()
