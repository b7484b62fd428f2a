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
    assert report.faces == len(f) <= 2 * soup.num_faces
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
