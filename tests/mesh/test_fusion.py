"""Depth fusion: analytic depth maps of known shapes fuse into the shape's surface, closed and outward; free pixels
carve; unobserved space stays solid; bad input is refused with the problem named."""
import numpy as np
import pytest

from trisplat.cameras import Camera
from trisplat.mesh.fusion import extract_surface, fuse_depths, grid_shape
from trisplat.mesh.stats import mesh_statistics


def look_at(center, target=(0.0, 0.0, 0.0), size=48, focal=60.0) -> Camera:
    """OpenCV camera at `center` looking at `target`."""
    c = np.asarray(center, float)
    f = np.asarray(target, float) - c
    f /= np.linalg.norm(f)
    up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(f, up)
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    R = np.stack([x, y, f])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ c
    K = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]])
    return Camera(world_to_camera=w2c, K=K, width=size, height=size)


def sphere_depth(cam: Camera, centre, radius) -> np.ndarray:
    """View depth of the first hit of each pixel-centre ray with a sphere; inf where it misses."""
    H, W = cam.height, cam.width
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    rays_cam = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(cam.K).T  # z = 1
    R, t = cam.world_to_camera[:3, :3], cam.world_to_camera[:3, 3]
    oc = R @ np.asarray(centre, float) + t  # sphere centre in the camera frame
    a = (rays_cam**2).sum(-1)
    b = -2 * rays_cam @ oc
    c = oc @ oc - radius**2
    disc = b * b - 4 * a * c
    s = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    return np.where(disc > 0, s, np.inf).astype(np.float32)  # ray z-component is 1: s is the view depth


def fibonacci_cameras(n, radius=2.5):
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return [look_at(radius * np.array([np.cos(t) * np.sin(p), np.sin(t) * np.sin(p), np.cos(p)]))
            for p, t in zip(phi, theta)]


def test_sphere_fuses_into_a_closed_outward_sphere():
    centre, r = np.array([0.1, -0.05, 0.0]), 0.6
    cams = fibonacci_cameras(24)
    depths = [sphere_depth(c, centre, r) for c in cams]
    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    grid = fuse_depths(cams, depths, bounds, resolution=48, truncation_voxels=3.0)
    v, f = extract_surface(grid)
    dist = np.linalg.norm(v - centre, axis=1)
    assert np.abs(dist - r).max() < 1.0 * grid.voxel  # on the sphere, within one voxel (2/48)
    st = mesh_statistics(v, f)
    assert st.connected_components == 1 and st.watertight and st.consistently_oriented
    assert st.genus == 0 and st.non_manifold_edges == 0
    tri = v[f]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    assert volume == pytest.approx(4 / 3 * np.pi * r**3, rel=0.05)  # positive: outward normals
    assert 0.49 < st.vertex_face_ratio < 0.51


def test_free_pixels_carve_and_unobserved_space_is_solid():
    # one camera looking down -z at a plane z = 0 covering the left half of the image, nothing on the right half
    cam = look_at([0.0, 0.0, 2.0], size=32, focal=32.0)
    depth = np.full((32, 32), np.inf, np.float32)
    depth[:, :16] = 2.0  # view depth of the plane z = 0
    bounds = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
    grid = fuse_depths([cam], [depth], bounds, resolution=16, truncation_voxels=2.0)
    centres = grid.origin + (np.argwhere(np.ones(grid.sdf.shape, bool)) + 0.5) * grid.voxel
    sdf = grid.sdf.reshape(-1)
    # where each voxel projects (the camera's x axis is world +x or -x: take it from the projection itself)
    pc = centres @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    u = cam.K[0, 0] * pc[:, 0] / pc[:, 2] + cam.K[0, 2]
    left, right = (u < 15) & (u > 1), (u > 17) & (u < 31)
    above = centres[:, 2] > 2 * grid.voxel
    below = centres[:, 2] < -3 * grid.voxel  # beyond the truncation band behind the plane: never observed
    assert np.all(sdf[left & above] > 0)  # in front of the observed plane: free
    assert np.all(sdf[left & below] == -1.0)  # occluded: solid
    assert np.all(sdf[right] == 1.0)  # the ray saw nothing: free all the way
    near_plane = left & (np.abs(centres[:, 2]) < 0.5 * grid.voxel + 1e-9)
    assert np.all(np.abs(sdf[near_plane]) < 0.5)


def test_unknown_pixels_say_nothing():
    # the plane z = 0 on the left half as before; the right half is unknown (nan: a hole in a SLAM map), not free.
    # Voxels seen only through unknown pixels are in no view: free (+1), not occluded-solid; the left is unchanged.
    cam = look_at([0.0, 0.0, 2.0], size=32, focal=32.0)
    depth = np.full((32, 32), np.nan, np.float32)
    depth[:, :16] = 2.0
    bounds = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
    grid = fuse_depths([cam], [depth], bounds, resolution=16, truncation_voxels=2.0)
    free = depth.copy()
    free[:, 16:] = np.inf
    ref = fuse_depths([cam], [free], bounds, resolution=16, truncation_voxels=2.0)
    centres = grid.origin + (np.argwhere(np.ones(grid.sdf.shape, bool)) + 0.5) * grid.voxel
    pc = centres @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    u = cam.K[0, 0] * pc[:, 0] / pc[:, 2] + cam.K[0, 2]
    left, right = (u < 15) & (u > 1), (u > 17) & (u < 31)
    sdf, w = grid.sdf.reshape(-1), grid.weight.reshape(-1)
    assert np.all(sdf[right] == 1.0) and np.all(w[right] == 0)  # no view's weight: nothing observed there
    assert np.all(ref.weight.reshape(-1)[right] > 0)  # free pixels do observe (carve)
    assert np.array_equal(sdf[left], ref.sdf.reshape(-1)[left])


def test_bad_input_is_refused():
    cam = look_at([0.0, 0.0, 2.0], size=16)
    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match="2 depth maps"):
        fuse_depths([cam], [np.ones((16, 16)), np.ones((16, 16))], box)
    with pytest.raises(ValueError, match="8x16"):
        fuse_depths([cam], [np.ones((16, 8))], box)
    with pytest.raises(ValueError, match="finite box"):
        grid_shape(np.array([[0.0, 0, 0], [np.nan, 1, 1]]), 32)
    with pytest.raises(ValueError, match="more than"):
        fuse_depths([cam], [np.ones((16, 16))], box, resolution=100_000)


def test_unseen_space_is_solid_only_up_to_max_depth_behind_the_surface():
    """The plane of the previous test seen only from above: with max_depth the occluded space below it is solid
    for max_depth and free beyond (a slab, not a block down to the bottom of the box), and the surface's lowest
    point lies max_depth below the observed band, within a voxel."""
    cam = look_at([0.0, 0.0, 2.0], size=32, focal=32.0)
    depth = np.full((32, 32), 2.0, np.float32)  # the plane z = 0 fills the view
    bounds = np.array([[-0.4, -0.4, -0.5], [0.4, 0.4, 0.5]])
    block = fuse_depths([cam], [depth], bounds, resolution=32, truncation_voxels=2.0)
    slab = fuse_depths([cam], [depth], bounds, resolution=32, truncation_voxels=2.0, max_depth=0.2)
    vb, _ = extract_surface(block)
    vs, fs = extract_surface(slab)
    assert vb[:, 2].min() < -0.45  # unbounded: solid down to the box
    # bounded: the slab's underside max_depth below the observed band (which reaches one truncation behind the plane)
    assert abs(vs[:, 2].min() - (-0.2 - slab.truncation)) <= slab.voxel
    assert abs(vs[:, 2].max() - 0.0) <= slab.voxel
    st = mesh_statistics(vs, fs)
    assert st.connected_components == 1 and st.watertight


def test_a_hollow_inside_is_a_cavity_whose_wall_is_dropped():
    """A sphere seen from all around with max_depth below its radius: the field is a shell; marching cubes gives
    the outer sphere and the (inside-out) wall of the hollow, which extract_surface drops: one outward sphere."""
    centre, r = np.zeros(3), 0.6
    cams = fibonacci_cameras(24)
    depths = [sphere_depth(c, centre, r) for c in cams]
    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    grid = fuse_depths(cams, depths, bounds, resolution=48, truncation_voxels=3.0, max_depth=0.25)
    assert grid.sdf[24, 24, 24] == 1.0  # the centre, 0.6 behind the surface from every view: free
    v_all, f_all = extract_surface(grid, drop_cavities=False)
    st_all = mesh_statistics(v_all, f_all)
    assert st_all.connected_components == 2
    v, f = extract_surface(grid)
    st = mesh_statistics(v, f)
    assert st.connected_components == 1 and st.watertight
    assert np.abs(np.linalg.norm(v, axis=1) - r).max() < grid.voxel  # the outer sphere is what stays
    tri = v[f]
    assert np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() > 0


def test_unseen_inside_wall_is_dropped_and_unseen_underside_kept():
    # a sphere seen only from above (elevation 15-75 degrees): unseen space is solid just behind what was measured,
    # so the fused shell is hollow, and its inside wall joins the outside through the never-seen underside (one
    # piece: extract_surface's cavity test keeps it). drop_enclosed removes that wall (its normals look at the
    # surface) and keeps the unseen underside (its normals look away into open space).
    from trisplat.train.switch import unseen_faces

    centre, r = np.zeros(3), 0.6
    cams = []
    for el in (15, 35, 55, 75):
        for az in range(0, 360, 30):
            e, a = np.radians(el), np.radians(az + el)
            cams.append(look_at(2.5 * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])))
    depths = [sphere_depth(c, centre, r) for c in cams]
    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    grid = fuse_depths(cams, depths, bounds, resolution=48, truncation_voxels=3.0, max_depth=4 * 2.0 / 48)
    v, f = extract_surface(grid)
    tri_r = np.linalg.norm(v[f].mean(1), axis=1)
    inner = tri_r < r - 2.5 * grid.voxel
    e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    n = np.cross(e1, e2)
    radial = np.einsum("ij,ij->i", n / np.linalg.norm(n, axis=1, keepdims=True), v[f].mean(1) / tri_r[:, None])
    outer = (np.abs(tri_r - r) < 1.5 * grid.voxel) & (radial > 0.5)  # not the lip where the two walls meet
    assert inner.sum() > 100 and mesh_statistics(v, f).connected_components == 1  # the hollow shell, one piece
    tol = 3.0 * grid.voxel
    drop = unseen_faces(v, f, cams, depths, tol, enclosed_only=True)
    assert drop[inner].mean() > 0.9 and not drop[outer].any()
    low = outer & (v[f].mean(1)[:, 2] < -0.9 * r)  # the bottom cap: no camera saw it
    every = unseen_faces(v, f, cams, depths, tol, enclosed_only=False)
    assert low.sum() > 10 and every[low].all()  # unseen ...
    assert not drop[low].any()  # ... but facing open space: kept


def test_occlusion_vote_outweighs_one_wrong_ray():
    """A plane z = 0 seen from above by four cameras; a voxel 0.3 below it is beyond the truncation band of every
    view (occluded). A fifth view whose depth is wrong (inf: its ray slipped through a gap in the soup) votes +1
    with weight 1; each occluded view adds -occlusion_weight to the sum only. Known answer: (1 - 4 w) / 1, and -1
    (solid) without the wrong view. Without the occlusion vote the wrong ray alone would carve the voxel (+1)."""
    eyes = [[0.3, 0.0, 2.0], [-0.3, 0.0, 2.0], [0.0, 0.3, 2.0], [0.0, -0.3, 2.0], [0.0, 0.0, 2.5]]
    cams = [look_at(e, target=(0.0, 0.0, -0.3), size=32, focal=32.0) for e in eyes]
    depths = []
    for c in cams[:4]:  # the view depth of the plane z = 0 along each pixel's ray
        ys, xs = np.mgrid[0:32, 0:32] + 0.5
        ray = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(c.K).T
        d_world = ray @ c.world_to_camera[:3, :3]
        depths.append(((0.0 - c.center[2]) / d_world[..., 2]).astype(np.float32))
    depths.append(np.full((32, 32), np.inf, np.float32))
    bounds = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
    res = 20  # voxel 0.05: centres at -0.475 + 0.05 k; the voxel (10, 10, 4) is centred at (0.025, 0.025, -0.275)
    ijk = (10, 10, 4)

    def fused(views, w):
        g = fuse_depths([cams[i] for i in views], [depths[i] for i in views], bounds, res, truncation_voxels=2.0,
                        occlusion_weight=w)
        return g.sdf[ijk], g.weight[ijk]

    assert fused(range(4), 0.1) == (-1.0, 0.0)  # occluded in every view: solid
    sdf, weight = fused(range(5), 0.1)
    assert weight == 1.0 and sdf == pytest.approx(1.0 - 4 * 0.1, abs=1e-6)
    assert fused(range(5), 0.3)[0] == pytest.approx(-0.2, abs=1e-6)  # enough occluded views: solid again
    assert fused(range(5), 0.0)[0] == 1.0  # no occlusion vote: the one wrong ray carves it


def test_one_wrong_view_does_not_hollow_a_sphere():
    """The sphere of the first test with one view's depth wrong (nothing seen: inf): the occlusion votes of the 23
    other views keep the inside solid and the surface one closed sphere."""
    centre, r = np.zeros(3), 0.6
    cams = fibonacci_cameras(24)
    depths = [sphere_depth(c, centre, r) for c in cams]
    depths[5] = np.full_like(depths[5], np.inf)
    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    grid = fuse_depths(cams, depths, bounds, resolution=32, truncation_voxels=3.0)
    assert grid.sdf[16, 16, 16] < 0  # the centre stays solid
    v, f = extract_surface(grid)
    st = mesh_statistics(v, f)
    assert st.connected_components == 1 and st.watertight
    assert np.abs(np.linalg.norm(v, axis=1) - r).max() < 1.5 * grid.voxel
    no_vote = fuse_depths(cams, depths, bounds, resolution=32, truncation_voxels=3.0, occlusion_weight=0.0)
    assert no_vote.sdf[16, 16, 16] == 1.0  # the wrong view alone decides the inside: carved


def test_streamed_fusion_equals_one_batch_and_holds_one_batch():
    """fuse_depths takes a generator and integrates it a batch at a time: the field is the one of a single batch,
    and no more than a batch of depth maps is alive at once (the switch's memory does not grow with the views)."""
    import weakref

    centre, r = np.array([0.1, 0.0, -0.05]), 0.5
    cams = fibonacci_cameras(12)
    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    whole = fuse_depths(cams, [sphere_depth(c, centre, r) for c in cams], bounds, resolution=24, max_depth=0.3)
    alive, most = [0], [0]

    def gone():
        alive[0] -= 1

    def maps():
        for c in cams:
            d = sphere_depth(c, centre, r)
            alive[0] += 1
            most[0] = max(most[0], alive[0])
            weakref.finalize(d, gone)
            yield d

    one_view = 48 * 48 * 4
    streamed = fuse_depths(cams, maps(), bounds, resolution=24, max_depth=0.3, batch_bytes=2 * one_view)
    assert most[0] <= 2  # a generator's maps are dropped once copied into the batch
    np.testing.assert_allclose(streamed.sdf, whole.sdf, atol=1e-5)
    np.testing.assert_array_equal(streamed.weight, whole.weight)
    with pytest.raises(ValueError, match="12 cameras but 11 depth maps"):
        fuse_depths(cams, (sphere_depth(c, centre, r) for c in cams[:11]), bounds, resolution=24)


def test_fill_holes_fills_cracks_and_keeps_background():
    """A depth ramp (depth = 1 + 0.01 column) with a crack two columns wide and a hole of 2 x 2 pixels inside, an
    empty band six columns wide, and empty background on the right: with px = 2 the crack and the hole take the
    depth of their nearest covered pixel, the wide band (wider than the closing reaches) and the background stay
    empty. Beyond the image border is empty (border_value 0): the crack's ends within px of the border stay open."""
    from trisplat.train.switch import fill_holes

    H, W = 20, 40
    depth = np.tile((1.0 + 0.01 * np.arange(W)).astype(np.float32), (H, 1))
    depth[:, 10:12] = np.inf  # crack
    depth[5:7, 20:22] = np.inf  # hole
    depth[:, 25:31] = np.inf  # a band too wide to close
    depth[:, 34:] = np.inf  # background
    out = fill_holes(depth, 2)
    assert np.all(out[2:-2, 10] == np.float32(1.09)) and np.all(out[2:-2, 11] == np.float32(1.12))  # nearest column
    assert np.all(np.isinf(out[:2, 10:12])) and np.all(np.isinf(out[-2:, 10:12]))
    assert np.all(np.isfinite(out[5:7, 20:22]))
    for r, c in [(5, 20), (5, 21), (6, 20), (6, 21)]:  # each takes a covered 4-neighbour's depth (ties: any)
        near = [depth[r + dr, c + dc] for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)) if np.isfinite(depth[r + dr, c + dc])]
        assert out[r, c] in near, (r, c, out[r, c], near)
    assert np.all(np.isinf(out[:, 25:31])) and np.all(np.isinf(out[:, 34:]))
    covered = np.isfinite(depth)
    assert np.array_equal(out[covered], depth[covered])  # covered pixels unchanged
    assert np.array_equal(fill_holes(depth, 0), depth, equal_nan=True)
    assert np.isinf(fill_holes(depth, 1)[1:-1, 10:12]).sum() == 0  # two columns close with one iteration
    assert np.isinf(fill_holes(depth, 1)[5:7, 20:22]).sum() == 0


def test_fusion_box_is_the_robust_extent_grown_and_cut_to_the_content_box():
    """1001 values per axis evenly over [0, 1] (y twice, z half as long), the four largest of each axis moved far
    out (floaters): the 0.5 / 99.5 percentiles are 0.005 / 0.995 of each axis's length, grown by 10% of the size
    on each side; the floaters do not count. A content box cuts it; a content box that misses it is ignored."""
    from trisplat.train.switch import fusion_box

    rng = np.random.default_rng(0)
    base = np.linspace(0.0, 1.0, 1001)
    base[-4:] = 1000.0
    pos = np.stack([rng.permutation(base), 2 * rng.permutation(base), 0.5 * rng.permutation(base)], 1)
    lo, hi = np.array([0.005, 0.010, 0.0025]), np.array([0.995, 1.990, 0.4975])
    grow = 0.1 * (hi - lo)
    box = fusion_box(pos, None)
    np.testing.assert_allclose(box, [lo - grow, hi + grow], atol=1e-9)
    cut = fusion_box(pos, np.array([[0.2, -5.0, 0.1], [0.8, 5.0, 5.0]]))
    np.testing.assert_allclose(cut, [[0.2, lo[1] - grow[1], 0.1], [0.8, hi[1] + grow[1], hi[2] + grow[2]]])
    np.testing.assert_allclose(fusion_box(pos, np.array([[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]])), box)


def test_transfer_attributes_weights_neighbours_by_opacity_over_distance():
    """Two soup vertices on the x axis: A at 0 (opacity 0.8, SH all bands 1), B at 1 (opacity 0.2, SH all bands
    -1). A point at x = 0.25 takes w_A = 0.8 / 0.25, w_B = 0.2 / 0.75 (normalised) of each; a point on A takes A's;
    with one neighbour, the nearest's values."""
    import torch

    from trisplat.scene.model import TriangleScene
    from trisplat.train.switch import transfer_attributes

    pos = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 50.0, 0.0]])
    sh = torch.stack([torch.ones(4, 3), -torch.ones(4, 3), torch.zeros(4, 3)])
    opac = torch.tensor([0.8, 0.2, 0.5])
    scene = TriangleScene(pos, sh, torch.logit(opac), torch.tensor([[0, 1, 2]], dtype=torch.int32), 0.0)
    pts = np.array([[0.25, 0.0, 0.0], [0.0, 0.0, 0.0], [0.9, 0.0, 0.0]])
    out_sh, out_op = transfer_attributes(scene, pts, neighbours=2)
    wa, wb = 0.8 / 0.25, 0.2 / 0.75
    a, b = wa / (wa + wb), wb / (wa + wb)
    assert out_sh.shape == (3, 4, 3)
    np.testing.assert_allclose(out_sh[0].numpy(), np.full((4, 3), a - b), rtol=1e-5)
    assert float(out_op[0]) == pytest.approx(0.8 * a + 0.2 * b, rel=1e-5)
    np.testing.assert_allclose(out_sh[1].numpy(), np.ones((4, 3)), atol=1e-6)  # on A: A's values
    wa, wb = 0.8 / 0.9, 0.2 / 0.1  # near B, B's weight wins although A is more opaque
    assert float(out_sh[2, 0, 0]) == pytest.approx((wa - wb) / (wa + wb), rel=1e-5)
    one_sh, one_op = transfer_attributes(scene, pts, neighbours=1)
    np.testing.assert_allclose(one_sh[:, 0, 0].numpy(), [1.0, 1.0, -1.0])
    np.testing.assert_allclose(one_op.numpy(), [0.8, 0.8, 0.2], rtol=1e-6)


def test_unseen_space_cut_matches_scipys_distance_transform():
    """The cut of unseen space (edt's multi-threaded distance transform) equals the same rule computed with
    scipy.ndimage's exact Euclidean distance transform, voxel for voxel."""
    from scipy import ndimage

    from trisplat.mesh.fusion import TSDFVolume

    cams = fibonacci_cameras(12)[:6]  # one side only: occluded space behind the sphere
    vol = TSDFVolume(np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), resolution=40, truncation_voxels=3.0)
    vol.integrate(cams, [sphere_depth(c, np.zeros(3), 0.6) for c in cams])
    max_depth = 0.15
    got = vol.grid(max_depth).sdf
    want = vol.grid().sdf
    dist = ndimage.distance_transform_edt(~vol.band, sampling=vol.voxel)
    ramp = np.clip((dist - max_depth) / vol.truncation, -1.0, 1.0).astype(np.float32)
    want = np.where(want < 0, np.maximum(want, ramp), want)
    assert (want == 1.0).sum() > (vol.grid().sdf == 1.0).sum()  # the cut frees some occluded voxels
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_fusion_kernel_matches_the_per_voxel_reference():
    """The kernel (each z-column visits only the run of voxels inside a view's frustum) adds exactly the votes of
    the readable per-voxel, per-view rule: views inside and outside the box, looking along and across z, depth maps
    with nothing seen (inf), unknown pixels (nan), a skewed pixel axis and a non-square image."""
    from trisplat.mesh.fusion import _fuse_kernel, fuse_reference

    rng = np.random.default_rng(3)
    import dataclasses

    cams = [look_at([2.0, 0.3, 0.4], size=20), look_at([0.03, 0.02, 2.5], size=24),
            look_at([0.2, -0.1, 0.1], target=(1, 1, 0), size=16), look_at([-0.5, 1.8, -1.2], target=(0.3, 0.0, 0.2), size=20)]
    skewed = cams[3].K.copy()
    skewed[0, 1] = 3.0
    cams[3] = dataclasses.replace(cams[3], K=skewed, height=14)  # skewed, not square: its map's bottom rows unused
    depths = [sphere_depth(c, [0.1, 0.0, 0.0], 0.5) for c in cams]
    depths[0][rng.random(depths[0].shape) < 0.2] = np.nan
    depths[2][:, :5] = np.inf
    dims = np.array([13, 11, 17], np.int64)
    origin, voxel = np.array([-0.7, -0.6, -0.8]), 0.1
    stack = np.full((4, 24, 24), np.nan, np.float32)
    for n, d in enumerate(depths):
        stack[n, : d.shape[0], : d.shape[1]] = d
    args = (origin, voxel, np.stack([c.world_to_camera for c in cams]), np.stack([c.K for c in cams]),
            np.array([[c.width, c.height] for c in cams], np.int64), stack, 0.15, 1e-3, 0.1)
    out = [np.zeros(tuple(dims), np.float32), np.zeros(tuple(dims), np.float32), np.zeros(tuple(dims), bool),
           np.zeros(tuple(dims), bool)]
    ref = [a.copy() for a in out]
    _fuse_kernel(dims, *args, *out)
    fuse_reference(dims, *args, *ref)
    assert ref[2].sum() > 500 and 0 < ref[3].sum() < ref[2].sum() and (ref[0] < 0).any()  # a real mix of votes
    np.testing.assert_allclose(out[0], ref[0], atol=1e-5)
    np.testing.assert_array_equal(out[1], ref[1])
    np.testing.assert_array_equal(out[2], ref[2])
    np.testing.assert_array_equal(out[3], ref[3])
