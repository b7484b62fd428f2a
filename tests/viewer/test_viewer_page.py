"""The browser viewer in headless Chromium: loads without console errors and draws the mesh, frusta and photos
where the cameras say they should be."""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from trisplat.cameras import Camera
from trisplat.viewer.data import ViewerData
from trisplat.viewer.server import ViewerServer

BACKGROUND = np.array([0x20, 0x24, 0x28])  # the page's background colour (viewer.js BACKGROUND)
FRUSTUM = np.array([0xD0, 0xA0, 0x40])  # viewer.js FRUSTUM_COLOR
COLOR_TOLERANCE = 6  # 8-bit levels between a drawn pixel and the colour it should have (antialiasing aside)
CHROMIUM_TIMEOUT_S = 120
READY_TIMEOUT_S = 30
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--hide-scrollbars",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--enable-logging=stderr",
    "--v=0",
    "--virtual-time-budget=15000",
]


def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if path := shutil.which(name):
            return path
    pytest.skip("no chromium on PATH: `apt-get install chromium` (scripts/ci_extras.sh does it)")


def _screenshot(data: ViewerData, query: str, size: tuple[int, int]) -> tuple[np.ndarray, ViewerServer, str]:
    """Serve `data`, load the page in headless Chromium at `size` (w, h), return (RGB array, server, stderr)."""
    chromium = _chromium()
    server = ViewerServer(data, port=0)
    server.start_background()
    try:
        with tempfile.TemporaryDirectory(prefix="trisplat-chromium-") as tmp:
            shot = Path(tmp) / "shot.png"
            proc = subprocess.run(
                [
                    chromium,
                    *CHROMIUM_FLAGS,
                    f"--user-data-dir={tmp}/profile",
                    f"--window-size={size[0]},{size[1]}",
                    f"--screenshot={shot}",
                    server.url + "?" + query,
                ],
                capture_output=True,
                text=True,
                timeout=CHROMIUM_TIMEOUT_S,
            )
            assert shot.is_file(), f"chromium wrote no screenshot (rc {proc.returncode}): {proc.stderr[-2000:]}"
            image = np.asarray(Image.open(shot).convert("RGB")).astype(np.int16)
        server.wait_for_report("ready", READY_TIMEOUT_S)
    finally:
        server.shutdown()
        server.server_close()
    return image, server, proc.stderr


def _assert_clean_load(server: ViewerServer, stderr: str) -> dict:
    assert server.errors() == [], f"the page reported errors: {server.errors()}"
    bad = [
        line for line in stderr.splitlines() if "CONSOLE" in line and ("Uncaught" in line or "Failed to load" in line)
    ]
    assert bad == [], bad
    ready = next((r for r in server.reports if r.get("kind") == "ready"), None)
    assert ready is not None, f"the page never reported ready; reports: {server.reports}; stderr: {stderr[-1500:]}"
    return ready


def _near(image: np.ndarray, rgb) -> np.ndarray:
    return np.abs(image - np.asarray(rgb)).max(axis=-1) <= COLOR_TOLERANCE


def _look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV world_to_camera looking from eye to target."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([r, d, f])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return w2c


def test_mesh_file_view_shows_the_mesh_in_its_colour():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    colour = np.array([0.9, 0.25, 0.1])
    data = ViewerData(
        sphere.vertices * 3.0 + [100.0, -50.0, 7.0], sphere.faces, np.tile(colour, (len(sphere.vertices), 1))
    )
    image, server, stderr = _screenshot(data, "clean=1", (480, 360))
    ready = _assert_clean_load(server, stderr)
    assert ready["faces"] == len(sphere.faces) and ready["drawn_triangles"] == len(sphere.faces)
    assert image.shape == (360, 480, 3)
    mesh_px = _near(image, np.round(colour * 255))
    bg_px = _near(image, BACKGROUND)
    assert mesh_px.mean() > 0.08, f"only {mesh_px.mean():.3f} of the pixels show the mesh colour"
    assert bg_px.mean() > 0.3 and (mesh_px | bg_px).mean() > 0.97
    ys, xs = np.nonzero(mesh_px)  # the orbit view is centred on the mesh
    assert abs(xs.mean() - 240) < 24 and abs(ys.mean() - 180) < 24


def _camera_scene():
    """A green quad 2 m in front of camera 0 (off-centre principal point), a ring of other cameras, photos."""
    W, H = 400, 300
    K = np.array([[330.0, 0.0, 215.0], [0.0, 330.0, 140.0], [0.0, 0.0, 1.0]])
    eye, target = np.array([4.0, 1.0, 2.0]), np.array([0.0, 0.0, 0.5])
    cams = [Camera(_look_at(eye, target), K, W, H, name="cam0")]
    for a in np.linspace(0.6, 5.6, 5):
        cams.append(Camera(_look_at([5 * np.cos(a), 5 * np.sin(a), 2.5], target), K, W, H, name=f"ring{a:.1f}"))
    c2w = cams[0].camera_to_world
    corners_cam = np.array([[-0.6, -0.4, 2.0], [0.5, -0.4, 2.0], [0.5, 0.45, 2.0], [-0.6, 0.45, 2.0]])
    corners = corners_cam @ c2w[:3, :3].T + c2w[:3, 3]
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    colours = np.tile([0.1, 0.8, 0.3], (4, 1))
    uv = corners_cam[:, :2] / corners_cam[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    photo = np.zeros((H, W, 3), np.float32)
    photo[:, : W // 2] = [0.2, 0.3, 0.9]
    photo[:, W // 2 :] = [0.95, 0.85, 0.1]
    data = ViewerData(corners, faces, colours, cams, load_image=lambda i: photo, up=np.array([0.0, 0.0, 1.0]))
    return data, uv, photo


def test_snapped_camera_view_puts_the_mesh_where_the_camera_projects_it():
    data, uv, _ = _camera_scene()
    image, server, stderr = _screenshot(data, "clean=1&frusta=0&cam=0", (400, 300))
    ready = _assert_clean_load(server, stderr)
    assert ready["snapped"] == 0 and ready["photo"] is False
    drawn = _near(image, [round(0.1 * 255), round(0.8 * 255), round(0.3 * 255)])
    expected = np.zeros(drawn.shape, bool)  # pixel centres inside the projected rectangle
    xs, ys = np.arange(400) + 0.5, np.arange(300) + 0.5
    expected[np.ix_((ys > uv[:, 1].min()) & (ys < uv[:, 1].max()), (xs > uv[:, 0].min()) & (xs < uv[:, 0].max()))] = (
        True
    )
    iou = (drawn & expected).sum() / (drawn | expected).sum()
    assert iou > 0.97, f"drawn quad overlaps its projection with IoU {iou:.3f}"


def test_photo_toggle_shows_the_ground_truth_photo_of_that_camera():
    data, _, photo = _camera_scene()
    image, server, stderr = _screenshot(data, "clean=1&cam=0&photo=1", (400, 300))
    ready = _assert_clean_load(server, stderr)
    assert ready["photo"] is True
    diff = np.abs(image - np.round(photo * 255)).max(axis=-1)
    assert (diff <= COLOR_TOLERANCE).mean() > 0.99


def test_free_view_draws_the_training_cameras_as_frusta():
    data, _, _ = _camera_scene()
    image, server, stderr = _screenshot(data, "clean=1", (480, 360))
    ready = _assert_clean_load(server, stderr)
    assert ready["cameras"] == 6 and ready["snapped"] is None
    assert _near(image, FRUSTUM).sum() > 200, "no frustum lines visible"
    no_frusta, server, stderr = _screenshot(data, "clean=1&frusta=0", (480, 360))
    _assert_clean_load(server, stderr)
    assert _near(no_frusta, FRUSTUM).sum() < 10


def test_keys_jump_to_the_nearest_camera_and_toggle_its_photo():
    data, _, photo = _camera_scene()
    # the first view looks from camera 0's side, so G (photo of the nearest camera) must pick camera 0
    image, server, stderr = _screenshot(data, "clean=1&do=g", (400, 300))
    ready = _assert_clean_load(server, stderr)
    assert ready["snapped"] == 0 and ready["photo"] is True
    assert (np.abs(image - np.round(photo * 255)).max(axis=-1) <= COLOR_TOLERANCE).mean() > 0.99
    # ] ] ] [ steps through cameras 0, 1, 2, 1; G shows the photo, G again returns to the mesh
    _, server, stderr = _screenshot(data, "clean=1&do=],],],[,g,g", (400, 300))
    ready = _assert_clean_load(server, stderr)
    assert ready["snapped"] == 1 and ready["photo"] is False
