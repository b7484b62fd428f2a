"""SE(3) maths, TUM trajectories, ATE, and the tracking pose gradient against finite differences."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from trisplat.slam.se3 import ate_rmse, exp_se3, read_tum_trajectory, write_tum_trajectory
from trisplat.slam.track import TrackConfig, pose_loss, track_frame


def _twist_matrix(xi):
    v, w = xi[:3], xi[3:]
    M = torch.zeros(4, 4, dtype=torch.float64)
    M[:3, :3] = torch.tensor([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]], dtype=torch.float64)
    M[:3, 3] = v
    return M


@pytest.mark.parametrize("scale", [0.0, 1e-7, 0.3, 2.5])
def test_exp_se3_matches_matrix_exponential(scale):
    rng = np.random.default_rng(1)
    xi = torch.tensor(rng.normal(size=6) * scale, dtype=torch.float64)
    np.testing.assert_allclose(exp_se3(xi).numpy(), torch.linalg.matrix_exp(_twist_matrix(xi)).numpy(), atol=1e-12)


def test_exp_se3_gradient_at_zero_is_finite_and_exact():
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    p = torch.tensor([0.3, -0.2, 1.5], dtype=torch.float64)
    (exp_se3(xi)[:3, :3] @ p + exp_se3(xi)[:3, 3]).sum().backward()
    # d/dxi of sum(R p + t) at 0: translation -> (1,1,1); rotation w -> sum(w x p) = w . (p x (1,1,1))
    np.testing.assert_allclose(xi.grad.numpy(), [1, 1, 1, *np.cross(p.numpy(), np.ones(3))], atol=1e-12)


def test_tum_trajectory_roundtrip_and_ate(tmp_path):
    rng = np.random.default_rng(0)
    poses = []
    for _ in range(20):
        T = exp_se3(torch.tensor(rng.normal(size=6) * 0.5, dtype=torch.float64)).numpy()
        poses.append(T)
    poses = np.array(poses)
    write_tum_trajectory(tmp_path / "t.txt", np.arange(20) * 0.1, poses)
    stamps, back = read_tum_trajectory(tmp_path / "t.txt")
    np.testing.assert_allclose(stamps, np.arange(20) * 0.1)
    np.testing.assert_allclose(back, poses, atol=1e-8)
    G = exp_se3(torch.tensor([1.0, -2.0, 0.5, 0.3, -0.2, 1.0], dtype=torch.float64)).numpy()
    moved = G @ poses  # same trajectory in another world frame: ATE 0 after alignment
    assert ate_rmse(moved, poses)[0] < 1e-9
    noisy = poses.copy()
    noisy[:, :3, 3] += rng.normal(size=(20, 3)) * 0.01
    rmse = ate_rmse(noisy, poses)[0]
    assert 0.005 < rmse < 0.02  # ~0.01 * sqrt(3) per frame, a little less after the alignment absorbs some


def _plane_scene(n=14, z=2.0, half=1.2):
    """A textured wall of n x n quads facing the camera at depth z, bumped in depth so every pose is observable."""
    xs = np.linspace(-half, half, n + 1)
    X, Y = np.meshgrid(xs, xs * 0.8)
    Z = z + 0.25 * np.sin(2.5 * X) * np.cos(2.0 * Y)
    P = np.stack([X, Y, Z], -1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    cols = np.stack([0.5 + 0.4 * np.sin(5 * P[:, 0]), 0.5 + 0.4 * np.cos(4 * P[:, 1]), 0.5 + 0.2 * np.sin(3 * P[:, 2])], 1)
    return (torch.tensor(P, dtype=torch.float32), torch.tensor(faces, dtype=torch.int32),
            torch.tensor(cols, dtype=torch.float32), torch.full((len(P),), 0.999))


def _soup(seed=0):
    """Four separated textured triangles in front of the camera, inside a 64x48 view."""
    rng = np.random.default_rng(seed)
    cent = np.array([[-0.5, -0.3, 2.0], [0.4, 0.2, 2.3], [0.0, 0.35, 1.8], [0.5, -0.35, 2.1]])
    tris = []
    for c in cent:
        a = rng.uniform(0, 2 * np.pi)
        tris.append(np.array([[0.3 * np.cos(a + 2.094 * k), 0.3 * np.sin(a + 2.094 * k), 0.1 * np.sin(a + k)]
                              for k in range(3)]) + c)
    pos = torch.tensor(np.concatenate(tris))
    return pos, torch.arange(12, dtype=torch.int32).reshape(4, 3), torch.tensor(rng.uniform(0.2, 0.9, (12, 3))), \
        torch.full((12,), 0.9, dtype=torch.float64)


@pytest.mark.parametrize("term", ["photometric", "depth"])
def test_pose_gradient_matches_finite_differences(term):
    """d loss / d xi by autograd through exp_se3 and the renderer vs central differences of the same loss.

    The dense reference renderer in float64 (the numba kernels compute the same, tested in tests/render), window
    sigma 1, no alpha_min cut, separated triangles (no depth-order swaps): the loss is smooth in the pose there.
    The depth term only sees pixels well inside the triangles, so its pixel set does not change under the step."""
    pos, faces, cols, op = _soup()
    W, H = 64, 48
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]], dtype=torch.float64)
    opts = dict(backend="reference", alpha_min=0.0)
    xi0 = torch.tensor([0.01, -0.02, 0.03, 0.01, 0.02, -0.01], dtype=torch.float64)
    T0 = exp_se3(xi0)
    from trisplat.render.rasterize import rasterize

    ref = rasterize(pos @ T0[:3, :3].T + T0[:3, 3], faces, cols, op, 1.0, torch.eye(4, dtype=torch.float64), K, W,
                    H, opacity_mode="mean", **opts)
    if term == "photometric":  # black target = the background: continuous where alpha reaches 0
        rgb, depth = torch.zeros(H, W, 3, dtype=torch.float64), torch.zeros(H, W, dtype=torch.float64)
        cfg = TrackConfig(min_alpha=-1.0, w_depth=0.0, w_color=1.0, lambda_dssim=0.2, outlier_depth=100.0)
        depth = torch.full((H, W), 3.0, dtype=torch.float64)  # valid everywhere; w_depth 0 ignores its value
    else:
        rgb = torch.zeros(H, W, 3, dtype=torch.float64)
        depth = torch.where(ref.alpha > 0.3, torch.tensor(3.0, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64))
        cfg = TrackConfig(min_alpha=0.05, w_depth=1.0, w_color=0.0, outlier_depth=100.0)
    assert int((depth > 0).sum()) > 40

    def loss_at(xi):
        T = exp_se3(xi)
        return pose_loss(pos @ T[:3, :3].T + T[:3, 3], faces, cols, op, 1.0, rgb, depth, K, cfg, **opts)[0]

    xi = xi0.clone().requires_grad_(True)
    loss_at(xi).backward()
    g = xi.grad.numpy()
    fd = np.zeros(6)
    h = 1e-5
    for k in range(6):
        e = torch.zeros(6, dtype=torch.float64)
        e[k] = h
        fd[k] = (float(loss_at(xi0 + e)) - float(loss_at(xi0 - e))) / (2 * h)
    assert (np.abs(g) > 1e-3).sum() >= 5  # the pose moves the loss (depth barely sees the roll about z)
    np.testing.assert_allclose(g, fd, rtol=0.03, atol=0.01 * np.abs(fd).max())


def test_track_frame_recovers_a_perturbed_pose():
    pos, faces, cols, op = _plane_scene()
    W, H = 128, 96
    K = np.array([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]])
    true_w2c = exp_se3(torch.tensor([0.03, -0.02, 0.04, 0.02, -0.015, 0.01], dtype=torch.float64)).numpy()
    from trisplat.render.rasterize import rasterize

    with torch.no_grad():
        o = rasterize(pos, faces, cols, op, torch.tensor(0.05), torch.tensor(true_w2c), torch.tensor(K), W, H,
                      opacity_mode="mean", supersample=2)
    rgb, depth = o.rgb, torch.where(o.alpha > 0.5, o.depth / o.alpha.clamp_min(1e-6), torch.zeros_like(o.depth))
    cfg = TrackConfig(levels=(2, 1), max_iters=(80, 60), lr_translation=4e-3, lr_rotation=4e-3)
    from trisplat.slam.system import _pyramid

    r = track_frame(pos, faces, cols, op, 0.05, _pyramid(rgb.numpy(), depth.numpy(), K, cfg.levels), np.eye(4), cfg)
    err_t = np.linalg.norm(np.linalg.inv(r.w2c)[:3, 3] - np.linalg.inv(true_w2c)[:3, 3])
    start_t = np.linalg.norm(np.linalg.inv(true_w2c)[:3, 3])
    assert start_t > 0.04 and err_t < 0.004, (start_t, err_t, r.iterations)
    assert r.iterations < 140  # the convergence test stopped it before the caps


def test_rpe_per_second_measures_a_known_drift():
    """A camera moving 1 m/s along x for 3 s at 30 fps; the estimate moves 1.1 m/s and turns 2 degrees/s more:
    RPE over 1 s is 0.1 m/s in translation and 2 deg/s in rotation (up to the lever of the turn)."""
    from scipy.spatial.transform import Rotation

    from trisplat.slam.trajectory import rpe_per_second

    t = np.arange(91) / 30.0
    ref, est = [], []
    for s in t:
        Q = np.eye(4)
        Q[0, 3] = s
        ref.append(Q)
        P = np.eye(4)
        P[0, 3] = 1.1 * s
        P[:3, :3] = Rotation.from_euler("z", 2.0 * s, degrees=True).as_matrix()
        est.append(P)
    r = rpe_per_second(np.array(est), np.array(ref), t)
    assert r["pairs"] == 61 and r["delta_s"] == pytest.approx(1.0)
    assert r["rotation_deg_per_s"] == pytest.approx(2.0, rel=1e-6)
    assert r["translation_m_per_s"] == pytest.approx(0.1, abs=0.02)
    assert rpe_per_second(np.array(est[:10]), np.array(ref[:10]), t[:10]) is None  # 0.3 s: no 1 s pair


def test_dense_tracker_jacobian_matches_finite_differences():
    """The closed-form d r / d xi of the dense tracker's depth and photometric residuals (left perturbation, ALGORITHM.md
    section 5) against central differences of the same residuals on a smooth synthetic observation."""
    from trisplat.slam.track import _make_level, _residuals

    H, W = 60, 80
    K = np.array([[70.0, 0, 40.0], [0, 70.0, 30.0], [0, 0, 1]])
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    depth = 2.0 + 0.1 * np.sin(u / 20) + 0.1 * np.cos(v / 15)
    grey = 0.5 + 0.3 * np.sin(u / 10) * np.cos(v / 13)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    cfg = TrackConfig(outlier_depth=1.0)
    L = _make_level(rgb, depth, np.ones((H, W), bool), rgb, depth, K, cfg)
    T = exp_se3(torch.tensor([0.01, -0.005, 0.008, 0.004, -0.003, 0.002], dtype=torch.float64)).numpy()
    o = _residuals(L, T, cfg)
    assert o["n"] > 2000 and o["JI"] is not None
    h = 1e-6
    for k in range(6):
        e = torch.zeros(6, dtype=torch.float64)
        e[k] = h
        op = _residuals(L, exp_se3(e).numpy() @ T, cfg)
        om = _residuals(L, exp_se3(-e).numpy() @ T, cfg)
        if not (op["n"] == om["n"] == o["n"]):
            continue  # a point crossed the border: the sets differ (rare at this step)
        for key, J in (("rD", o["JD"]), ("rI", o["JI"])):
            fd = (op[key] - om[key]) / (2 * h)
            # central image gradients vs the bilinear patch's slope: equal up to the smooth images' curvature
            err = np.median(np.abs(J[:, k] - fd)) / max(np.median(np.abs(fd)), 1e-9)
            assert err < 0.05, (key, k, err)


def test_dense_tracker_normal_equations_kernel_matches_the_numpy_reference():
    """track_kernels.normal_equations (one Numba pass) against _normal_equations_reference (numpy, from _residuals):
    the same points kept, robust cost, J^T W J and J^T W r, with the photometric term and without, with outliers,
    depth edges and points leaving the image."""
    from trisplat.slam.track import _make_level, _normal_equations, _normal_equations_reference

    rng = np.random.default_rng(0)
    H, W = 60, 80
    K = np.array([[70.0, 0, 40.0], [0, 70.0, 30.0], [0, 0, 1]])
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    depth = 2.0 + 0.1 * np.sin(u / 20) + 0.1 * np.cos(v / 15)
    depth[20:30, 50:60] += 0.5  # a box in front: depth edges
    depth[rng.random((H, W)) < 0.02] = 0.0  # missing depth
    grey = 0.5 + 0.3 * np.sin(u / 10) * np.cos(v / 13) + 0.05 * rng.standard_normal((H, W))
    obs_depth = depth + 0.02 * rng.standard_normal((H, W)) * (depth > 0)  # residuals on both sides of Huber's k
    rgb = np.repeat(grey[..., None], 3, axis=2)
    for photo_flat, z2, mode in ((False, 0.0, "projective"), (True, 0.0, "projective"), (False, 1.0, "projective"),
                                 (True, 0.5, "projective"), (False, 0.0, "point_to_plane"),
                                 (True, 1.0, "point_to_plane")):
        obs_rgb = np.full_like(rgb, 0.4) if photo_flat else rgb[:, ::-1] * 0.9 + 0.05
        cfg = TrackConfig(outlier_depth=0.05, depth_noise=z2, depth_residual=mode)
        L = _make_level(rgb, depth, depth > 0, obs_rgb, obs_depth, K, cfg)
        assert L.photo is not photo_flat
        T = exp_se3(torch.tensor([0.03, -0.02, 0.01, 0.02, -0.01, 0.015], dtype=torch.float64)).numpy()
        for w_photo in (1.0, 0.3):
            c_ref, n_ref, H_ref, g_ref = _normal_equations_reference(L, T, cfg, w_photo)
            c, n, Hk, gk = _normal_equations(L, T, cfg, w_photo)
            assert 500 < n == n_ref < len(L.X)  # some points dropped (outliers, edges, outside), most kept
            assert c == pytest.approx(c_ref, rel=1e-9)
            np.testing.assert_allclose(Hk, H_ref, rtol=1e-9, atol=1e-9 * np.abs(H_ref).max())
            np.testing.assert_allclose(gk, g_ref, rtol=1e-9, atol=1e-9 * np.abs(g_ref).max())
            if z2 or mode != "projective":  # not the default's equations (z2: the points at ~2 m)
                L0 = _make_level(rgb, depth, depth > 0, obs_rgb, obs_depth, K, TrackConfig(outlier_depth=0.05))
                c0, _, H0, _ = _normal_equations(L0, T, TrackConfig(outlier_depth=0.05), w_photo)
                assert abs(c - c0) > 0.05 * c0 and not np.allclose(Hk, H0, rtol=0.05)


def test_depth_normals_of_a_tilted_plane():
    from trisplat.slam.track import _edges, depth_normals

    H, W = 40, 50
    K = np.array([[60.0, 0, 25.0], [0, 60.0, 20.0], [0, 0, 1]])
    n_true = np.array([0.3, -0.2, -1.0])
    n_true /= np.linalg.norm(n_true)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    ray = np.stack([(u + 0.5 - 25.0) / 60.0, (v + 0.5 - 20.0) / 60.0, np.ones_like(u)], -1)
    depth = -2.0 / (ray @ n_true)  # the plane n . P = 2 (facing the camera: n . P < 0 means n_true points back)
    depth[10, 10] = 0.0  # a hole: its 4 neighbours are depth edges, so no normal within 2 steps of it
    n = depth_normals(depth, _edges(depth, 0.05), K)
    inner = np.zeros((H, W), bool)
    inner[1:-1, 1:-1] = True
    inner &= np.abs(v - 10) + np.abs(u - 10) > 2
    np.testing.assert_allclose(n[inner], np.broadcast_to(n_true, n[inner].shape), atol=1e-9)
    assert not n[~inner].any()


def test_point_to_plane_residual_is_the_distance_to_the_observed_plane():
    """A map of a wall seen at a slant, moved 1 cm off the wall along its normal: the point-to-plane residual is
    that 1 cm at every pixel; the projective depth residual, along the camera's axis, is larger the more the view
    grazes the wall (here about 2x)."""
    from trisplat.slam.track import _make_level, _residuals

    H, W = 40, 50
    K = np.array([[60.0, 0, 25.0], [0, 60.0, 20.0], [0, 0, 1]])
    n = np.array([np.sin(np.radians(60)), 0.0, -np.cos(np.radians(60))])  # the wall turned 60 degrees
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    ray = np.stack([(u + 0.5 - 25.0) / 60.0, (v + 0.5 - 20.0) / 60.0, np.ones_like(u)], -1)
    depth = -2.0 / (ray @ n)
    rgb = np.repeat((0.5 + 0.2 * np.sin(u / 5))[..., None], 3, axis=2)
    T = np.eye(4)
    T[:3, 3] = -0.01 * n  # 1 cm towards the camera, off the observed plane
    out = {}
    for mode in ("projective", "point_to_plane"):
        cfg = TrackConfig(depth_residual=mode)
        L = _make_level(rgb, depth, depth > 0, rgb, depth, K, cfg)
        out[mode] = np.abs(_residuals(L, T, cfg)["rD"])
    assert len(out["point_to_plane"]) > 0.7 * len(out["projective"]) > 500
    np.testing.assert_allclose(out["point_to_plane"], 0.01, rtol=0.05)  # (bilinear depth of a slanted plane)
    assert np.median(out["projective"]) > 1.5 * 0.01
    # on a plane the observed point slides along the plane as the map point moves, so the Jacobian that holds the
    # correspondence is the residual's derivative: central differences of exp(xi) T
    cfg = TrackConfig(depth_residual="point_to_plane")
    L = _make_level(rgb, depth, depth > 0, rgb, depth, K, cfg)
    o = _residuals(L, T, cfg)
    for k in range(6):
        e = np.zeros(6)
        e[k] = 1e-5
        rp = _residuals(L, exp_se3(torch.as_tensor(e)).numpy() @ T, cfg)
        rm = _residuals(L, exp_se3(torch.as_tensor(-e)).numpy() @ T, cfg)
        assert rp["n"] == rm["n"] == o["n"]
        tol = 0.05 * np.abs(o["JD"]).max()  # (the bilinear depth of a slanted plane: ~3%)
        np.testing.assert_allclose((rp["rD"] - rm["rD"]) / 2e-5, o["JD"][:, k], atol=tol)


def test_depth_scale_follows_the_sensor_noise_model():
    from trisplat.slam.track import depth_scale

    z = np.array([0.5, 1.0, 2.0, 3.0])
    np.testing.assert_allclose(depth_scale(z, TrackConfig(depth_sigma=0.01)), 0.01)
    kinect = (0.0012 + 0.0019 * (z - 0.4) ** 2) / (0.0012 + 0.0019 * 0.36)  # 1 at 1 m
    np.testing.assert_allclose(depth_scale(z, TrackConfig(depth_sigma=0.01, depth_noise=1.0)), 0.01 * kinect)
    np.testing.assert_allclose(depth_scale(z, TrackConfig(depth_sigma=0.01, depth_noise=0.5)),
                               0.01 * (0.5 + 0.5 * kinect))
    assert kinect[2] == pytest.approx(3.22, abs=0.01) and kinect[3] == pytest.approx(7.45, abs=0.01)


def test_dense_tracker_coverage_kernel_matches_the_numpy_reference():
    """track_kernels.coverage (one Numba pass) against _coverage_reference (numpy): the share of valid observed pixels
    landed on and the mean depth residual of the landings, with points landing twice on a pixel, behind the camera,
    outside the image, on missing depth and beyond the outlier distance; none landing gives (0, 0)."""
    from trisplat.slam.track import _coverage, _coverage_reference, _make_level

    rng = np.random.default_rng(1)
    H, W = 60, 80
    K = np.array([[70.0, 0, 40.0], [0, 70.0, 30.0], [0, 0, 1]])
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    depth = 2.0 + 0.2 * np.sin(u / 9) + 0.1 * np.cos(v / 7)
    obs = depth + 0.03 * rng.standard_normal((H, W))
    obs[rng.random((H, W)) < 0.1] = 0.0
    rgb = np.full((H, W, 3), 0.5)
    L = _make_level(rgb, depth, depth > 0, rgb, obs, K, TrackConfig())
    L.Xall = np.concatenate([L.Xall, L.Xall[:50] * 1.001, [[0.0, 0.0, -1.0]]])  # doubles and a point behind
    for xi in ([0.0] * 6, [0.05, -0.02, 0.01, 0.02, -0.03, 0.01], [0.5, 0, 0, 0, 0, 0]):
        T = exp_se3(torch.tensor(xi, dtype=torch.float64)).numpy()
        for outlier in (0.05, 0.1):
            ref = _coverage_reference(L, T, outlier)
            got = _coverage(L, T, outlier)
            assert 0.0 < ref[0] < 1.0 and ref[1] > 0
            assert got[0] == pytest.approx(ref[0], rel=1e-12) and got[1] == pytest.approx(ref[1], rel=1e-9)
    far = exp_se3(torch.tensor([0.0, 0.0, -5.0, 0, 0, 0], dtype=torch.float64)).numpy()  # everything behind
    assert _coverage(L, far, 0.1) == _coverage_reference(L, far, 0.1) == (0.0, 0.0)


def test_ate_summary_skips_frames_without_reference_and_needs_three():
    from trisplat.slam.trajectory import ate_summary

    rng = np.random.default_rng(3)
    ref = [np.eye(4) for _ in range(6)]
    for k, T in enumerate(ref):
        T[:3, 3] = [0.1 * k, 0.02 * k * k, 0.0]
    est = [T.copy() for T in ref]
    # a rigid motion of the whole estimate is aligned away; 1 cm of error on one frame is what remains
    c, s = np.cos(0.3), np.sin(0.3)
    M = np.array([[c, -s, 0, 1.0], [s, c, 0, -2.0], [0, 0, 1, 0.5], [0, 0, 0, 1]])
    est = [M @ T for T in est]
    est[2][:3, 3] += M[:3, :3] @ np.array([0.0, 0.0, 0.01])
    est[4][:3, 3] += rng.normal(size=3)  # a wild pose whose frame has no reference: left out
    refs = [T if k != 4 else None for k, T in enumerate(ref)]
    a = ate_summary(est, refs)
    assert a["frames"] == 5
    assert 0.003 < a["rmse_m"] < 0.01 and 0.005 < a["max_m"] <= 0.0101
    assert ate_summary(est, [ref[0], None, ref[2], None, None, None]) is None
