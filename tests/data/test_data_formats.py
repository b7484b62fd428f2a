"""Every capture format on the shared data: cameras, splits, images, depth, points, normalisation, downscaling."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_data
from PIL import Image

from trisplat.data import load_dataset
from trisplat.data.images import read_image


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("trisplat_cache"))


@pytest.fixture(scope="module")
def fox_colmap(cache):
    return load_dataset(shared_data("fox") / "sparse" / "0", downscale=4, cache_dir=cache, prepare="lazy")


@pytest.fixture(scope="module")
def fox_ngp(cache):
    # fox holds both a transforms.json and a COLMAP model with points: auto picks COLMAP, so ask for ngp
    return load_dataset(shared_data("fox"), downscale=4, cache_dir=cache, prepare="lazy", format="ngp")


def project(cam, X):
    """Pixel coordinates (corner-based, centres at +0.5) and depth of world points X [N,3]."""
    xc = X @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    uv = xc @ cam.K.T
    return uv[:, :2] / uv[:, 2:3], xc[:, 2]


def umeyama(src, dst):
    """Similarity (s, R, t) minimising |s R src + t - dst|^2."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / (a**2).sum(1).mean()
    return s, R, mu_d - s * R @ mu_s


# ---------------------------------------------------------------- Blender / NeRF-synthetic


def test_lego_blender_cameras_split_and_alpha(cache):
    root = shared_data("lego")
    data = load_dataset(root, downscale=8, cache_dir=cache)
    assert data.format == "blender"
    assert len(data.cameras) == 300 and len(data.train_indices) == 100 and len(data.test_indices) == 200
    assert data.cameras[data.test_indices[0]].name.startswith("test/")
    import json

    angle = json.loads((root / "transforms_train.json").read_text())["camera_angle_x"]
    cam = data.cameras[0]
    assert (cam.width, cam.height) == (50, 50)
    np.testing.assert_allclose(cam.K[0, 0], 0.5 * 400 / np.tan(0.5 * angle) / 8, rtol=1e-12)
    np.testing.assert_allclose(cam.K[:2, 2], [25.0, 25.0])
    # The object box projects around every silhouette: checks the OpenGL -> OpenCV pose conversion.
    lo, hi = data.bounds
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    for i in (0, 37, 150):
        c = data.cameras[i]
        uv, z = project(c, corners)
        assert (z > 0).all()
        src = read_image(c.extras["source_image"])
        rows, cols = np.nonzero(src[..., 3] > 0)
        u, v = (cols + 0.5) / 8, (rows + 0.5) / 8
        assert u.min() >= uv[:, 0].min() and u.max() <= uv[:, 0].max()
        assert v.min() >= uv[:, 1].min() and v.max() <= uv[:, 1].max()
    # the box really is the object's: its centre projects near the silhouette's centre
    uv0, _ = project(data.cameras[0], (0.5 * (lo + hi))[None])
    src = read_image(data.cameras[0].extras["source_image"])
    rows, cols = np.nonzero(src[..., 3] > 0)
    assert np.hypot(uv0[0, 0] - cols.mean() / 8, uv0[0, 1] - rows.mean() / 8) < 50 / 8


def test_lego_background_compositing(cache):
    root = shared_data("lego")
    white = load_dataset(root, cache_dir=cache)
    black = load_dataset(root, cache_dir=cache, background=(0.0, 0.0, 0.0))
    assert white.options["background"] == [1.0, 1.0, 1.0] and black.background == (0.0, 0.0, 0.0)
    assert white.cameras[0].image_path.resolve() == (root / "train" / "r_0.png").resolve()  # the original file
    src = np.asarray(Image.open(root / "train" / "r_0.png")).astype(np.float32) / 255
    a = src[..., 3:]
    np.testing.assert_allclose(white.load_image(0), src[..., :3] * a + (1 - a), atol=1e-6)
    np.testing.assert_allclose(black.load_image(0), src[..., :3] * a, atol=1e-6)
    assert (a == 0).any() and np.all(white.load_image(0)[a[..., 0] == 0] == 1.0)


@pytest.mark.parametrize("factor", [2, 4, 8])
def test_downscale_scales_K_and_area_filters(cache, factor):
    root = shared_data("lego")
    full = load_dataset(root, cache_dir=cache, test_every=0)
    small = load_dataset(root, downscale=factor, cache_dir=cache, prepare="lazy")
    for i in (0, 150):
        c1, cd = full.cameras[i], small.cameras[i]
        assert (cd.width, cd.height) == (400 // factor, 400 // factor)
        np.testing.assert_allclose(cd.K[:2], c1.K[:2] / factor, rtol=1e-12)
        np.testing.assert_array_equal(cd.world_to_camera, c1.world_to_camera)
        # composite-then-box-average == box-average (premultiplied) then composite, up to 8-bit rounding
        big = full.load_image(i)
        ref = big.reshape(400 // factor, factor, 400 // factor, factor, 3).mean((1, 3))
        assert np.abs(small.load_image(i) - ref).max() < 3.0 / 255
        assert cd.image_path.exists() and root not in cd.image_path.parents  # written on first load (lazy)


def test_options_reload_the_same_dataset(cache):
    root = shared_data("lego")
    a = load_dataset(root, downscale=8, cache_dir=cache, background=(0.2, 0.3, 0.4), test_every=4)
    opts = dict(a.options)
    b = load_dataset(root, **opts)
    np.testing.assert_array_equal(a.normalization, b.normalization)
    assert [c.image_path for c in a.cameras] == [c.image_path for c in b.cameras]
    np.testing.assert_array_equal(a.load_image(3), b.load_image(3))
    assert b.background == (0.2, 0.3, 0.4)


# ---------------------------------------------------------------- instant-ngp and COLMAP (fox)


def test_fox_ngp_skips_missing_frames(fox_ngp):
    assert fox_ngp.format == "ngp"
    assert len(fox_ngp.cameras) == 50
    assert any("skipped 17 of 67 frames" in w for w in fox_ngp.warnings)
    assert len(fox_ngp.test_indices) == 7 and 0 in fox_ngp.test_indices and 8 in fox_ngp.test_indices
    assert all(c.extras["source_model"] == "OPENCV" and c.extras["undistorted"] for c in fox_ngp.cameras)


def test_transforms_json_path_reads_like_its_folder(fox_ngp, cache):
    direct = load_dataset(shared_data("fox") / "transforms.json", downscale=4, cache_dir=cache, prepare="lazy")
    assert direct.root == fox_ngp.root and len(direct.cameras) == len(fox_ngp.cameras)
    for a, b in zip(direct.cameras, fox_ngp.cameras):
        np.testing.assert_array_equal(a.world_to_camera, b.world_to_camera)
        assert a.image_path == b.image_path


def test_fox_colmap_reads_rigs_frames_model(fox_colmap):
    assert fox_colmap.format == "colmap"
    assert len(fox_colmap.cameras) == 50 and fox_colmap.points.shape == (13540, 3)
    assert fox_colmap.point_colors.shape == (13540, 3) and 0 <= fox_colmap.point_colors.min() <= 1
    names = [c.name for c in fox_colmap.cameras]
    assert names == sorted(names)
    # normalisation rule 'cameras': centres within radius 1/1.1 about the origin, one touches it
    centres = np.stack([c.center for c in fox_colmap.cameras])
    np.testing.assert_allclose(centres.mean(0), 0.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1).max(), 1 / 1.1, rtol=1e-9)
    N = fox_colmap.normalization
    assert np.allclose(N[:3, :3], N[0, 0] * np.eye(3))  # translation + uniform scale only


def test_fox_ngp_and_colmap_agree_after_similarity(fox_ngp, fox_colmap):
    a = {c.name: c for c in fox_ngp.cameras}
    b = {c.name: c for c in fox_colmap.cameras}
    names = sorted(set(a) & set(b))
    assert len(names) == 50
    ca = np.stack([a[n].center for n in names])
    cb = np.stack([b[n].center for n in names])
    s, R, t = umeyama(cb, ca)
    residual = np.linalg.norm(s * cb @ R.T + t - ca, axis=1)
    radius = np.linalg.norm(ca - ca.mean(0), axis=1).max()
    assert residual.max() < 0.01 * radius
    fa = np.stack([a[n].forward for n in names])
    fb = np.stack([b[n].forward for n in names]) @ R.T
    angles = np.degrees(np.arccos(np.clip((fa * fb).sum(1), -1, 1)))
    assert angles.max() < 1.0


def test_colmap_points_reproject_onto_undistorted_observations(fox_colmap):
    import pycolmap

    rec = pycolmap.Reconstruction(str(shared_data("fox") / "sparse" / "0"))
    by_name = {im.name: im for im in rec.images.values()}
    src_cam = rec.cameras[1]
    N = fox_colmap.normalization
    errors, colour_err, shifted_err = [], [], []
    for i in (1, 20):
        cam = fox_colmap.cameras[i]
        im = by_name[cam.name]
        obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        xy = np.array([o[0] for o in obs])
        X = np.array([o[1] for o in obs])
        Xn = X @ N[:3, :3].T + N[:3, 3]
        uv, z = project(cam, Xn)
        assert (z > 0).all()
        # the observation, undistorted with COLMAP's own camera model, then through our K
        ray = np.asarray(src_cam.cam_from_img(xy))
        expected = np.c_[ray, np.ones(len(ray))] @ cam.K.T
        errors.append(np.linalg.norm(uv - expected[:, :2], axis=1) * 4)  # in full-resolution pixels
        # the undistorted image shows at `uv` what the original shows at `xy` (checks the cached remap)
        und = fox_colmap.load_image(i)
        orig = read_image(shared_data("fox") / "images" / cam.name).astype(np.float32) / 255
        orig4 = orig[: orig.shape[0] // 4 * 4, : orig.shape[1] // 4 * 4]
        orig4 = orig4.reshape(orig.shape[0] // 4, 4, orig.shape[1] // 4, 4, 3).mean((1, 3))
        inside = (uv[:, 0] > 2) & (uv[:, 1] > 2) & (uv[:, 0] < cam.width - 2) & (uv[:, 1] < cam.height - 2)

        def sample(img, pts):
            r = np.clip(np.floor(pts[:, 1]).astype(int), 0, img.shape[0] - 1)
            c = np.clip(np.floor(pts[:, 0]).astype(int), 0, img.shape[1] - 1)
            return img[r, c]

        ref = sample(orig4, xy[inside] / 4)
        colour_err.append(np.abs(sample(und, uv[inside]) - ref).mean())
        shifted_err.append(np.abs(sample(und, uv[inside] + [3.0, 0.0]) - ref).mean())
    errors = np.concatenate(errors)
    assert np.median(errors) < 1.0 and np.percentile(errors, 95) < 3.0
    assert max(colour_err) < 0.04 and min(shifted_err) > 3 * max(colour_err)


# ---------------------------------------------------------------- RGB-D


def test_icl_rgbd_depth_consistent_across_frames(cache):
    data = load_dataset(shared_data("icl_rgbd"), cache_dir=cache)
    assert data.format == "rgbd" and len(data.cameras) == 5
    assert data.options["normalize"] == "points"  # cameras a few cm apart: the content sets the scale
    assert data.scene_radius < 0.05 and 0.5 < data.bounds_radius <= 1.0
    np.testing.assert_allclose(data.cameras[0].K, [[525, 0, 320], [0, 525, 240], [0, 0, 1]])  # +0.5 px centre
    raw = np.asarray(Image.open(data.cameras[0].depth_path)).astype(np.float32)
    d0 = data.load_depth(0)
    np.testing.assert_allclose(d0, raw / 1000 * data.scale, rtol=1e-6)
    # back-project frame 0, project into frame 4: depths agree (source: 6.6 mm median between frames 0 and 4)
    c0, c4 = data.cameras[0], data.cameras[4]
    rows, cols = np.nonzero(d0 > 0)
    sel = slice(None, None, 37)
    rows, cols, z = rows[sel], cols[sel], d0[rows[sel], cols[sel]]
    pc = np.stack([(cols + 0.5 - 320) / 525 * z, (rows + 0.5 - 240) / 525 * z, z], 1)
    Xw = (pc - c0.world_to_camera[:3, 3]) @ c0.world_to_camera[:3, :3]
    uv, z4 = project(c4, Xw)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480) & (z4 > 0)
    d4 = data.load_depth(4)[uv[ok, 1].astype(int), uv[ok, 0].astype(int)]
    valid = d4 > 0
    diff_m = np.abs(d4[valid] - z4[ok][valid]) / data.scale
    assert valid.sum() > 1000 and np.median(diff_m) < 0.012
    # the points are back-projected depth: they lie on frame 0's depth surface where frame 0 sees them
    uvp, zp = project(c0, data.points.astype(np.float64))
    okp = (uvp[:, 0] >= 0) & (uvp[:, 0] < 640) & (uvp[:, 1] >= 0) & (uvp[:, 1] < 480) & (zp > 0)
    dp = d0[uvp[okp, 1].astype(int), uvp[okp, 0].astype(int)]
    assert np.median(np.abs(dp[dp > 0] - zp[okp][dp > 0])) / data.scale < 0.02


def test_rgbd_depth_scale_and_downscale(cache):
    root = shared_data("icl_rgbd")
    a = load_dataset(root, cache_dir=cache, depth_scale=0.002, downscale=2)
    assert a.options["depth_scale"] == 0.002 and a.cameras[1].depth_scale == 0.002
    d = a.load_depth(1)
    assert d.shape == (240, 320)
    raw = np.asarray(Image.open(root / "depth" / "00001.png")).astype(np.float64)
    blocks = raw.reshape(240, 2, 320, 2).transpose(0, 2, 1, 3).reshape(240, 320, 4)
    i, j = 100, 150
    vals = blocks[i, j][blocks[i, j] > 0]
    np.testing.assert_allclose(d[i, j], np.median(vals) * 0.002 * a.scale, rtol=1e-3)


def test_memory_budget_bounds_the_image_cache(cache):
    data = load_dataset(shared_data("icl_rgbd"), cache_dir=cache, memory_budget_mb=640 * 480 * 3 * 4 * 2.5 / 2**20)
    first = data.load_image(0).copy()
    for i in range(5):
        data.load_image(i)
    assert len(data.image_loader) == 2 and data.image_loader.nbytes <= data.image_loader.budget_bytes
    np.testing.assert_array_equal(data.load_image(0), first)  # evicted, then decoded again
    assert not data.load_image(0).flags.writeable
