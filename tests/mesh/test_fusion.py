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
