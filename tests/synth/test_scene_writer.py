"""Orbit cameras, the procedural meshes and the Blender-format writer (cameras round-trip through the JSON)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
from PIL import Image

from trisplat.synth import (
    DEMO_SHADING,
    demo_mesh,
    orbit_cameras,
    raycast_view,
    two_object_mesh,
    write_blender_scene,
)
from trisplat.synth.blender import CV_TO_GL
from trisplat.synth.orbit import intrinsics, look_at


def _project(cam, X):
    x = X @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    uv = x @ cam.K.T
    return uv[:, :2] / uv[:, 2:3]


def test_look_at_is_a_proper_rotation_with_opencv_axes():
    w2c = look_at([0, -5, 0], [0, 0, 0], up=(0, 0, 1))
    R = w2c[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(R[2], [0, 1, 0], atol=1e-12)  # looks along +y towards the target
    np.testing.assert_allclose(R[1], [0, 0, -1], atol=1e-12)  # image y (down) is world -z: up is up
    np.testing.assert_allclose(R[0], [1, 0, 0], atol=1e-12)  # image x is world +x (right-handed)
    # looking straight down the up axis still gives a rotation
    R2 = look_at([0, 0, 5], [0, 0, 0])[:3, :3]
    assert np.isclose(np.linalg.det(R2), 1.0) and np.allclose(R2[2], [0, 0, -1])


def test_orbit_cameras_look_at_centre_at_radius_within_elevations():
    center = np.array([0.3, -0.2, 0.5])
    cams = orbit_cameras(40, 3.0, 120, 80, fov_deg=50, center=center, seed=3, elevation_deg=(15, 70))
    assert len(cams) == 40
    for cam in cams:
        np.testing.assert_allclose(np.linalg.norm(cam.center - center), 3.0, rtol=1e-12)
        np.testing.assert_allclose(_project(cam, center[None])[0], [60, 40], atol=1e-9)  # centre -> image centre
        elev = math.degrees(math.asin((cam.center - center)[2] / 3.0))
        assert 15 - 1e-9 <= elev <= 70 + 1e-9
        # the horizontal field of view is 50 degrees: a point 25 degrees off axis lands on the image edge
    np.testing.assert_allclose(cams[0].K, intrinsics(120, 80, 50))
    assert np.isclose(2 * math.degrees(math.atan(60 / cams[0].K[0, 0])), 50)
    # evenly spread: no two cameras nearly coincide; different seeds rotate the spiral
    P = np.stack([c.center for c in cams])
    d = np.linalg.norm(P[:, None] - P[None], axis=-1) + np.eye(40) * 1e9
    assert d.min() > 0.3
    other = orbit_cameras(40, 3.0, 120, 80, fov_deg=50, center=center, seed=4, elevation_deg=(15, 70))
    assert not np.allclose(other[0].center, cams[0].center)
    with pytest.raises(ValueError, match="elevations"):
        orbit_cameras(3, 1.0, 8, 8, elevation_deg=(0, 100))


def test_demo_and_two_object_meshes():
    m = demo_mesh()
    assert m.visual.kind == "vertex" and 1000 < len(m.faces) < 10000
    assert m.bounds[0, 2] == 0.0  # the ground disk at z = 0 is the lowest point
    assert m.area_faces.min() > 0  # no degenerate faces
    mesh, label = two_object_mesh()
    assert label.shape == (len(mesh.faces),) and set(np.unique(label)) == {1, 2}
    sphere = mesh.vertices[np.unique(mesh.faces[label == 1])]
    np.testing.assert_allclose(np.linalg.norm(sphere - [-0.35, 0, 0], axis=1), 0.35, rtol=1e-9)
    # outward winding: face normals point away from each object's centre
    c = mesh.triangles_center
    assert (np.einsum("ij,ij->i", mesh.face_normals[label == 1], c[label == 1] - [-0.35, 0, 0]) > 0).all()
    assert (np.einsum("ij,ij->i", mesh.face_normals[label == 2], c[label == 2] - [0.4, 0, 0]) > 0).all()
    # the baked light: ground vertices (normal +z) are their albedo times ambient + (1 - ambient) * light_z
    flat, lit = demo_mesh(shaded=False), demo_mesh()
    ground = np.nonzero(flat.vertex_normals[:, 2] > 0.999)[0]
    light = np.asarray(DEMO_SHADING.light_dir) / np.linalg.norm(DEMO_SHADING.light_dir)
    k = DEMO_SHADING.ambient + (1 - DEMO_SHADING.ambient) * light[2]
    np.testing.assert_allclose(lit.visual.vertex_colors[ground, :3],
                               np.round(flat.visual.vertex_colors[ground, :3] * k), atol=1)
    _, label_g = two_object_mesh(ground=True)
    assert set(np.unique(label_g)) == {0, 1, 2}


def test_blender_scene_round_trips_cameras_and_images(tmp_path):
    mesh = demo_mesh()
    out = write_blender_scene(tmp_path / "scene", mesh, n_train=5, n_test=2, width=48, height=40, fov_deg=45,
                              samples_per_pixel=1, shading=DEMO_SHADING, seed=7, n_points=300)
    meta = json.loads((out / "transforms_train.json").read_text())
    lego = {"camera_angle_x", "frames"}
    assert set(meta) == lego and set(meta["frames"][0]) == {"file_path", "rotation", "transform_matrix"}
    assert meta["frames"][0]["file_path"] == "./train/r_0"
    info = json.loads((out / "synth.json").read_text())
    cams = orbit_cameras(5, info["radius"], 48, 40, 45, info["center"], 7, (10, 80))
    for cam, frame in zip(cams, meta["frames"]):
        c2w_gl = np.array(frame["transform_matrix"])
        w2c = np.linalg.inv(c2w_gl @ CV_TO_GL)  # the loader's conversion (docs/conventions.md)
        np.testing.assert_allclose(w2c, cam.world_to_camera, atol=1e-9)
        # intrinsics from camera_angle_x, as a Blender loader computes them
        f = 0.5 * 48 / math.tan(meta["camera_angle_x"] / 2)
        np.testing.assert_allclose(cam.K, [[f, 0, 24], [0, f, 20], [0, 0, 1]], atol=1e-9)
        # the PNG holds exactly the ray-cast view from that camera (straight alpha, 8 bit)
        img = np.asarray(Image.open(out / (frame["file_path"] + ".png"))).astype(np.float32) / 255
        assert img.shape == (40, 48, 4)
        ref = raycast_view(mesh, cam, shading=DEMO_SHADING).rgba
        np.testing.assert_allclose(img, ref, atol=0.5 / 255 + 1e-6)
    test_meta = json.loads((out / "transforms_test.json").read_text())
    assert len(test_meta["frames"]) == 2 and (out / "test" / "r_1.png").exists()
    gt = trimesh.load(out / "gt_mesh.ply", process=False)
    np.testing.assert_allclose(gt.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(gt.faces, mesh.faces)
    pts = trimesh.load(out / "points3d.ply")
    assert len(pts.vertices) == 300
    assert trimesh.proximity.closest_point(mesh, pts.vertices)[1].max() < 1e-6  # samples lie on the surface


def test_blender_scene_loads_through_load_dataset(tmp_path):
    data = pytest.importorskip("trisplat.data")
    if not hasattr(data, "load_dataset"):
        pytest.skip("trisplat.data.load_dataset is not written yet")
    mesh, _ = two_object_mesh()
    out = write_blender_scene(tmp_path / "s", mesh, n_train=4, n_test=2, width=32, height=32, samples_per_pixel=1,
                              seed=1, n_points=0)
    scene = data.load_dataset(out)
    assert len(scene.train_indices) == 4 and len(scene.test_indices) == 2
    info = json.loads((out / "synth.json").read_text())
    cams = orbit_cameras(4, info["radius"], 32, 32, 40, info["center"], 1, (10, 80))
    X = mesh.vertices[::37]
    Xn = X @ scene.normalization[:3, :3].T + scene.normalization[:3, 3]
    for i, cam in zip(scene.train_indices, cams):
        loaded = scene.cameras[int(i)]
        assert (loaded.width, loaded.height) == (32, 32)
        np.testing.assert_allclose(_project(loaded, Xn), _project(cam, X), atol=1e-4)
        img = scene.load_image(int(i))
        ref = raycast_view(mesh, cam, background=scene.background).rgba[..., :3]
        np.testing.assert_allclose(img, ref, atol=1.0 / 255 + 1e-6)


def test_spot_mesh_is_textured_and_z_up():
    from conftest import shared_data

    from trisplat.synth import spot_mesh

    obj = shared_data("meshes") / "spot_triangulated.obj"
    raw = trimesh.load(obj, process=False, force="mesh")
    spot = spot_mesh(obj)
    assert spot.visual.kind == "texture" and spot.visual.material.image.size == (1024, 1024)
    # +90 degrees about x: the original y (up) becomes z, the original z becomes -y
    np.testing.assert_allclose(spot.vertices, np.c_[raw.vertices[:, 0], -raw.vertices[:, 2], raw.vertices[:, 1]],
                               atol=1e-12)
    np.testing.assert_array_equal(spot.faces, raw.faces)
    # a render shows the texture: the pixel colours come from its palette (white hide, black patches, pink nose)
    cam = orbit_cameras(1, 3.5, 64, 64, 40, center=spot.bounds.mean(0), seed=0)[0]
    rgba = raycast_view(spot, cam).rgba
    hit = rgba[..., 3] == 1
    assert hit.mean() > 0.1
    tex = np.asarray(spot.visual.material.image.convert("RGB"), np.float32)[::8, ::8].reshape(-1, 3) / 255
    d = np.linalg.norm(rgba[hit][:, None, :3] - tex[None], axis=-1).min(1)
    assert np.median(d) < 0.02
    with pytest.raises(FileNotFoundError, match="Spot mesh not found"):
        spot_mesh(obj.with_name("nope.obj"))
