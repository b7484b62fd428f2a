"""The compiled BVH segment query agrees with the brute-force numpy twin."""
import numpy as np
import pytest
import trimesh

from trisplat.mesh.bvh import build_bvh, segment_any_hit, segment_any_hit_reference


def _random_case(seed, n_tri=300, n_seg=2000):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1, 1, (n_tri, 3))
    verts = (centres[:, None, :] + rng.normal(0, 0.15, (n_tri, 3, 3))).reshape(-1, 3)
    faces = np.arange(3 * n_tri).reshape(-1, 3)
    p0 = rng.uniform(-1.2, 1.2, (n_seg, 3))
    p1 = p0 + rng.normal(0, 0.3, (n_seg, 3))
    return verts, faces, p0, p1


def test_bvh_matches_brute_force():
    for seed in range(3):
        verts, faces, p0, p1 = _random_case(seed)
        got = segment_any_hit(build_bvh(verts, faces), p0, p1)
        ref = segment_any_hit_reference(verts, faces, p0, p1)
        assert np.array_equal(got >= 0, ref >= 0)
        assert 0.05 < np.mean(ref >= 0) < 0.95  # the case exercises both answers
        # the triangle returned is itself a genuine hit of that segment
        hit = np.nonzero(got >= 0)[0]
        one = np.array([segment_any_hit_reference(verts, faces[[got[i]]], p0[[i]], p1[[i]])[0] for i in hit])
        assert np.all(one == 0)


def test_exclusion_skips_triangles_using_the_vertex():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    faces = np.array([[0, 1, 2]])
    p0, p1 = np.array([[0.2, 0.2, -1.0]]), np.array([[0.2, 0.2, 1.0]])
    bvh = build_bvh(verts, faces)
    assert segment_any_hit(bvh, p0, p1)[0] == 0
    assert segment_any_hit(bvh, p0, p1, exclude=np.array([[3, 1]]))[0] == -1
    assert segment_any_hit(bvh, p0, p1, exclude=np.array([[3, -1]]))[0] == 0
    # segment ending just short of the plane misses; zero-length and in-plane segments never hit
    assert segment_any_hit(bvh, p0, np.array([[0.2, 0.2, -1e-6]]))[0] == -1
    assert segment_any_hit(bvh, p0, p0)[0] == -1
    assert segment_any_hit(bvh, np.array([[-1, 0.2, 0.0]]), np.array([[2, 0.2, 0.0]]))[0] == -1


def test_bvh_on_many_triangles_matches_trimesh_ray_count():
    sphere = trimesh.creation.icosphere(5)  # 20480 faces, > many leaves
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    inside = d * rng.uniform(0, 0.9, (500, 1))
    bvh = build_bvh(sphere.vertices, sphere.faces)
    assert np.all(segment_any_hit(bvh, inside, inside + 2 * d) >= 0)  # every ray from inside leaves the sphere
    assert np.all(segment_any_hit(bvh, inside, inside + 0.05 * d) < 0)  # too short to reach the surface
    assert np.all(segment_any_hit(bvh, 1.5 * d, 3 * d) < 0)  # wholly outside


def test_nearest_other_triangle_matches_brute_force():
    from trisplat.mesh.bvh import build_bvh, nearest_other_triangle
    from trisplat.mesh.cleanup import closest_points_on_triangles

    rng = np.random.default_rng(3)
    verts = rng.normal(size=(300, 3))
    faces = rng.integers(0, 300, size=(200, 3))
    group = rng.integers(0, 4, size=200)  # the triangles' groups
    pts = rng.normal(size=(150, 3)) * 1.2
    pgroup = rng.integers(0, 4, size=150)
    for max_d in (np.inf, 0.3):
        t, d, q = nearest_other_triangle(build_bvh(verts, faces), pts, pgroup, group, max_d)
        tri = verts[faces]
        for i in range(len(pts)):
            other = np.nonzero(group != pgroup[i])[0]
            qq, dd = closest_points_on_triangles(np.repeat(pts[i:i + 1], len(other), 0), tri[other])
            k = int(np.argmin(dd))
            if dd[k] > max_d:
                assert t[i] == -1 and np.isinf(d[i])
            else:
                assert d[i] == pytest.approx(dd[k], abs=1e-12) and group[t[i]] != pgroup[i]
                np.testing.assert_allclose(q[i], qq[k], atol=1e-9)
