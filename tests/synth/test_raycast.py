"""The independent ray-cast renderer: exact pixel coverage from K, colour interpolation, textures, antialiasing."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from trisplat.cameras import Camera
from trisplat.synth import Shading, raycast_view, render_face_ids, render_views
from trisplat.synth.orbit import look_at

W, H, F = 64, 48, 100.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
Z = 2.0  # depth of the test square, scene units


def _pix_to_cam(u, v, z=Z):
    """The camera-frame point at depth z that projects to pixel coordinate (u, v) (corner-based)."""
    return np.array([(u - K[0, 2]) * z / F, (v - K[1, 2]) * z / F, z])


def _square(u0, u1, v0, v1, rgb=(0.2, 0.4, 0.6)) -> trimesh.Trimesh:
    """A quad at depth Z covering pixel coordinates [u0,u1] x [v0,v1], wound to face the camera (normal -z)."""
    c = [_pix_to_cam(u0, v0), _pix_to_cam(u1, v0), _pix_to_cam(u1, v1), _pix_to_cam(u0, v1)]
    m = trimesh.Trimesh(np.array(c), np.array([[0, 1, 2], [0, 2, 3]]), process=False)
    m.visual.vertex_colors = np.tile(np.r_[np.round(np.asarray(rgb) * 255), 255].astype(np.uint8), (4, 1))
    return m


def _random_pose(seed):
    rng = np.random.default_rng(seed)
    A = trimesh.transformations.random_rotation_matrix(rng.random(3))
    A[:3, 3] = rng.normal(size=3) * 3
    return A


@pytest.mark.parametrize("pose_seed", [None, 1, 2])
def test_square_covers_exact_pixel_rectangle(pose_seed):
    mesh = _square(10, 30, 5, 20, rgb=(0.2, 0.4, 0.6))
    w2c = np.eye(4)
    if pose_seed is not None:  # move square and camera together: the image must not change
        A = _random_pose(pose_seed)
        mesh.apply_transform(A)
        w2c = np.linalg.inv(A)
    cam = Camera(world_to_camera=w2c, K=K, width=W, height=H)
    view = raycast_view(mesh, cam)
    expected = np.zeros((H, W), bool)
    expected[5:20, 10:30] = True
    np.testing.assert_array_equal(view.rgba[..., 3] == 1.0, expected)
    np.testing.assert_array_equal(view.rgba[..., 3] == 0.0, ~expected)
    np.testing.assert_allclose(view.rgba[expected][:, :3], np.tile([51, 102, 153], (expected.sum(), 1)) / 255,
                               atol=1e-6)
    np.testing.assert_allclose(view.depth[expected], Z, rtol=1e-5)
    assert (view.face_id[expected] >= 0).all() and (view.face_id[~expected] == -1).all()


def test_antialiasing_gives_fractional_coverage_on_half_covered_pixels():
    mesh = _square(10.5, 30, 5, 20.5)  # left edge splits column 10, bottom edge splits row 20
    cam = Camera(world_to_camera=np.eye(4), K=K, width=W, height=H)
    a = raycast_view(mesh, cam, samples_per_pixel=2).rgba[..., 3]
    assert a[10, 10] == 0.5 and a[20, 15] == 0.5 and a[20, 10] == 0.25
    assert a[10, 11] == 1.0 and a[10, 9] == 0.0 and a[21, 15] == 0.0
    # composited over a background, a half-covered pixel is the average of surface and background
    rgba = raycast_view(mesh, cam, background=(1.0, 0.0, 0.0), samples_per_pixel=2).rgba
    np.testing.assert_allclose(rgba[10, 10, :3], 0.5 * np.array([51, 102, 153]) / 255 + 0.5 * np.array([1, 0, 0]),
                               atol=1e-6)


def _rgb_triangle():
    P = np.array([_pix_to_cam(5, 5), _pix_to_cam(60, 8, 3.0), _pix_to_cam(20, 45, 1.5)])
    m = trimesh.Trimesh(P, np.array([[0, 1, 2]]), process=False)
    m.visual.vertex_colors = np.array([[255, 0, 0, 255], [0, 255, 0, 255], [0, 0, 255, 255]], np.uint8)
    return m, P


def test_vertex_colours_interpolate_with_3d_barycentrics():
    mesh, P = _rgb_triangle()
    cam = Camera(world_to_camera=np.eye(4), K=K, width=W, height=H)
    view = raycast_view(mesh, cam)
    hit = view.rgba[..., 3] == 1
    assert hit.sum() > 300
    ys, xs = np.nonzero(hit)
    # the pixel-centre ray meets the triangle's plane at t * d; barycentrics of that point are the expected colour
    d = np.stack([(xs + 0.5 - K[0, 2]) / F, (ys + 0.5 - K[1, 2]) / F, np.ones_like(xs, float)], 1)
    n = np.cross(P[1] - P[0], P[2] - P[0])
    X = d * ((P[0] @ n) / (d @ n))[:, None]
    T = np.stack([P[0] - P[2], P[1] - P[2]], 1)  # [3,2]
    ab = np.linalg.lstsq(T, (X - P[2]).T, rcond=None)[0].T
    bary = np.c_[ab, 1 - ab.sum(1)]
    np.testing.assert_allclose(view.rgba[ys, xs, :3], bary, atol=1e-5)
    np.testing.assert_allclose(view.depth[ys, xs], X[:, 2], rtol=1e-5)


def test_face_colours_and_texture_lookup():
    # face colours: each of the two triangles of a quad is one flat colour
    mesh = _square(10, 30, 5, 20)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, face_colors=np.array([[255, 0, 0, 255], [0, 0, 255, 255]]))
    cam = Camera(world_to_camera=np.eye(4), K=K, width=W, height=H)
    view = raycast_view(mesh, cam)
    fid = view.face_id
    np.testing.assert_array_equal(view.rgba[fid == 0][:, :3], np.tile([1, 0, 0], ((fid == 0).sum(), 1)))
    np.testing.assert_array_equal(view.rgba[fid == 1][:, :3], np.tile([0, 0, 1], ((fid == 1).sum(), 1)))


def test_texture_one_texel_per_pixel_is_reproduced_exactly():
    # a quad covering 8 x 6 pixels with an 8 x 6 texture: every pixel centre lands on a texel centre
    rng = np.random.default_rng(0)
    tex = rng.integers(0, 256, size=(6, 8, 3)).astype(np.uint8)  # image rows top -> bottom
    mesh = _square(10, 18, 5, 11)
    # corners (u0,v0), (u1,v0), (u1,v1), (u0,v1) in pixels; texture v = 1 is the image's top row
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.array([[0, 1], [1, 1], [1, 0], [0, 0]], float),
                                                image=Image.fromarray(tex))
    cam = Camera(world_to_camera=np.eye(4), K=K, width=W, height=H)
    rgba = raycast_view(mesh, cam).rgba
    np.testing.assert_allclose(rgba[5:11, 10:18, :3], tex / 255.0, atol=2e-4)


def test_shading_is_view_independent_and_lambertian():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    sphere.visual.vertex_colors = np.tile([200, 200, 200, 255], (len(sphere.vertices), 1)).astype(np.uint8)
    shading = Shading(light_dir=(0, 0, 1), ambient=0.25)
    K2 = np.array([[80.0, 0, 32], [0, 80.0, 32], [0, 0, 1]])
    cams = [Camera(world_to_camera=look_at(e, (0, 0, 0)), K=K2, width=64, height=64)
            for e in ([0, -4, 0.5], [3, 3, 1.5])]
    for cam in cams:
        view = raycast_view(sphere, cam, shading=shading)
        ys, xs = np.nonzero(view.rgba[..., 3] == 1)
        assert len(ys) > 500
        # hit points from the depth map; on a unit sphere the smooth normal is (nearly) the position itself
        z = view.depth[ys, xs]
        X_cam = np.stack([(xs + 0.5 - 32) / 80 * z, (ys + 0.5 - 32) / 80 * z, z], 1)
        X = (X_cam - cam.world_to_camera[:3, 3]) @ cam.world_to_camera[:3, :3]
        n = X / np.linalg.norm(X, axis=1, keepdims=True)
        expected = 200 / 255 * (0.25 + 0.75 * np.clip(n[:, 2], 0, None))  # a function of the point, not the view
        np.testing.assert_allclose(view.rgba[ys, xs, 0], expected, atol=0.02)


def test_render_views_and_face_ids_agree():
    mesh = _square(10, 30, 5, 20)
    cams = [Camera(world_to_camera=np.eye(4), K=K, width=W, height=H)] * 2
    imgs = render_views(mesh, cams)
    ids = render_face_ids(mesh, cams)
    assert len(imgs) == 2 and imgs[0].shape == (H, W, 4) and imgs[0].dtype == np.float32
    np.testing.assert_array_equal(ids[0] >= 0, imgs[0][..., 3] == 1)
    with pytest.raises(ValueError, match="samples_per_pixel"):
        raycast_view(mesh, cams[0], samples_per_pixel=0)
