"""Known answers (both backends) and finite differences of the dense reference renderer (float64)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from render_scenes import camera, mesh_scene, random_scene, unproject

from trisplat.render import rasterize
from trisplat.scene.sh import rgb_to_sh_dc

FD_STEP = 1e-8  # central finite-difference step (scene units / colour units); small, to cross no kink
FD_RTOL = 1e-4  # relative agreement of directional derivatives
BACKENDS = ["reference", "numba"]
ABS_TOL = {"reference": 1e-9, "numba": 2e-5}  # known-answer tolerance: float64 reference, float32 kernels


def screen_triangle(uv, z=2.0, width=40, height=32, dtype=torch.float64):
    """positions [3,3] of a triangle with the given screen vertices uv [3,2] at constant view depth z."""
    _, K = camera(width, height, dtype)
    return torch.tensor(unproject(np.asarray(uv, float), np.full(3, z), K.numpy()), dtype=dtype)


def cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def incentre(uv):
    uv = np.asarray(uv, float)
    opp = np.array([np.linalg.norm(uv[1] - uv[2]), np.linalg.norm(uv[2] - uv[0]), np.linalg.norm(uv[0] - uv[1])])
    return (opp[:, None] * uv).sum(0) / opp.sum()


def render_one(uv, sigma, opacity=1.0, backend="reference", **opts):
    w2c, K = camera()
    pos = screen_triangle(uv)
    faces = torch.tensor([[0, 1, 2]], dtype=torch.int32)
    col = torch.tensor([[1.0, 0.2, 0.1]] * 3, dtype=torch.float64)
    op = torch.full((3,), opacity, dtype=torch.float64)
    return rasterize(pos, faces, col, op, sigma, w2c, K, 40, 32, backend=backend, **opts)


@pytest.mark.parametrize("backend", BACKENDS)
def test_window_is_one_at_incentre_and_zero_outside(backend):
    # An isosceles triangle whose incentre falls exactly on the pixel centre (20.5, 16.5).
    base = np.array([[10.5, 24.5], [30.5, 24.5], [20.5, 4.5]])
    shift = np.array([20.5, 16.5]) - incentre(base)
    uv = base + shift
    for sigma in (0.3, 1.0, 2.0):
        out = render_one(uv, sigma, alpha_max=1.0, backend=backend)
        assert out.alpha[16, 20].item() == pytest.approx(1.0, abs=ABS_TOL[backend])
        assert out.alpha.max().item() == pytest.approx(1.0, abs=ABS_TOL[backend])
        xs, ys = np.meshgrid(np.arange(40) + 0.5, np.arange(32) + 0.5)
        p = np.stack([xs, ys], -1)
        e = [cross2(uv[(k + 1) % 3] - uv[k], p - uv[k]) for k in range(3)]
        outside = (np.stack(e) < 0).any(0) & (np.stack(e) > 0).any(0)
        assert outside.sum() > 500
        assert (out.alpha.numpy()[outside] == 0).all()
        assert (out.rgb.numpy()[outside] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_window_falls_towards_edges_as_power_sigma(backend):
    uv = np.array([[10.5, 24.5], [30.5, 24.5], [20.5, 4.5]])
    s = incentre(uv)
    # Point halfway from the incentre to the base edge midpoint: phi(p)/phi(s) = 1/2 (the base is the nearest edge).
    mid = (uv[0] + uv[1]) / 2
    p = (s + mid) / 2
    shift = np.array([20.5, 16.5]) - p
    for sigma in (0.5, 1.0, 3.0):
        out = render_one(uv + shift, sigma, opacity=0.8, backend=backend)
        assert out.alpha[16, 20].item() == pytest.approx(0.8 * 0.5 ** sigma, abs=ABS_TOL[backend])


@pytest.mark.parametrize("backend", BACKENDS)
def test_covered_area_tends_to_geometric_area(backend):
    uv = np.array([[3.3, 2.1], [36.7, 9.4], [12.2, 29.8]])
    area = 0.5 * abs(cross2(uv[1] - uv[0], uv[2] - uv[0]))
    xs, ys = np.meshgrid(np.arange(40) + 0.5, np.arange(32) + 0.5)
    p = np.stack([xs, ys], -1)
    e = np.stack([cross2(uv[(k + 1) % 3] - uv[k], p - uv[k]) for k in range(3)])
    inside = int(((e > 0).all(0) | (e < 0).all(0)).sum())
    sums = [render_one(uv, s, alpha_max=1.0, alpha_min=0.0, backend=backend).alpha.sum().item()
            for s in (1.0, 0.1, 1e-4)]
    assert sums[0] < sums[1] < sums[2]
    assert sums[2] == pytest.approx(inside, rel=1e-3)
    assert sums[2] == pytest.approx(area, rel=0.03)


@pytest.mark.parametrize("backend", BACKENDS)
def test_two_layers_composite_front_to_back(backend):
    w2c, K = camera()
    big = np.array([[-50.0, -50.0], [120.0, -40.0], [20.0, 120.0]])
    pos = torch.cat([screen_triangle(big, z=2.0), screen_triangle(big, z=3.0)])
    faces = torch.tensor([[3, 4, 5], [0, 1, 2]], dtype=torch.int32)  # back face listed first
    c1, c2, bg = np.array([0.9, 0.1, 0.2]), np.array([0.1, 0.7, 0.3]), np.array([0.2, 0.2, 0.9])
    col = torch.tensor(np.array([c1] * 3 + [c2] * 3))
    op = torch.tensor([0.6] * 3 + [0.5] * 3, dtype=torch.float64)
    out = rasterize(pos, faces, col, op, 1e-9, w2c, K, 40, 32, background=torch.tensor(bg), backend=backend)
    expect = 0.6 * c1 + 0.4 * 0.5 * c2 + 0.4 * 0.5 * bg
    tol = max(1e-6, ABS_TOL[backend])
    np.testing.assert_allclose(out.rgb[10, 10].numpy(), expect, atol=tol)
    assert out.alpha[10, 10].item() == pytest.approx(1 - 0.4 * 0.5, abs=tol)
    assert out.depth[10, 10].item() == pytest.approx(0.6 * 2.0 + 0.2 * 3.0, abs=tol)
    assert out.face_id[10, 10].item() == 1  # the front face (index 1) passes 0.5 accumulated weight
    np.testing.assert_allclose(out.normal[10, 10].numpy(), [0, 0, -0.8], atol=tol)
    np.testing.assert_allclose(out.max_weight.numpy(), [0.2, 0.6], atol=tol)


@pytest.mark.parametrize("backend", BACKENDS)
def test_alpha_cap_and_early_stop(backend):
    w2c, K = camera()
    big = np.array([[-50.0, -50.0], [120.0, -40.0], [20.0, 120.0]])
    pos = torch.cat([screen_triangle(big, z=2.0 + i) for i in range(4)])
    faces = torch.arange(12, dtype=torch.int32).reshape(4, 3)
    cols = [np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]), np.array([1.0, 1.0, 1.0])]
    col = torch.tensor(np.repeat(np.array(cols), 3, axis=0))
    op = torch.ones(12, dtype=torch.float64)
    out = rasterize(pos, faces, col, op, 1e-9, w2c, K, 40, 32, backend=backend, alpha_max=0.999)
    # T after two faces is 1e-6 < 1e-4: the third and fourth faces are not composited.
    tol = ABS_TOL[backend]
    np.testing.assert_allclose(out.rgb[5, 5].numpy(), [0.999, 0.999 * 1e-3, 0.0], atol=max(1e-7, tol))
    assert out.alpha[5, 5].item() == pytest.approx(1 - 1e-6, abs=tol)
    out = rasterize(pos, faces, col, op, 1e-9, w2c, K, 40, 32, backend=backend)  # default cap 0.99
    # (T = 0.01^2 before the third face sits exactly on the 1e-4 stop: float32 may stop one face earlier.)
    np.testing.assert_allclose(out.max_weight.numpy()[[0, 1, 3]], [0.99, 0.0099, 0.0], atol=tol)


def _loss_weights(out, seed):
    g = torch.Generator().manual_seed(seed)
    return [torch.rand(t.shape, generator=g, dtype=t.dtype) - 0.3 for t in (out.rgb, out.alpha, out.depth, out.normal)]


def _loss(out, wts):
    return sum((t * w).sum() for t, w in zip((out.rgb, out.alpha, out.depth, out.normal), wts))


@pytest.mark.parametrize("seed,kind,opts", [
    (0, "soup", {}), (1, "soup", {"perspective_correct": True}), (2, "mesh", {}),
    (3, "mesh", {"opacity_mode": "mean"}), (4, "soup", {"supersample": 2}),
])
def test_reference_gradients_match_finite_differences(seed, kind, opts):
    pos, faces, col, op, w2c, K = random_scene(seed, 10) if kind == "soup" else mesh_scene(seed)
    sigma = 0.7
    params = [pos.clone().requires_grad_(), col.clone().requires_grad_(), op.clone().requires_grad_()]

    def f(p, c, o):
        return rasterize(p, faces, c, o, sigma, w2c, K, 40, 32, backend="reference", **opts)

    out = f(*params)
    wts = _loss_weights(out, seed)
    _loss(out, wts).backward()
    rng = np.random.default_rng(seed)
    with torch.no_grad():
        for i, prm in enumerate(params):
            for _ in range(2):
                v = torch.tensor(rng.normal(size=prm.shape))
                if i == 2:  # stay inside [0, 1]
                    v = v * 0.1
                args_p = [q.detach().clone() for q in params]
                args_m = [q.detach().clone() for q in params]
                args_p[i] += FD_STEP * v
                args_m[i] -= FD_STEP * v
                fd = (_loss(f(*args_p), wts) - _loss(f(*args_m), wts)).item() / (2 * FD_STEP)
                an = (prm.grad * v).sum().item()
                assert an == pytest.approx(fd, rel=FD_RTOL, abs=1e-4), f"param {i}"


def test_sh_degree0_equals_rgb_and_gradients_reach_sh():
    pos, faces, col, op, w2c, K = random_scene(5, 12)
    ref = rasterize(pos, faces, col, op, 0.5, w2c, K, 40, 32, backend="reference")
    sh = rgb_to_sh_dc(col)[:, None, :].clone().requires_grad_()
    out = rasterize(pos, faces, sh, op, 0.5, w2c, K, 40, 32, backend="reference")
    torch.testing.assert_close(out.rgb, ref.rgb, atol=1e-12, rtol=0)
    sh3 = torch.zeros(sh.shape[0], 16, 3, dtype=sh.dtype)
    sh3[:, :1] = sh.detach()
    out3 = rasterize(pos, faces, sh3, op, 0.5, w2c, K, 40, 32, backend="reference")
    torch.testing.assert_close(out3.rgb, ref.rgb, atol=1e-12, rtol=0)
    out.rgb.sum().backward()
    assert sh.grad.abs().sum() > 0


def test_face_order_does_not_change_the_image():
    pos, faces, col, op, w2c, K = random_scene(6, 20)
    a = rasterize(pos, faces, col, op, 0.5, w2c, K, 40, 32, backend="reference")
    perm = torch.randperm(faces.shape[0], generator=torch.Generator().manual_seed(0))
    b = rasterize(pos, faces[perm], col, op, 0.5, w2c, K, 40, 32, backend="reference")
    torch.testing.assert_close(a.rgb, b.rgb, atol=1e-12, rtol=0)
    torch.testing.assert_close(a.max_weight[perm], b.max_weight, atol=1e-12, rtol=0)
    fa = a.face_id.clone()
    inv = torch.argsort(perm)
    fb = torch.where(b.face_id >= 0, perm[b.face_id.clamp(min=0)], b.face_id)
    assert torch.equal(fa, fb)
    del inv


@pytest.mark.parametrize("kw,msg", [
    ({"positions": np.zeros((3, 2))}, "positions must be"),
    ({"positions": np.array([[0.0, 0, 1], [np.nan, 0, 1], [0, 1, 1]])}, "NaN or Inf"),
    ({"faces": np.array([[0, 1, 3]])}, "face indices must lie in"),
    ({"faces": np.array([[0.0, 1, 2]])}, "integer"),
    ({"width": 0}, "empty or absurd"),
    ({"height": 100000}, "empty or absurd"),
    ({"sigma": 0.0}, "sigma must be"),
    ({"colors": np.zeros((3, 5, 3))}, "colors must be"),
    ({"opacities": np.full(3, 1.5)}, "opacities must lie"),
    ({"K": np.eye(4)}, "K must be"),
    ({"world_to_camera": np.eye(3)}, "world_to_camera must be"),
])
def test_bad_inputs_get_precise_errors(kw, msg):
    args = dict(positions=np.array([[0.0, 0, 1], [1, 0, 1], [0, 1, 1]]), faces=np.array([[0, 1, 2]], np.int32),
                colors=np.ones((3, 3)), opacities=np.ones(3), sigma=1.0, world_to_camera=np.eye(4),
                K=np.array([[10.0, 0, 5], [0, 10, 5], [0, 0, 1]]), width=10, height=10)
    args.update(kw)
    with pytest.raises(ValueError, match=msg):
        rasterize(**args, backend="reference")


def test_unknown_option_is_refused():
    with pytest.raises(ValueError, match="unknown rasterize option"):
        rasterize(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.ones((3, 3)), np.ones(3), 1.0, np.eye(4), np.eye(3),
                  4, 4, supersampling=2)
