"""The hard z-buffer renderer: brute-force nearest-face oracle, and the limit of the soft render."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from render_scenes import mesh_scene, random_scene

from trisplat.render import rasterize, rasterize_hard

BOUNDARY_FRACTION = 0.02  # pixels whose centre lies within rounding of an edge may pick either face


def brute_force(pos, faces, col, w2c, K, W, H):
    """Nearest face per pixel centre by testing every face (numpy, float64), screen-space colour interpolation."""
    cam = pos @ w2c[:3, :3].T + w2c[:3, 3]
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    best = np.full((H, W), np.inf)
    fid = np.full((H, W), -1)
    rgb = np.zeros((H, W, 3))
    for f, (i, j, k) in enumerate(faces):
        tri = cam[[i, j, k]]
        if (tri[:, 2] < 0.01).any():
            continue
        uv = (tri @ K.T)[:, :2] / tri[:, 2:3]
        area2 = (uv[1, 0] - uv[0, 0]) * (uv[2, 1] - uv[0, 1]) - (uv[1, 1] - uv[0, 1]) * (uv[2, 0] - uv[0, 0])
        if area2 == 0:
            continue
        def sub(a, b):  # noqa: E306
            return ((a[0] - xs) * (b[1] - ys) - (a[1] - ys) * (b[0] - xs)) / area2  # noqa: B023 - called within the iteration
        b = np.stack([sub(uv[1], uv[2]), sub(uv[2], uv[0]), sub(uv[0], uv[1])])
        inside = (b >= 0).all(0)
        z = 1.0 / (b / tri[:, 2][:, None, None]).sum(0)
        win = inside & (z < best)
        best[win] = z[win]
        fid[win] = f
        c = np.einsum("kyx,kc->yxc", b, col[[i, j, k]])
        rgb[win] = c[win]
    best[fid < 0] = 0
    return fid, rgb, best


def test_hard_matches_brute_force_z_buffer():
    for seed in range(3):
        pos, faces, col, _, w2c, K = random_scene(seed, 40)
        out = rasterize_hard(pos, faces, col, w2c, K, 40, 32)
        fid, rgb, depth = brute_force(pos.numpy(), faces.numpy(), col.numpy(), w2c.numpy(), K.numpy(), 40, 32)
        same = out.face_id.numpy() == fid
        assert same.mean() >= 1 - BOUNDARY_FRACTION
        assert (fid >= 0).sum() > 300
        np.testing.assert_allclose(out.rgb.numpy()[same], rgb[same], atol=1e-4)
        np.testing.assert_allclose(out.depth.numpy()[same], depth[same], rtol=1e-4)
        assert torch.equal(out.alpha, (out.face_id >= 0).to(out.alpha.dtype))


def test_soft_render_tends_to_hard_render():
    pos, faces, col, op, w2c, K = mesh_scene(3)
    hard = rasterize_hard(pos, faces, col, w2c, K, 40, 32)
    ones = torch.ones_like(op)
    errs = []
    for sigma in (0.5, 0.05, 1e-6):
        soft = rasterize(pos, faces, col, ones, sigma, w2c, K, 40, 32, alpha_max=1 - 1e-6)
        diff = (soft.rgb - hard.rgb).abs().amax(-1)
        errs.append(diff.mean().item())
    assert errs[0] > errs[1] > errs[2]
    soft = rasterize(pos, faces, col, ones, 1e-6, w2c, K, 40, 32, alpha_max=1 - 1e-6)
    diff = (soft.rgb - hard.rgb).abs().amax(-1)
    assert (diff > 1e-3).float().mean().item() <= BOUNDARY_FRACTION
    assert (soft.face_id != hard.face_id).float().mean().item() <= BOUNDARY_FRACTION
    torch.testing.assert_close(soft.depth, hard.depth, atol=1e-3, rtol=0)
    np.testing.assert_allclose(soft.normal.numpy(), hard.normal.numpy(), atol=1e-3)


def test_hard_sh_degree0_and_batched():
    from trisplat.scene.sh import rgb_to_sh_dc

    pos, faces, col, _, w2c, K = random_scene(4, 20, kinds=False)
    a = rasterize_hard(pos, faces, col, w2c, K, 40, 32, background=torch.tensor([0.1, 0.2, 0.3]))
    b = rasterize_hard(pos, faces, rgb_to_sh_dc(col)[:, None], torch.stack([w2c, w2c]), K, 40, 32,
                       background=torch.tensor([0.1, 0.2, 0.3]))
    torch.testing.assert_close(b.rgb[1], a.rgb, atol=1e-5, rtol=0)
    assert torch.equal(b.face_id[0], a.face_id)
    assert (a.face_id < 0).sum() > 50
    np.testing.assert_allclose(a.rgb.numpy()[a.face_id.numpy() < 0], [[0.1, 0.2, 0.3]] * int((a.face_id < 0).sum()),
                               atol=1e-6)


def test_hard_deep_scene_matches_brute_force():
    """Thousands of overlapping faces (tens of layers per pixel): the slab order, the occlusion culling and its
    lazily refreshed block depths must never hide the nearest face; max_weight marks exactly the winners."""
    pos, faces, col, _, w2c, K = random_scene(11, 3000, 64, 48, kinds=False)
    out = rasterize_hard(pos, faces, col, w2c, K, 64, 48)
    fid, rgb, depth = brute_force(pos.numpy(), faces.numpy(), col.numpy(), w2c.numpy(), K.numpy(), 64, 48)
    same = out.face_id.numpy() == fid
    assert same.mean() >= 1 - BOUNDARY_FRACTION
    assert out.pairs_evaluated < 0.5 * (fid >= 0).sum() * 30  # culling skipped most of the ~30 layers
    np.testing.assert_allclose(out.rgb.numpy()[same], rgb[same], atol=1e-4)
    np.testing.assert_allclose(out.depth.numpy()[same], depth[same], rtol=1e-4)
    winners = np.zeros(faces.shape[0])
    winners[out.face_id.numpy()[out.face_id.numpy() >= 0]] = 1
    np.testing.assert_array_equal(out.max_weight.numpy(), winners)


def _edge_quad(u_edge: float):
    """A constant-colour quad at depth 2 covering every pixel right of the vertical screen line u = u_edge (32x32
    camera, f = 20, principal point at the centre)."""
    f, c, z = 20.0, 16.0, 2.0
    x0, x1, y0, y1 = (u_edge - c) * z / f, (40 - c) * z / f, (-10 - c) * z / f, (42 - c) * z / f
    pos = torch.tensor([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]], dtype=torch.int32)
    col = torch.tensor([[0.2, 0.4, 0.6]]).repeat(4, 1)
    K = torch.tensor([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    return pos, faces, col, torch.eye(4), K


def test_supersampled_hard_render_averages_the_samples_of_each_pixel():
    """An edge at u = 10.3 crosses pixel column 10: its centre (10.5) is covered at s = 1, 1 of its 2 sample
    columns (centres 10.25, 10.75) at s = 2, 3 of 4 (10.125 ... 10.875) at s = 4; the pixel is that share of the
    face's colour over the background."""
    pos, faces, col, w2c, K = _edge_quad(10.3)
    bg = torch.tensor([1.0, 1.0, 1.0])
    for s, share in ((1, 1.0), (2, 0.5), (4, 0.75)):
        out = rasterize_hard(pos, faces, col, w2c, K, 32, 32, bg, supersample=s)
        torch.testing.assert_close(out.alpha[:, 10], torch.full((32,), share))
        torch.testing.assert_close(out.alpha[:, 11:], torch.ones(32, 21))
        torch.testing.assert_close(out.alpha[:, :10], torch.zeros(32, 10))
        torch.testing.assert_close(out.rgb[:, 10], (share * col[0] + (1 - share) * bg).expand(32, 3))
        assert out.rgb.shape == (32, 32, 3) and out.face_id.shape == (32, 32)
        torch.testing.assert_close(out.depth[:, 11:], torch.full((32, 21), 2.0))


def test_supersampled_hard_render_is_the_pooled_brute_force_of_the_sample_grid():
    pos, faces, col, _, w2c, K = random_scene(5, 40)
    s = 2
    out = rasterize_hard(pos, faces, col, w2c, K, 40, 32, supersample=s)
    K2 = K.clone()
    K2[:2] *= s
    fid, rgb, _ = brute_force(pos.numpy(), faces.numpy(), col.numpy(), w2c.numpy(), K2.numpy(), 40 * s, 32 * s)
    rgb[fid < 0] = 0.0  # black background, as rasterize_hard's default
    pooled = rgb.reshape(32, s, 40, s, 3).mean((1, 3))
    close = np.abs(out.rgb.numpy() - pooled).max(-1) < 1e-4
    assert close.mean() >= 1 - 4 * BOUNDARY_FRACTION  # a pixel holds 4 samples that may sit on an edge
    assert (fid >= 0).mean() > 0.3
    np.testing.assert_allclose(out.alpha.numpy(), (fid >= 0).reshape(32, s, 40, s).mean((1, 3)), atol=0.26)
    with pytest.raises(ValueError, match="supersample"):
        rasterize_hard(pos, faces, col, w2c, K, 40, 32, supersample=5)


def test_depth_order_is_a_stable_sort_by_slab_with_gathered_rows():
    from trisplat.render.hard import ORDER_CHUNKS, depth_order

    rng = np.random.default_rng(0)
    F = 10 * ORDER_CHUNKS + 7  # chunks of unequal size
    znear = rng.uniform(0.1, 1.0, F).astype(np.float32)
    box = np.tile(np.array([[0, 5, 0, 5]], np.int32), (F, 1))
    box[rng.random(F) < 0.2, :2] = (1, 0)  # culled faces are left out
    uvz = rng.random((F, 9)).astype(np.float32)
    order, uvz_o = np.empty(F, np.int32), np.empty((F, 9), np.float32)
    box_o, znear_o = np.empty((F, 4), np.int32), np.empty(F, np.float32)
    n = depth_order(box, znear, uvz, 16, order, uvz_o, box_o, znear_o)
    vis = np.flatnonzero(box[:, 0] <= box[:, 1])
    z = 1.0 / znear[vis].astype(np.float64)
    slab = np.minimum(15, ((z - z.min()) * (16 / (z.max() - z.min()))).astype(int))
    expected = vis[np.argsort(slab, kind="stable")]
    assert n == len(vis)
    np.testing.assert_array_equal(order[:n], expected)
    np.testing.assert_array_equal(uvz_o[:n], uvz[expected])
    np.testing.assert_array_equal(box_o[:n], box[expected])
    np.testing.assert_array_equal(znear_o[:n], znear[expected])
