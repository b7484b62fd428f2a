"""Initial triangles: Delaunay faces (known counts, orientation, degenerate sets), soup sizes, random bounds."""
from __future__ import annotations

import time

import numpy as np
import pytest
import torch
from conftest import shared_data

from trisplat.scene.init import (
    SOUP_SIZE_FACTOR,
    TSPLUS_OPACITY,
    init_delaunay,
    init_random,
    init_soup,
    initial_scene,
    point_normals,
    tetra_faces,
)


def face_normals(pos, faces):
    a, b, c = pos[faces[:, 0]], pos[faces[:, 1]], pos[faces[:, 2]]
    return np.cross(b - a, c - a)


def test_tetrahedron_with_interior_point_known_faces():
    # 4 tetrahedron corners + 1 interior point: 4 tetrahedra, 4 hull faces + 6 interior faces
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.2, 0.2, 0.2]], dtype=float)
    scene, report = init_delaunay(pts, sh_degree=0)
    assert (report.vertices, report.faces) == (5, 10)
    faces = scene.faces.numpy()
    assert len({tuple(sorted(f)) for f in faces}) == 10
    # every face not touching the interior point is a hull face, oriented outwards
    pos = scene.positions.numpy().astype(np.float64)
    hull = faces[(faces != 4).all(1)]
    assert len(hull) == 4
    n = face_normals(pos, hull)
    centroid = pos[:4].mean(0)
    assert (np.einsum("ij,ij->i", n, pos[hull[:, 0]] - centroid) > 0).all()


def test_delaunay_face_count_matches_tetrahedra_and_hull():
    from scipy.spatial import ConvexHull, Delaunay

    rng = np.random.default_rng(1)
    pts = rng.random((400, 3))
    scene, report = init_delaunay(pts, rng.random((400, 3)), sh_degree=3)
    T = len(Delaunay(pts).simplices)
    H = len(ConvexHull(pts).simplices)
    assert report.faces == (4 * T + H) // 2  # each interior face is shared by two tetrahedra
    # hull faces point away from the centroid
    hull = {tuple(sorted(f)) for f in ConvexHull(pts).simplices}
    faces = scene.faces.numpy()
    is_hull = np.array([tuple(sorted(f)) in hull for f in faces])
    pos = scene.positions.numpy().astype(np.float64)
    n = face_normals(pos, faces[is_hull])
    assert is_hull.sum() == H
    assert (np.einsum("ij,ij->i", n, pos[faces[is_hull, 0]] - pts.mean(0)) > 0).all()


def test_delaunay_attributes_colours_opacity_sh():
    rng = np.random.default_rng(2)
    pts, cols = rng.random((50, 3)), rng.random((50, 3))
    scene, _ = init_delaunay(pts, cols, sh_degree=3)
    assert scene.sh.shape == (50, 16, 3) and scene.sh_degree == 3
    assert torch.all(scene.sh[:, 1:] == 0)
    np.testing.assert_allclose(scene.base_colors().numpy(), cols, atol=1e-5)
    np.testing.assert_allclose(scene.opacities().numpy(), TSPLUS_OPACITY, atol=1e-6)
    np.testing.assert_allclose(scene.positions.numpy(), pts, atol=1e-6)


def test_delaunay_deduplicates():
    rng = np.random.default_rng(3)
    pts = rng.random((300, 3))
    ref, _ = init_delaunay(pts)
    noisy = np.concatenate([pts, pts, pts + 1e-12, [[np.nan, 0, 0], [np.inf, 1, 1]]])
    scene, report = init_delaunay(noisy)
    assert report.duplicates_removed == 600 and report.nonfinite_removed == 2
    assert report.faces == ref.num_faces and report.vertices == 300
    assert "600 duplicate points merged" in report.summary()


@pytest.mark.parametrize("kind", ["plane", "line", "grid_plane", "big_plane"])
def test_delaunay_survives_flat_sets(kind):
    rng = np.random.default_rng(4)
    if kind == "plane":
        pts = rng.random((500, 3)) * [1, 1, 0] + [0, 0, 2]
    elif kind == "line":
        pts = np.outer(np.linspace(0, 1, 200), [1, 2, 3])
    elif kind == "grid_plane":  # cospherical + coplanar: the classic Qhull trouble
        g = np.stack(np.meshgrid(np.arange(30.0), np.arange(30.0)), -1).reshape(-1, 2)
        pts = np.c_[g, np.zeros(len(g))]
    else:
        pts = rng.random((20_000, 3)) * [1, 1, 0]
    t = time.perf_counter()
    scene, report = init_delaunay(pts)
    assert time.perf_counter() - t < 30
    assert report.jittered and report.faces > 0 and "jittered" in report.summary()
    pos = scene.positions.numpy()
    assert np.isfinite(pos).all()
    # vertices keep their original (un-jittered) positions
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(pts).query(pos.astype(np.float64))
    assert dist.max() < 1e-5 * np.ptp(pts, axis=0).max()
    assert scene.faces.max() < scene.num_vertices and scene.faces.min() >= 0


@pytest.mark.parametrize("pts", [np.zeros((10, 3)), np.eye(3), np.array([[0, 0, 0], [1, 1, 1.0]])])
def test_delaunay_too_few_points_falls_back_to_soup(pts):
    scene, report = init_delaunay(pts)
    distinct = len(np.unique(pts, axis=0))
    assert report.fallback and "soup" in report.fallback
    assert report.faces == distinct and report.vertices == 3 * distinct


def test_empty_input_is_an_error():
    with pytest.raises(ValueError, match="empty point set"):
        init_delaunay(np.full((4, 3), np.nan))


def test_tetra_faces_orientation_independent_of_vertex_order():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    for perm in ([0, 1, 2, 3], [3, 2, 1, 0], [1, 0, 2, 3]):
        faces = tetra_faces(np.array([perm]), pts)
        n = face_normals(pts, faces)
        assert (np.einsum("ij,ij->i", n, pts[faces[:, 0]] - pts.mean(0)) > 0).all()


def test_soup_sizes_and_shape():
    g = np.stack(np.meshgrid(np.arange(8.0), np.arange(8.0), np.arange(8.0)), -1).reshape(-1, 3)
    scene, report = init_soup(g, np.full((len(g), 3), 0.25), seed=5)
    assert (report.faces, report.vertices) == (512, 1536)
    tri = scene.positions.numpy().astype(np.float64)[scene.faces.numpy()]
    np.testing.assert_allclose(tri.mean(1), g, atol=1e-5)  # centred on the points
    # unit grid: the 3 nearest neighbours are at distance 1, so the circumradius is 2.23
    np.testing.assert_allclose(np.linalg.norm(tri - tri.mean(1, keepdims=True), axis=2), SOUP_SIZE_FACTOR, rtol=1e-5)
    sides = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
    np.testing.assert_allclose(sides, SOUP_SIZE_FACTOR * np.sqrt(3), rtol=1e-5)  # equilateral
    normals = face_normals(scene.positions.numpy(), scene.faces.numpy())
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    assert np.abs(normals.mean(0)).max() < 0.15  # random orientations
    again, _ = init_soup(g, seed=5)
    assert torch.equal(again.positions, scene.positions)


def test_point_normals_on_planes_and_not_on_blobs():
    rng = np.random.default_rng(0)
    # a wall (x = 2) and a floor (z = 0), with a little noise, and an isotropic blob with no plane
    wall = np.c_[np.full(300, 2.0), rng.uniform(-1, 1, 300), rng.uniform(0, 2, 300)]
    floor = np.c_[rng.uniform(-1, 1, 300), rng.uniform(-1, 1, 300), np.zeros(300)]
    wall[:, 0] += rng.normal(0, 0.01, 300)
    blob = rng.normal(size=(300, 3)) * 0.2 + [-5, 0, 0]
    n = point_normals(np.concatenate([wall, floor, blob]))
    assert np.isfinite(n[:600]).all() and np.isnan(n[600:]).mean() > 0.9
    np.testing.assert_allclose(np.abs(n[:300, 0]), 1.0, atol=0.02)  # the wall's normal is +-x
    np.testing.assert_allclose(np.abs(n[300:600, 2]), 1.0, atol=0.02)  # the floor's, +-z
    np.testing.assert_allclose(np.linalg.norm(n[:600], axis=1), 1.0, atol=1e-9)
    assert np.isnan(point_normals(np.zeros((3, 3)))).all()  # too few points: no normal


def test_unbounded_soup_lies_in_its_points_planes(tmp_path):
    """A room seen from inside seeds a soup (method 'auto'); with soup_planes its triangles on the walls and floor
    lie in the planes of their points, not at random angles (a layer as thick as the triangles are wide: issue 49's
    walls in front of the truth). Fails with randomly oriented triangles (mean |cos| to the plane's normal about
    0.5)."""
    from trisplat.data import load_dataset
    from trisplat.synth.room import write_room_scene

    room = write_room_scene(tmp_path / "room", n_views=8, width=32, height=24, samples_per_pixel=1, n_points=1500)
    data = load_dataset(room, cache_dir=tmp_path / "cache", prepare="lazy")
    scene, report = initial_scene(data, method="auto", sh_degree=0, soup_planes=True)
    assert report.method == "soup" and "in their local plane" in report.summary()
    tri = scene.positions.numpy().astype(np.float64)[scene.faces.numpy()]
    normals = face_normals(scene.positions.numpy().astype(np.float64), scene.faces.numpy())
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # the true room in the normalised frame: floor at the lowest points, walls at the extreme x
    world = np.linalg.inv(np.asarray(data.normalization, np.float64))
    c = tri.mean(1) @ world[:3, :3].T + world[:3, 3]
    n_world = normals @ world[:3, :3].T
    n_world /= np.linalg.norm(n_world, axis=1, keepdims=True)
    floor = np.abs(c[:, 2]) < 0.05
    walls = np.abs(np.abs(c[:, 0]) - 3.0) < 0.05
    assert floor.sum() > 100 and walls.sum() > 100
    assert np.median(np.abs(n_world[floor, 2])) > 0.97
    assert np.median(np.abs(n_world[walls, 0])) > 0.97
    _, plain = initial_scene(data, method="auto", sh_degree=0)  # off by default: TS v1's random angles
    assert "in their local plane" not in plain.summary()


def test_random_init_inside_bounds():
    scene, report = init_random([-1, 0, 2], [1, 0.5, 3], n=500, seed=3, sh_degree=1)
    assert report.method == "random" and report.faces == 500 and scene.sh.shape == (1500, 4, 3)
    centroids = scene.positions.numpy()[scene.faces.numpy()].mean(1)
    assert (centroids >= [-1, 0, 2]).all() and (centroids <= [1, 0.5, 3]).all()
    with pytest.raises(ValueError, match="max > min"):
        init_random([0, 0, 0], [1, 0, 1])


def test_initial_scene_on_captures(tmp_path):
    from trisplat.data import load_dataset

    lego = load_dataset(shared_data("lego"), downscale=8, cache_dir=tmp_path, prepare="lazy")
    scene, report = initial_scene(lego, method="random", random_points=2000, sh_degree=2)
    assert report.method == "random" and scene.num_faces == 2000 and scene.sh_degree == 2
    centroids = scene.positions.numpy()[scene.faces.numpy()].mean(1)
    assert (centroids >= lego.bounds[0] - 1e-6).all() and (centroids <= lego.bounds[1] + 1e-6).all()
    # lego: [-1.5, 1.5]^3 of its own frame
    lo = (lego.normalization @ np.array([-1.5, -1.5, -1.5, 1.0]))[:3]
    np.testing.assert_allclose(lego.bounds[0], lo)

    fox = load_dataset(shared_data("fox") / "sparse" / "0", downscale=8, cache_dir=tmp_path, prepare="lazy")
    scene, report = initial_scene(fox, sh_degree=3)
    distinct = len(np.unique(fox.points, axis=0))  # the float32 cloud has a few exact duplicates
    assert report.method == "delaunay" and report.duplicates_removed == 13540 - distinct
    assert report.vertices == distinct and report.faces > 5 * distinct
    scene, report = initial_scene(fox, method="soup", max_points=1000)
    assert report.subsampled_from == distinct and report.faces == 1000
    with pytest.raises(ValueError, match="needs points"):
        initial_scene(lego, method="delaunay")
    # MeshSplatting's soup on a capture without points: seeded on the visual hull of the silhouettes
    scene, report = initial_scene(lego, method="soup", random_points=300, sh_degree=0)
    assert report.method == "soup" and "visual hull" in report.summary()
    assert scene.num_faces == 300 and scene.num_vertices == 900  # a soup: three private vertices per face
