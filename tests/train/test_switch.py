"""The stage-2 switch: a layered, overlapping soup (what training leaves) becomes one connected, manifold, outward
surface at the right place with the soup's colours; surface depth is the plane depth of the face a pixel shows."""
import numpy as np
import pytest
import torch

from trisplat.mesh.stats import mesh_statistics
from trisplat.render import rasterize
from trisplat.scene.init import init_soup
from trisplat.train.switch import SurfaceConfig, soup_to_surface, surface_depth

from tests.mesh.test_fusion import fibonacci_cameras, look_at


def layered_sphere_soup(r=0.6, n=1500, seed=0):
    """Three overlapping layers of tangent soup triangles around a sphere (radii 0.97 r, r, 1.03 r); the upper
    half (z > 0) red, the lower half blue: a soup like a trained one, thick and overlapping."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = np.concatenate([d * r * s for s in (0.97, 1.0, 1.03)])
    normals = np.concatenate([d, d, d])
    cols = np.where(pts[:, 2:3] > 0, [[0.9, 0.1, 0.1]], [[0.1, 0.1, 0.9]])
    scene, _ = init_soup(pts, cols, seed=seed, opacity=0.95, sh_degree=1, normals=normals, size_factor=3.0)
    return scene


def _render(scene, cam, sigma=0.05):
    return rasterize(scene.positions, scene.faces, scene.sh, scene.opacities(), sigma,
                     torch.as_tensor(cam.world_to_camera, dtype=torch.float32),
                     torch.as_tensor(cam.K, dtype=torch.float32), cam.width, cam.height,
                     background=torch.ones(3))


def test_surface_depth_is_the_plane_depth_of_the_shown_face():
    cam = look_at([0.0, 0.0, 3.0], size=24, focal=30.0)
    # one big tilted triangle in front of the camera: plane z = 0.2 x (world); camera looks down -z from z = 3
    pos = np.array([[-2.0, -2.0, -0.4], [2.0, -2.0, 0.4], [0.0, 2.0, 0.0]])
    faces = np.array([[0, 1, 2]])
    fid = np.zeros((24, 24), np.int64)
    fid[0, 0] = -1
    depth = surface_depth(fid, pos, faces, cam.world_to_camera, cam.K)
    ys, xs = np.mgrid[0:24, 0:24] + 0.5
    ray = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(cam.K).T
    dirs = ray @ cam.world_to_camera[:3, :3]  # camera-frame rays to world directions (R^T r)
    c = cam.center
    # world ray c + s * dir meets z = 0.2 x: c_z + s d_z = 0.2 (c_x + s d_x); the view depth of that point is s
    s = (0.2 * c[0] - c[2]) / (dirs[..., 2] - 0.2 * dirs[..., 0])
    assert np.isinf(depth[0, 0])
    np.testing.assert_allclose(depth[1:, 1:], s[1:, 1:], rtol=1e-6)


def test_layered_soup_becomes_one_manifold_surface_with_its_colours():
    soup = layered_sphere_soup()
    cams = fibonacci_cameras(20)
    surface, report = soup_to_surface(soup, cams, lambda n: _render(soup, cams[n]),
                                      np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]),
                                      SurfaceConfig(resolution=48, face_ratio=2.0))
    v = surface.positions.numpy().astype(np.float64)
    f = surface.faces.numpy()
    st = mesh_statistics(v, f)
    # what a soup can never be: one piece, V/F near 0.5, no edge with more than two faces, consistently oriented
    assert st.connected_components == 1
    assert 0.45 < st.vertex_face_ratio < 0.55
    assert st.non_manifold_edges == 0 and st.consistently_oriented
    assert report.faces == len(f)
    # on the visible (outer) layer, within two voxels
    r = np.linalg.norm(v, axis=1)
    # (a few vertices, where the fine grid resolves a gap between the layers, reach the inner layer at ~0.5)
    assert np.abs(np.median(r) - 0.6 * 1.03) < 2 * report.voxel and np.percentile(r, 1) > 0.55
    # outward: positive signed volume
    tri = v[f]
    assert np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() > 0
    # the soup's colours came along: red on top, blue below (DC of the SH)
    rgb = (0.28209479177387814 * surface.sh[:, 0] + 0.5).numpy()
    top, bottom = v[:, 2] > 0.15, v[:, 2] < -0.15
    assert rgb[top, 0].mean() > 0.7 and rgb[top, 2].mean() < 0.3
    assert rgb[bottom, 2].mean() > 0.7 and rgb[bottom, 0].mean() < 0.3
    # opacity starts at least at the configured value, above the soup's floor
    assert float(surface.opacities().min()) >= 0.9 - 1e-4


def test_decimation_meets_the_face_budget_and_keeps_one_watertight_manifold_piece():
    """Marching cubes gives far more faces than a budget of 1000: decimation (and the manifold repair after it)
    runs, and the result has the budget's face count, in one closed, manifold, outward piece on the sphere."""
    soup = layered_sphere_soup()
    cams = fibonacci_cameras(20)
    cfg = SurfaceConfig(resolution=48, face_ratio=0.1, max_faces=1500)  # budget max(0.1 x 4500, 1000) = 1000
    surface, report = soup_to_surface(soup, cams, lambda n: _render(soup, cams[n]),
                                      np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), cfg)
    v, f = surface.positions.numpy().astype(np.float64), surface.faces.numpy()
    assert report.marching_cubes_faces > 10 * 1000  # so decimation had work to do
    assert 950 <= len(f) <= 1000 and report.faces == len(f)
    st = mesh_statistics(v, f)
    assert st.connected_components == 1 and st.watertight and st.non_manifold_edges == 0
    assert st.consistently_oriented and st.vertex_face_ratio == pytest.approx(0.5, abs=0.01)  # closed, genus 0
    r = np.linalg.norm(v, axis=1)
    assert np.abs(r - 0.6 * 1.03).max() < 3 * report.voxel  # still the (outer layer's) sphere
    tri = v[f]
    assert np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() > 0  # outward
    rgb = (0.28209479177387814 * surface.sh[:, 0] + 0.5).numpy()  # the colours came along the decimated vertices
    assert rgb[v[:, 2] > 0.15, 0].mean() > 0.7 and rgb[v[:, 2] < -0.15, 2].mean() > 0.7


def test_drop_enclosed_removes_the_unseen_inside_wall_and_keeps_what_the_views_see():
    """The trainer's default (surface_unseen_faces='drop_enclosed') through the whole switch, on a case with a known
    enclosed part: the layered sphere seen only from above (elevations 15-75 degrees) with unseen space solid only
    a few voxels deep fuses into a hollow shell whose inside wall joins the outside through the never-seen underside.
    drop_enclosed removes that wall and nothing the views see; the unseen underside, facing open space, stays."""
    soup = layered_sphere_soup()
    cams = []
    for el in (15, 35, 55, 75):
        for az in range(0, 360, 30):
            e, a = np.radians(el), np.radians(az + el)
            cams.append(look_at(2.5 * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])))
    r_out = 0.6 * 1.03
    parts = {}
    for mode in ("keep", "drop_enclosed", "drop"):
        cfg = SurfaceConfig(resolution=48, max_depth_fraction=0.0, unseen_faces=mode, face_ratio=100.0)
        surface, report = soup_to_surface(soup, cams, lambda n: _render(soup, cams[n]),
                                          np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), cfg)
        v, f = surface.positions.numpy().astype(np.float64), surface.faces.numpy()
        c = v[f].mean(1)
        rc = np.linalg.norm(c, axis=1)
        outer = rc > r_out - 1.5 * report.voxel
        parts[mode] = {"inner": int((rc < r_out - 2.5 * report.voxel).sum()),  # the hollow's inside wall
                       "top": int((outer & (c[:, 2] > 0.2)).sum()),  # the outside the views see
                       "bottom": int((outer & (c[:, 2] < -0.5)).sum()),  # the outside no view sees
                       "pieces": mesh_statistics(v, f).connected_components}
    keep, enclosed, drop = parts["keep"], parts["drop_enclosed"], parts["drop"]
    assert keep["inner"] > 2000 and keep["pieces"] == 1  # the enclosed wall is there, joined to the outside
    assert enclosed["inner"] < 0.05 * keep["inner"]  # ... and gone
    assert enclosed["top"] == keep["top"] > 2000  # every face the views see stays
    assert enclosed["bottom"] >= 0.98 * keep["bottom"] > 1000 and enclosed["pieces"] == 1  # the underside closes it
    assert drop["bottom"] < 0.6 * keep["bottom"]  # (the underside is unseen: 'drop' takes much of it)


def test_photo_colours_replace_the_soups_base_colour():
    soup = layered_sphere_soup()
    cams = fibonacci_cameras(12)
    green = np.zeros((48, 48, 3), np.float32)
    green[..., 1] = 0.8
    surface, report = soup_to_surface(soup, cams, lambda n: _render(soup, cams[n]),
                                      np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]),
                                      SurfaceConfig(resolution=40), images=lambda n: green)
    rgb = (0.28209479177387814 * surface.sh[:, 0] + 0.5).numpy()
    seen = np.abs(rgb[:, 1] - 0.8) < 1e-4
    assert seen.mean() > 0.9  # (nearly) every vertex is seen by some photo and takes its colour
    np.testing.assert_allclose(rgb[seen], np.broadcast_to([0.0, 0.8, 0.0], rgb[seen].shape), atol=1e-4)


def test_switch_refuses_an_empty_render():
    soup = layered_sphere_soup(n=50)
    cams = fibonacci_cameras(4)

    class Empty:
        face_id = torch.full((48, 48), -1, dtype=torch.int64)

    with pytest.raises(ValueError, match="covers no pixel"):
        soup_to_surface(soup, cams, lambda n: Empty(), None)


def test_views_that_disagree_about_a_surface_keep_it_with_a_larger_truncation_only_where_needed():
    """A real capture's soup shows a surface at depths that differ between views by more than a few voxels: here
    three spheres (radii 0.24, 0.3, 0.36), each view shown one of them. With the object default (3 voxels) the
    views that see the inner sphere carve away what the others measured and the object shrinks to the inner one,
    in pieces (a thin object, the bonsai's table, is carved out altogether). The switch measures that (the share
    of what the views saw that the surface carved away) and fuses again with the larger truncations of
    `retry_truncations` (what the trainer sets for photos of a scene), which average the views to the middle
    sphere; a soup whose views agree keeps the default."""
    from trisplat.train.switch import append_scene

    cams = fibonacci_cameras(24)
    layers = [layered_sphere_soup(r=r, n=600, seed=k) for k, r in enumerate((0.24, 0.3, 0.36))]
    offsets = np.cumsum([0] + [s.num_faces for s in layers[:-1]])
    soup = layers[0]
    for s in layers[1:]:
        soup = append_scene(soup, s)

    def render(n):  # view n shows layer n % 3 only: face ids into the whole soup
        out = _render(layers[n % 3], cams[n])
        out.face_id[out.face_id >= 0] += int(offsets[n % 3])
        return out

    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    plain, rep0 = soup_to_surface(soup, cams, render, box, SurfaceConfig(resolution=64))
    retried, rep = soup_to_surface(soup, cams, render, box, SurfaceConfig(resolution=64, retry_truncations=(0.1, 0.3)))
    r0 = float(np.median(np.linalg.norm(plain.positions.numpy(), axis=1)))
    r = float(np.median(np.linalg.norm(retried.positions.numpy(), axis=1)))
    assert rep0.truncation_voxels == 3.0 and rep0.carved_fraction is None
    assert r0 < 0.24 * 1.03 + 0.005, r0  # shrunk to the inner sphere (its outer layer: 1.03 r)
    assert rep.truncation_voxels == pytest.approx(0.3 * max(rep.grid), rel=0.02)  # 0.3 of the fused box's side
    assert rep.carved_fraction > 0.1 and any("carved away" in n for n in rep.notes)
    assert abs(r - 0.3 * 1.03) < 0.02, r  # the middle sphere
    # views that agree: nothing carved, the object default kept
    agree = layers[1]
    kept, rep2 = soup_to_surface(agree, cams, lambda n: _render(agree, cams[n]), box,
                                 SurfaceConfig(resolution=64, retry_truncations=(0.1, 0.3)))
    assert rep2.truncation_voxels == 3.0 and rep2.carved_fraction <= 0.1, rep2.carved_fraction
    assert abs(float(np.median(np.linalg.norm(kept.positions.numpy(), axis=1))) - 0.3 * 1.03) < 0.02


def test_carved_fraction_counts_what_the_views_saw_and_the_surface_lost():
    """A camera looks at a plane (its soup depth); a surface at the plane carves nothing, a surface with the
    plane's right half missing carves half of it, and pixels that see a point outside the box do not count."""
    from trisplat.train.switch import carved_fraction

    cam = look_at([0.0, 0.0, 2.0], size=32, focal=32.0)
    soup_depth = np.full((32, 32), 2.0, np.float32)  # the plane z = 0 seen head-on
    verts = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    whole = np.array([[0, 1, 2], [0, 2, 3]])
    box = np.array([[-2.0, -2.0, -1.0], [2.0, 2.0, 1.0]])
    assert carved_fraction(verts, whole, [cam], [soup_depth], box, 0.05) == 0.0
    # keep only the x < 0 half: the camera's image x runs along world x or against it; either way half is lost
    half_v = np.array([[-2.0, -2.0, 0.0], [0.0, -2.0, 0.0], [0.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    assert carved_fraction(half_v, whole, [cam], [soup_depth], box, 0.05) == pytest.approx(0.5, abs=0.04)
    # the same plane farther than the soup by more than the tolerance: all of it carved
    far = verts - [0.0, 0.0, 0.2]
    assert carved_fraction(far, whole, [cam], [soup_depth], box, 0.05) == 1.0
    # pixels whose soup point lies outside the box say nothing, unknown ones (nan) neither
    above = np.array([[-2.0, -2.0, 0.5], [2.0, 2.0, 1.0]])
    assert carved_fraction(far, whole, [cam], [soup_depth], above, 0.05) == 0.0
    unknown = soup_depth.copy()
    unknown[:, :16] = np.nan
    assert carved_fraction(far, whole, [cam], [unknown], box, 0.05) == 1.0
    assert carved_fraction(half_v, whole, [cam], [unknown], box, 0.05) in (0.0, 1.0)  # one half known, all or none


def test_the_trainers_truncation_is_wider_for_objects_unless_given():
    """The switch's truncation (--surface-truncation): 6 voxels for a capture with alpha (Spot: 3 voxels lost 1.6% of
    the object's outline, the re-switched run gained 1 dB; lego the same at 6, -0.5 dB at 9), 3 for real photos
    (fox: -0.13 dB at 6); a given value wins, and a value that is not positive is refused."""
    from trisplat.train.config import TrainConfig
    from trisplat.train.trainer import surface_truncation

    cfg = TrainConfig()
    assert surface_truncation(cfg, True) == 6.0 and surface_truncation(cfg, False) == 3.0
    given = TrainConfig(surface_truncation=4.5)
    assert surface_truncation(given, True) == 4.5 == surface_truncation(given, False)
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match="surface_truncation must be > 0"):
            TrainConfig(surface_truncation=bad)


def test_pieces_cut_off_by_the_inner_box_are_told_apart_from_the_scenes_own():
    """An unbounded capture's surface is fused in the inner box: the near ends of walls and furniture that the box
    cuts off come out as slabs at its faces (bonsai: five, 17-32% of the fused faces). Those go to the far field; the
    largest piece stays even where it reaches the box (a floor), and so does a piece wholly inside (an object)."""
    import trimesh

    from trisplat.scene.model import TriangleScene
    from trisplat.train.switch import box_cut_pieces, cut_pieces_last, inner_box

    def scene_of(meshes):
        mesh = trimesh.util.concatenate(meshes)
        return TriangleScene.from_rgb(torch.as_tensor(mesh.vertices, dtype=torch.float32),
                                      torch.as_tensor(mesh.faces, dtype=torch.int32),
                                      torch.full((len(mesh.vertices), 3), 0.5))

    main = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    main.apply_translation((0, 0.7, 0))  # the largest piece, reaching the box's face y = 1
    slab = trimesh.creation.box(extents=(0.05, 0.3, 0.3))
    slab.apply_translation((0.975, 0.5, 0))  # a wall's end at x = 1
    corner = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    corner.apply_translation((-0.895, -0.5, 0.5))  # 0.005 from x = -1: within the tolerance
    inside = trimesh.creation.icosphere(subdivisions=2, radius=0.1)  # an object standing in the room
    parts = [main, slab, corner, inside]
    n = np.cumsum([0] + [len(p.faces) for p in parts])
    cut = box_cut_pieces(scene_of(parts), inner_box(), tolerance=0.01)
    expected = np.zeros(n[-1], bool)
    expected[n[1]:n[3]] = True  # the slab and the corner
    np.testing.assert_array_equal(cut, expected)
    # a tolerance below the corner's gap keeps it; one piece is never cut, whatever it reaches
    assert cut[n[2]:n[3]].all() and not box_cut_pieces(scene_of(parts), inner_box(), 0.001)[n[2]:n[3]].any()
    assert not box_cut_pieces(scene_of([slab]), inner_box(), 0.01).any()
    # the trainer's order: the scene's own piece(s) first, then the cut-off pieces (the far field's first rows), each
    # with its own vertices, the same triangles
    whole = scene_of(parts)
    moved, n_cut = cut_pieces_last(whole, inner_box(), 0.01)
    assert n_cut == n[3] - n[1] and moved.num_faces == whole.num_faces and moved.num_vertices == whole.num_vertices
    tri = lambda sc: sc.positions[sc.faces.long()].numpy()  # noqa: E731
    keep = np.r_[0:n[1], n[3]:n[4]]
    np.testing.assert_array_equal(tri(moved)[:len(keep)], tri(whole)[keep])
    np.testing.assert_array_equal(tri(moved)[len(keep):], tri(whole)[n[1]:n[3]])
    main_vertices = int(moved.faces[:len(keep)].max()) + 1
    assert main_vertices == len(main.vertices) + len(inside.vertices)
    assert int(moved.faces[len(keep):].min()) == main_vertices
