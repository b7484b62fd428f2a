"""Undistortion against an analytic image: a pattern defined on ideal (undistorted) rays, rendered through each
camera model with a distortion inverse written here (independent of pycolmap), must come back on the pinhole grid."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from trisplat.data import load_dataset

W, H = 160, 120


def pattern(x, y):
    """Smooth RGB pattern of normalised (undistorted) image coordinates."""
    return np.stack([0.5 + 0.4 * np.sin(5 * x) * np.cos(4 * y), 0.5 + 0.4 * np.cos(3 * x + 2 * y), 0.5 + 0.3 * x], -1)


def distort(model, params, x, y):
    """Forward distortion of normalised coordinates (COLMAP's formulas, written out)."""
    if model == "OPENCV_FISHEYE":
        k1, k2, k3, k4 = params[4:]
        r = np.hypot(x, y)
        th = np.arctan(r)
        thd = th * (1 + k1 * th**2 + k2 * th**4 + k3 * th**6 + k4 * th**8)
        s = np.where(r > 1e-12, thd / np.maximum(r, 1e-12), 1.0)
        return x * s, y * s
    if model == "SIMPLE_RADIAL":
        k1, k2, p1, p2 = params[3], 0.0, 0.0, 0.0
    elif model == "RADIAL":
        k1, k2, p1, p2 = params[3], params[4], 0.0, 0.0
    else:
        k1, k2, p1, p2 = params[4:8]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def undistort_points(model, params, xd, yd, iters=200):
    """Inverse of `distort` by Newton iteration with a numerical Jacobian."""
    x, y = xd.copy(), yd.copy()
    eps = 1e-7
    for _ in range(iters):
        fx, fy = distort(model, params, x, y)
        ex, ey = fx - xd, fy - yd
        ax, ay = distort(model, params, x + eps, y)
        bx, by = distort(model, params, x, y + eps)
        j11, j21, j12, j22 = (ax - fx) / eps, (ay - fy) / eps, (bx - fx) / eps, (by - fy) / eps
        det = j11 * j22 - j12 * j21
        x = x - (j22 * ex - j12 * ey) / det
        y = y - (-j21 * ex + j11 * ey) / det
    return x, y


CASES = {
    "SIMPLE_RADIAL": (100.0, 80.0, 60.0, -0.1),
    "RADIAL": (100.0, 80.0, 60.0, -0.1, 0.01),
    "OPENCV": (100.0, 104.0, 78.0, 61.0, -0.1, 0.01, 0.006, -0.004),
    "OPENCV_FISHEYE": (90.0, 92.0, 80.0, 60.0, 0.05, -0.02, 0.01, 0.0),
}


def intrinsics(model, params):
    if model in ("SIMPLE_RADIAL", "RADIAL"):
        return params[0], params[0], params[1], params[2]
    return params[:4]


def write_capture(root, model, params):
    fx, fy, cx, cy = intrinsics(model, params)
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x, y = undistort_points(model, params, (cols - cx) / fx, (rows - cy) / fy)
    img = np.clip(pattern(x, y) * 255 + 0.5, 0, 255).astype(np.uint8)
    (root / "images").mkdir(parents=True)
    Image.fromarray(img).save(root / "images" / "a.png")
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"1 {model} {W} {H} {' '.join(repr(p) for p in params)}\n")
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    (sparse / "points3D.txt").write_text("# no points\n")
    return img


@pytest.mark.parametrize("model", list(CASES))
def test_undistortion_recovers_the_pinhole_image(tmp_path, model):
    params = CASES[model]
    distorted = write_capture(tmp_path / "cap", model, params)
    data = load_dataset(tmp_path / "cap", cache_dir=tmp_path / "cache", test_every=0)
    cam = data.cameras[0]
    assert cam.extras["undistorted"] and cam.image_path.parent.is_relative_to(tmp_path / "cache")
    got = data.load_image(0)
    assert got.shape == (cam.height, cam.width, 3)
    cols, rows = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    K = cam.K
    want = pattern((cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1])
    err = np.abs(got - want)
    inner = err[2:-2, 2:-2]
    assert np.median(inner) < 0.003 and np.percentile(inner, 99) < 0.01  # 8-bit quantisation is 0.002
    # control: treating the distorted image as pinhole is clearly worse, so the test sees the distortion
    fx, fy, cx, cy = intrinsics(model, params)
    c2, r2 = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    naive = np.abs(distorted / 255.0 - pattern((c2 - cx) / fx, (r2 - cy) / fy))
    assert np.percentile(naive, 99) > 3 * np.percentile(inner, 99)
    # the downscaled undistorted camera is the same camera with K / 2
    half = load_dataset(tmp_path / "cap", downscale=2, cache_dir=tmp_path / "cache", test_every=0)
    hc = half.cameras[0]
    assert (hc.width, hc.height) == (round(cam.width / 2), round(cam.height / 2))
    np.testing.assert_allclose(hc.K[0], K[0] * hc.width / cam.width)
    np.testing.assert_allclose(hc.K[1], K[1] * hc.height / cam.height)


def test_zero_distortion_needs_no_cache(tmp_path):
    write_capture(tmp_path / "cap", "OPENCV", (100.0, 100.0, 80.0, 60.0, 0.0, 0.0, 0.0, 0.0))
    data = load_dataset(tmp_path / "cap", cache_dir=tmp_path / "cache", test_every=0)
    assert data.cameras[0].image_path == tmp_path / "cap" / "images" / "a.png"
    assert not (tmp_path / "cache").exists()


def test_rgba_undistortion_does_not_bleed_hidden_colour(tmp_path):
    """Grey where opaque, pure red where fully transparent: resampling premultiplied keeps every composited pixel
    on the grey-white segment (R == G == B); resampling straight alpha would leak red at the silhouette."""
    model, params = "OPENCV", CASES["OPENCV"]
    write_capture(tmp_path / "cap", model, params)
    fx, fy, cx, cy = intrinsics(model, params)
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x, y = undistort_points(model, params, (cols - cx) / fx, (rows - cy) / fy)
    opaque = (x**2 + y**2) < 0.3**2
    rgba = np.zeros((H, W, 4), np.uint8)
    rgba[opaque] = [128, 128, 128, 255]
    rgba[~opaque] = [255, 0, 0, 0]
    Image.fromarray(rgba, "RGBA").save(tmp_path / "cap" / "images" / "a.png")
    data = load_dataset(tmp_path / "cap", cache_dir=tmp_path / "cache", test_every=0, downscale=2)
    img = data.load_image(0)
    assert (img[..., 1] < 0.6).sum() > 50 and (img[..., 1] > 0.99).sum() > 50  # both regions are there
    partial = (img[..., 1] > 0.55) & (img[..., 1] < 0.95)
    assert partial.sum() > 10  # the silhouette edge was resampled
    assert np.abs(img[..., 0] - img[..., 1]).max() < 2.5 / 255
