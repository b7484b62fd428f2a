"""Restricted Delaunay triangulation: closed genus-0 surface from sphere samples; degenerate inputs terminate."""
import numpy as np
import pytest
import trimesh

from trisplat.mesh.restricted_delaunay import restricted_delaunay, restricted_delaunay_report
from trisplat.mesh.stats import mesh_statistics


def fibonacci_sphere(n, radius=1.0):
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5 ** 0.5) * i
    return radius * np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)


def _assert_closed_sphere(points, faces):
    st = mesh_statistics(points, faces)
    assert st.boundary_edges == 0 and st.non_manifold_edges == 0
    assert st.watertight and st.consistently_oriented
    assert st.connected_components == 1
    assert st.euler_characteristic == 2 and st.genus == 0
    assert st.num_unreferenced_vertices == 0
    assert st.self_intersecting_edges == 0
    mesh = trimesh.Trimesh(points, faces, process=False)
    assert mesh.volume > 0  # outward orientation
    return st


def test_samples_on_soup_sphere_give_closed_genus0_mesh():
    soup = trimesh.creation.icosphere(4)
    pts, _ = trimesh.sample.sample_surface_even(soup, 1500, seed=3)
    faces, rep = restricted_delaunay_report(pts, soup.vertices, soup.faces)
    assert faces.dtype == np.int32 and faces.shape[1] == 3
    st = _assert_closed_sphere(pts, faces)
    assert st.num_faces == 2 * len(pts) - 4  # Euler for a closed genus-0 triangulation
    assert rep.num_kept_faces == len(faces) and rep.mode == "3d"


def test_soup_orientation_does_not_matter():
    soup = trimesh.creation.icosphere(3)
    rng = np.random.default_rng(0)
    flipped = soup.faces.copy()
    flip = rng.random(len(flipped)) < 0.5
    flipped[flip] = flipped[flip][:, ::-1]
    pts, _ = trimesh.sample.sample_surface_even(soup, 600, seed=1)
    a = restricted_delaunay(pts, soup.vertices, soup.faces)
    b = restricted_delaunay(pts, soup.vertices, flipped)
    assert set(map(tuple, np.sort(a, 1))) == set(map(tuple, np.sort(b, 1)))
    _assert_closed_sphere(pts, b)


def test_cospherical_points_give_their_convex_hull():
    # points exactly on a sphere are all co-spherical: every Voronoi vertex is the centre, only hull rays hit
    pts = fibonacci_sphere(800)
    soup = trimesh.creation.icosphere(3, radius=0.999)
    faces = restricted_delaunay(pts, soup.vertices, soup.faces)
    _assert_closed_sphere(pts, faces)
    hull = trimesh.convex.convex_hull(pts)
    assert len(faces) == len(hull.faces) == 2 * 800 - 4


def test_soup_covering_part_of_the_sphere_gives_open_patch():
    soup = trimesh.creation.icosphere(4)
    cap = soup.submesh([np.nonzero(soup.triangles_center[:, 2] > 0.3)[0]], append=True)
    pts, _ = trimesh.sample.sample_surface_even(soup, 1500, seed=5)
    faces = restricted_delaunay(pts, cap.vertices, cap.faces)
    st = mesh_statistics(pts, faces)
    assert st.boundary_edges > 0 and st.non_manifold_edges == 0 and st.consistently_oriented
    centres = pts[faces].mean(axis=1)
    assert centres[:, 2].min() > 0.15  # kept faces lie over the cap only
    normals = np.cross(pts[faces[:, 1]] - pts[faces[:, 0]], pts[faces[:, 2]] - pts[faces[:, 0]])
    assert np.all(np.einsum("ij,ij->i", normals, centres) > 0)  # outward (agrees with the soup normals)


def test_coplanar_points_give_planar_triangulation_under_the_soup():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (400, 2))
    pts = np.c_[xy, np.zeros(400)]
    soup_v = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0.0]])
    soup_f = np.array([[0, 1, 2], [0, 2, 3]])
    faces, rep = restricted_delaunay_report(pts, soup_v, soup_f)
    assert rep.mode == "planar"
    assert len(faces) > 50
    st = mesh_statistics(pts, faces)
    assert st.non_manifold_edges == 0 and st.connected_components == 1 and st.consistently_oriented
    # every kept face's circumcentre lies under the square soup; the 2D Delaunay has no overlapping faces
    assert abs(st.surface_area - 1.0) < 0.35
    centres = pts[faces].mean(axis=1)
    assert np.all(np.abs(centres[:, :2]) < 0.75)


def test_duplicates_and_degenerate_inputs_terminate():
    soup = trimesh.creation.icosphere(3)
    pts, _ = trimesh.sample.sample_surface_even(soup, 500, seed=2)
    dup = np.concatenate([pts, pts[:100]])  # 100 exact duplicates
    faces, rep = restricted_delaunay_report(dup, soup.vertices, soup.faces)
    assert faces.max() < len(dup)
    assert rep.num_unused_vertices >= 100
    # the duplicates are never used twice: the result is the same surface as without them
    st = mesh_statistics(dup, faces)
    assert st.watertight and st.genus == 0
    # collinear, too few points, empty soup
    line = np.c_[np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)]
    f, r = restricted_delaunay_report(line, soup.vertices, soup.faces)
    assert f.shape == (0, 3) and r.mode == "collinear"
    f, r = restricted_delaunay_report(pts[:3], soup.vertices, soup.faces)
    assert f.shape == (0, 3) and r.mode == "too-few-points"
    f = restricted_delaunay(pts, np.zeros((0, 3)), np.zeros((0, 3), int))
    assert f.shape == (0, 3)
    # a regular grid: many co-spherical groups of 8 points
    g = np.stack(np.meshgrid(*[np.linspace(-1, 1, 8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    box = trimesh.creation.box(extents=(1.3, 1.3, 1.3))
    f = restricted_delaunay(g, box.vertices, box.faces)
    assert len(f) > 0 and f.max() < len(g)


def test_bad_input_is_rejected_precisely():
    soup = trimesh.creation.icosphere(1)
    with pytest.raises(ValueError, match=r"vertices must be \[V,3\]"):
        restricted_delaunay(np.zeros((10, 2)), soup.vertices, soup.faces)
    with pytest.raises(ValueError, match="non-finite"):
        restricted_delaunay(np.full((10, 3), np.nan), soup.vertices, soup.faces)
    with pytest.raises(ValueError, match="out of range"):
        restricted_delaunay(np.random.rand(10, 3), soup.vertices, soup.faces + 1000)


def test_points_on_flat_facets_give_closed_mesh():
    # samples on a cube's faces: large exactly coplanar groups (the degenerate case of low-poly ground truth)
    box = trimesh.creation.box(extents=(1, 1, 1))
    pts, _ = trimesh.sample.sample_surface_even(box, 3000, seed=0)
    faces, rep = restricted_delaunay_report(pts, box.vertices, box.faces)
    assert rep.num_flat_tets > 0
    st = _assert_closed_sphere(pts, faces)
    assert st.num_faces == 2 * len(pts) - 4


def test_spot_samples_give_closed_genus0_mesh():
    from conftest import shared_data

    spot = trimesh.load(shared_data("meshes/spot_triangulated.obj"), force="mesh")
    pts, _ = trimesh.sample.sample_surface_even(spot, 20000, seed=0)
    faces = restricted_delaunay(pts, spot.vertices, spot.faces)
    _assert_closed_sphere(pts, faces)


def test_qhull_failure_falls_back_to_joggle(monkeypatch):
    import trisplat.mesh.restricted_delaunay as rd

    monkeypatch.setattr(rd, "QHULL_OPTIONS", "Qbb Qc Qz Q12 Qnot-an-option")  # makes Qhull raise
    soup = trimesh.creation.icosphere(3)
    pts, _ = trimesh.sample.sample_surface_even(soup, 600, seed=2)
    faces, rep = rd.restricted_delaunay_report(pts, soup.vertices, soup.faces)
    assert rep.joggled and rep.qhull_options == rd.QHULL_JOGGLE_OPTIONS
    assert any("retried with joggle" in n for n in rep.notes)
    _assert_closed_sphere(pts, faces)
