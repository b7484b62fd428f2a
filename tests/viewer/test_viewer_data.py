"""Viewer data and server: capture-frame cameras consistent with the mesh, packed mesh layout, routes, runs."""

from __future__ import annotations

import io
import json
import urllib.error
import urllib.request

import numpy as np
import pytest
import trimesh

from trisplat.cameras import Camera
from trisplat.io import export_mesh, save_model_ply
from trisplat.scene.model import TriangleScene
from trisplat.viewer.data import (
    DEFAULT_COLOR,
    ViewerData,
    rigid_cameras_in_capture_frame,
    viewer_data_from_mesh,
    viewer_data_from_run,
)
from trisplat.viewer.server import ViewerServer


def _project(cam: Camera, pts: np.ndarray) -> np.ndarray:
    x = pts @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    return (x[:, :2] / x[:, 2:]) * [cam.K[0, 0], cam.K[1, 1]] + [cam.K[0, 2], cam.K[1, 2]]


def test_capture_frame_cameras_see_capture_points_where_normalised_cameras_saw_them():
    rng = np.random.default_rng(0)
    N = np.eye(4)
    N[:3, :3] *= 0.2
    N[:3, 3] = [3.0, -1.0, 0.5]
    R = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, [0.1, -0.2, 3.0]
    cam_n = Camera(w2c, np.array([[100.0, 0, 40], [0, 110.0, 30], [0, 0, 1]]), 80, 60, name="a")
    (cam_c,) = rigid_cameras_in_capture_frame([cam_n], N)
    pts_c = rng.normal(size=(20, 3)) * 5
    pts_n = pts_c * 0.2 + N[:3, 3]
    np.testing.assert_allclose(_project(cam_c, pts_c), _project(cam_n, pts_n), atol=1e-9)
    np.testing.assert_allclose(cam_c.world_to_camera[:3, :3], R, atol=1e-12)  # rigid: orientation unchanged
    np.testing.assert_allclose(cam_c.center, (cam_n.center - N[:3, 3]) / 0.2, atol=1e-9)


def test_scene_dict_uses_opengl_axes_relative_to_the_mesh_origin():
    cam = Camera(np.eye(4), np.diag([50.0, 50.0, 1.0]), 64, 48)
    data = ViewerData([[10.0, 0, 0], [12.0, 0, 0], [10.0, 2.0, 0]], [[0, 1, 2]], np.zeros((3, 3)), [cam])
    d = data.scene_dict()
    np.testing.assert_allclose(d["origin"], [11.0, 1.0, 0.0])
    c2w = np.array(d["cameras"][0]["c2w"]).reshape(4, 4)
    np.testing.assert_allclose(c2w[:3, :3], np.diag([1.0, -1.0, -1.0]))  # OpenCV -> OpenGL camera axes
    np.testing.assert_allclose(c2w[:3, 3], [-11.0, -1.0, 0.0])
    raw = data.mesh_bytes()
    assert len(raw) == 3 * 12 + 12 + 12  # positions, 9 colour bytes padded to 12, one face
    np.testing.assert_allclose(np.frombuffer(raw[:36], "<f4").reshape(3, 3)[0], [-1.0, -1.0, 0.0])
    np.testing.assert_array_equal(np.frombuffer(raw[48:], "<u4"), [0, 1, 2])


def test_mesh_without_colours_is_grey_and_bad_meshes_are_refused(tmp_path):
    box = trimesh.creation.box()
    export_mesh(tmp_path / "b.ply", box.vertices, box.faces)
    data = viewer_data_from_mesh(tmp_path / "b.ply")
    np.testing.assert_allclose(data.colors, np.broadcast_to(DEFAULT_COLOR, data.positions.shape))
    with pytest.raises(ValueError, match="faces index vertices outside"):
        ViewerData(box.vertices, box.faces + 100, np.zeros((8, 3)))


def test_server_routes_and_reports():
    box = trimesh.creation.box()
    server = ViewerServer(ViewerData(box.vertices, box.faces, np.full((8, 3), 0.5)), port=0)
    server.start_background()
    try:
        with urllib.request.urlopen(server.url + "api/scene.json") as r:
            assert json.loads(r.read())["num_faces"] == 12
        with urllib.request.urlopen(server.url) as r:
            assert b"viewer.js" in r.read()
        with urllib.request.urlopen(server.url + "static/three.bundle.min.js") as r:
            assert r.headers["Content-Type"] == "text/javascript"
        for bad in ("static/../data.py", "static/%2e%2e/server.py", "api/image/0.png", "nothing"):
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(server.url + bad)
            assert err.value.code == 404, bad
        req = urllib.request.Request(
            server.url + "api/report", data=b'{"kind": "error", "message": "boom"}', method="POST"
        )
        urllib.request.urlopen(req).read()
        assert server.errors() == [{"kind": "error", "message": "boom"}]
    finally:
        server.shutdown()
        server.server_close()


def test_the_hold_image_is_answered_only_once_the_page_is_ready():
    """/api/hold (the image a ?hold=1 page inserts, so headless Chromium's load event and virtual time wait for the
    mesh) stays unanswered until the page reports 'ready' (or an error), then answers a 1x1 GIF."""
    import threading

    from PIL import Image

    box = trimesh.creation.box()
    server = ViewerServer(ViewerData(box.vertices, box.faces, np.full((8, 3), 0.5)), port=0)
    server.start_background()
    got = {}

    def fetch_hold():
        with urllib.request.urlopen(server.url + "api/hold", timeout=30) as r:
            got["type"], got["body"] = r.headers["Content-Type"], r.read()

    try:
        waiter = threading.Thread(target=fetch_hold)
        waiter.start()
        waiter.join(1.0)
        assert waiter.is_alive() and not got  # no report yet: held
        req = urllib.request.Request(server.url + "api/report", data=b'{"kind": "layout"}', method="POST")
        urllib.request.urlopen(req).read()
        waiter.join(0.5)
        assert waiter.is_alive()  # a layout report is not 'ready'
        req = urllib.request.Request(server.url + "api/report", data=b'{"kind": "ready"}', method="POST")
        urllib.request.urlopen(req).read()
        waiter.join(10.0)
        assert not waiter.is_alive() and got["type"] == "image/gif"
        assert Image.open(io.BytesIO(got["body"])).size == (1, 1)
        with urllib.request.urlopen(server.url + "api/hold", timeout=5) as r:  # once ready, at once
            assert r.read() == got["body"]
    finally:
        server.shutdown()
        server.server_close()


def test_run_view_undoes_the_normalisation_for_mesh_and_cameras(tmp_path):
    from trisplat.data import load_dataset
    from trisplat.synth.blender import write_blender_scene

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.7)
    mesh.apply_translation([5.0, -2.0, 1.0])  # far from the origin, so the normalisation is not the identity
    mesh.visual.vertex_colors = np.tile([200, 60, 30, 255], (len(mesh.vertices), 1)).astype(np.uint8)
    capture = write_blender_scene(
        tmp_path / "capture", mesh, n_train=3, n_test=1, width=32, height=32, samples_per_pixel=1, n_points=0
    )
    sd = load_dataset(capture)
    N = sd.normalization
    assert not np.allclose(N, np.eye(4))
    pos_n = mesh.vertices @ N[:3, :3].T + N[:3, 3]
    scene = TriangleScene.from_rgb(pos_n.astype(np.float32), mesh.faces, np.tile([0.8, 0.2, 0.1], (len(pos_n), 1)))
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": str(capture)}))
    save_model_ply(run / "model.ply", scene, N)

    data = viewer_data_from_run(run)
    np.testing.assert_allclose(data.positions, mesh.vertices, atol=1e-5)
    assert len(data.cameras) == len(sd.train_indices) == 3
    for cam_c, i in zip(data.cameras, sd.train_indices):
        cam_n = sd.cameras[int(i)]
        np.testing.assert_allclose(_project(cam_c, mesh.vertices), _project(cam_n, pos_n), atol=1e-6)
    np.testing.assert_array_equal(data.up, [0.0, 0.0, 1.0])  # Blender captures are Z-up
    photo = data.load_image(0)
    assert photo.shape == (32, 32, 3)
    np.testing.assert_array_equal(photo, sd.load_image(int(sd.train_indices[0])))


def test_view_command_rejects_what_it_cannot_show(tmp_path):
    from trisplat.commands.view import main as view_main

    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(FileNotFoundError, match="notes.txt: neither a run folder nor a mesh file"):
        view_main([str(tmp_path / "notes.txt"), "--no-browser"])
    with pytest.raises(FileNotFoundError, match="not a trisplat run"):
        view_main([str(tmp_path), "--no-browser"])
