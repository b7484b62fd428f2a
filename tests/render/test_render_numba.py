"""The Numba kernels against the dense reference: forward values and every gradient, on awkward random scenes."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from render_scenes import mesh_scene, random_scene

from trisplat.render import rasterize

SIGMA = 0.7
IMG_ATOL = 2e-4  # float32 kernel vs float64 reference, per pixel value
BOUNDARY_FRACTION = 0.01  # pixels allowed to exceed IMG_ATOL (centres within float32 rounding of an edge/threshold)
GRAD_RTOL = 2e-3  # gradient agreement, relative to the largest gradient of the same kind


def _both(scene, opts, weights_seed=0):
    pos, faces, col, op, w2c, K = scene
    res = {}
    for be in ("reference", "numba"):
        P = [pos.clone().requires_grad_(), col.clone().requires_grad_(), op.clone().requires_grad_()]
        out = rasterize(P[0], faces, P[1], P[2], SIGMA, w2c, K, 40, 32, backend=be, **opts)
        g = torch.Generator().manual_seed(weights_seed)
        loss = sum((t * (torch.rand(t.shape, generator=g, dtype=t.dtype) - 0.3)).sum()
                   for t in (out.rgb, out.alpha, out.depth, out.normal))
        loss.backward()
        res[be] = (out, [p.grad for p in P])
    return res


def _close_images(a, b):
    for name in ("rgb", "alpha", "depth", "normal"):
        x, y = getattr(a, name).detach(), getattr(b, name).detach()
        bad = (x - y).abs() > IMG_ATOL
        if bad.ndim == 3:
            bad = bad.any(-1)
        assert bad.float().mean().item() <= BOUNDARY_FRACTION, f"{name}: {int(bad.sum())} pixels differ"


SCENES = [
    (0, "soup", {}), (1, "soup", {}), (2, "mesh", {}), (3, "soup", {"perspective_correct": True}),
    (4, "mesh", {"opacity_mode": "mean"}), (5, "soup", {"tile_size": 8}), (6, "soup", {"supersample": 2}),
    (7, "mesh", {"perspective_correct": True, "tile_size": 32}),
    (8, "deep", {"tile_size": 32}),  # ~100 pairs per tile: several gather blocks, tiles that turn opaque early
    (9, "soup", {"linear_light": True}), (10, "mesh", {"linear_light": True, "supersample": 2}),
]


@pytest.mark.parametrize("seed,kind,opts", SCENES)
def test_numba_matches_reference_forward_and_backward(seed, kind, opts):
    scene = {"soup": lambda: random_scene(seed, 30), "deep": lambda: random_scene(seed, 200, opacity_range=(0.6, 0.95)),
             "mesh": lambda: mesh_scene(seed)}[kind]()
    res = _both(scene, opts, seed)
    (ref, gref), (nb, gnb) = res["reference"], res["numba"]
    _close_images(ref, nb)
    torch.testing.assert_close(nb.max_weight, ref.max_weight, atol=IMG_ATOL, rtol=0)
    assert (nb.face_id != ref.face_id).float().mean().item() <= BOUNDARY_FRACTION
    for name, a, b in zip(("positions", "colors", "opacities"), gref, gnb):
        scale = a.abs().max().item()
        assert scale > 0
        err = (a - b).abs().max().item()
        assert err <= GRAD_RTOL * scale, f"{name}: max error {err:.3g} vs scale {scale:.3g}"


def test_pairs_evaluated_far_fewer_than_bounding_boxes():
    scene = random_scene(11, 60)
    nb = rasterize(*scene[:4], SIGMA, *scene[4:], 40, 32)
    ref = rasterize(*scene[:4], SIGMA, *scene[4:], 40, 32, backend="reference")
    # The reference evaluates every pixel of every block a face's bounding box touches; the kernel only
    # pixel centres inside the per-row spans of the exact tile overlaps.
    assert 0 < nb.pairs_evaluated < 0.5 * ref.pairs_evaluated
    assert nb.faces_visible <= 60 + 6 and nb.faces_visible >= 30


def test_face_order_invariance_numba():
    pos, faces, col, op, w2c, K = random_scene(12, 40)
    a = rasterize(pos, faces, col, op, SIGMA, w2c, K, 40, 32)
    perm = torch.randperm(faces.shape[0], generator=torch.Generator().manual_seed(1))
    b = rasterize(pos, faces[perm], col, op, SIGMA, w2c, K, 40, 32)
    torch.testing.assert_close(a.rgb, b.rgb, atol=1e-6, rtol=0)
    torch.testing.assert_close(a.max_weight[perm], b.max_weight, atol=1e-6, rtol=0)


def test_batched_views_equal_single_views():
    pos, faces, col, op, w2c, K = random_scene(13, 20)
    R = torch.tensor([[np.cos(0.1), 0, np.sin(0.1)], [0, 1, 0], [-np.sin(0.1), 0, np.cos(0.1)]])
    w2c2 = w2c.clone()
    w2c2[:3, :3] = R
    w2c2[:3, 3] = torch.tensor([0.1, -0.05, 0.2])
    both = rasterize(pos, faces, col, op, SIGMA, torch.stack([w2c, w2c2]), K, 40, 32)
    for i, m in enumerate((w2c, w2c2)):
        one = rasterize(pos, faces, col, op, SIGMA, m, K, 40, 32)
        torch.testing.assert_close(both.rgb[i], one.rgb, atol=0, rtol=0)
        torch.testing.assert_close(both.max_weight[i], one.max_weight, atol=0, rtol=0)


def test_float32_inputs_and_numpy_inputs_work_alike():
    pos, faces, col, op, w2c, K = random_scene(14, 20)
    a = rasterize(pos.float(), faces, col.float(), op.float(), SIGMA, w2c.numpy(), K.numpy(), 40, 32)
    b = rasterize(pos.numpy(), faces.numpy(), col.numpy(), op.numpy(), SIGMA, w2c, K, 40, 32)
    assert a.rgb.dtype == torch.float32 and b.rgb.dtype == torch.float64
    torch.testing.assert_close(a.rgb.double(), b.rgb, atol=1e-5, rtol=0)


def test_faces_crossing_the_near_plane_or_off_screen_are_culled_whole():
    w2c = torch.eye(4, dtype=torch.float64)
    K = torch.tensor([[40.0, 0, 20], [0, 40.0, 16], [0, 0, 1]], dtype=torch.float64)
    crossing = torch.tensor([[-0.5, -0.5, 0.005], [0.5, -0.4, 2.0], [0.0, 0.5, 2.0]], dtype=torch.float64)
    inside = crossing.clone()
    inside[0, 2] = 0.05
    off = torch.tensor([[3.0, 0, 2], [4.0, 0, 2], [3.5, 1, 2]], dtype=torch.float64)  # right of the image
    faces = torch.tensor([[0, 1, 2]], dtype=torch.int32)
    col, op = torch.ones(3, 3, dtype=torch.float64), torch.full((3,), 0.9, dtype=torch.float64)
    for backend in ("numba", "reference"):
        a = rasterize(crossing, faces, col, op, 0.5, w2c, K, 40, 32, near=0.01, backend=backend)
        b = rasterize(inside, faces, col, op, 0.5, w2c, K, 40, 32, near=0.01, backend=backend)
        assert a.alpha.max().item() == 0 and b.alpha.sum().item() > 20
        assert a.faces_visible == 0 and b.faces_visible == 1
    c = rasterize(off, faces, col, op, 0.5, w2c, K, 40, 32)
    assert c.faces_visible == 0 and c.pairs_evaluated == 0 and c.alpha.max().item() == 0


@pytest.mark.parametrize("s,C", [(2, 3), (2, 1), (4, 3)])
def test_box_pool_is_the_mean_over_each_pixels_samples_value_and_gradient(s, C):
    """Supersampling's box filter (render.types.box_downsample, a custom autograd function for speed) against the plain
    reshape-and-mean it replaces, forward and backward, and torch's gradcheck in float64."""
    from trisplat.render.types import box_downsample as _pool

    g = torch.Generator().manual_seed(s * 10 + C)
    H, W = 5, 7
    x = torch.rand(H * s, W * s, C, generator=g, dtype=torch.float64, requires_grad=True)
    ref = x.reshape(H, s, W, s, C).mean(dim=(1, 3))
    out = _pool(x, s)
    assert out.shape == (H, W, C)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    w = torch.rand(H, W, C, generator=g, dtype=torch.float64)
    (gx,) = torch.autograd.grad((out * w).sum(), x)
    (gref,) = torch.autograd.grad((ref * w).sum(), x)
    torch.testing.assert_close(gx, gref, rtol=0, atol=1e-12)
    assert torch.autograd.gradcheck(lambda t: _pool(t, s), (x,))
    assert not x.grad_fn and _pool(x.detach().float(), s).dtype == torch.float32


def test_scatter_vertices_parallel_copies_sum_as_np_add_at():
    """The backward's vertex scatter (per-thread private copies, then added) against numpy's unbuffered add, on
    enough faces for its parallel path."""
    from trisplat.render import kernels as kn

    rng = np.random.default_rng(0)
    V, F, f0 = 5_000, 60_000, 7
    faces = rng.integers(0, V, size=(F + f0, 3)).astype(np.int32)
    gp, gr, go = (rng.normal(size=(F, 3, 3)).astype(np.float32), rng.normal(size=(F, 3, 3)).astype(np.float32),
                  rng.normal(size=(F, 3)).astype(np.float32))
    assert F >= kn.SCATTER_SERIAL_BELOW
    out = [np.zeros((V, 3), np.float32), np.zeros((V, 3), np.float32), np.zeros(V, np.float32)]
    kn.scatter_vertices(faces, f0, gp, gr, go, *out)
    ref = [np.zeros((V, 3)), np.zeros((V, 3)), np.zeros(V)]
    idx = faces[f0:].reshape(-1)
    np.add.at(ref[0], idx, gp.reshape(-1, 3))
    np.add.at(ref[1], idx, gr.reshape(-1, 3))
    np.add.at(ref[2], idx, go.reshape(-1))
    for got, want in zip(out, ref):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("threads", [1, 2])
def test_scatter_vertices_skips_the_faces_without_pairs(threads):
    """Given bin_faces' face_start, the scatter adds only the faces with pairs (setup_backward leaves the others'
    rows unwritten): with NaN in those rows, the sums equal the scatter of the same gradients with zeros there,
    over two chunks (f0 > 0 on the second)."""
    import numba

    from trisplat.render import kernels as kn

    old = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        rng = np.random.default_rng(2)
        V, F = 2_000, 2 * kn.SCATTER_SERIAL_BELOW
        faces = rng.integers(0, V, size=(F, 3)).astype(np.int32)
        pairs = rng.integers(0, 3, size=F) * (rng.random(F) < 0.3)  # 70% of the faces not shown
        face_start = np.concatenate([[0], np.cumsum(pairs)]).astype(np.int64)
        shown = pairs > 0
        gp, gr = rng.normal(size=(F, 3, 3)).astype(np.float32), rng.normal(size=(F, 3, 3)).astype(np.float32)
        go = rng.normal(size=(F, 3)).astype(np.float32)
        zero = [np.where(shown.reshape((-1,) + (1,) * (g.ndim - 1)), g, 0).astype(np.float32) for g in (gp, gr, go)]
        nan = [np.where(shown.reshape((-1,) + (1,) * (g.ndim - 1)), g, np.nan).astype(np.float32) for g in (gp, gr, go)]
        outs = []
        for grads, fs in ((zero, None), (nan, face_start)):
            out = [np.zeros((V, 3), np.float32), np.zeros((V, 3), np.float32), np.zeros(V, np.float32)]
            for f0, f1 in ((0, F // 2), (F // 2, F)):
                kn.scatter_vertices(faces, f0, *(g[f0:f1] for g in grads), *out, face_start=fs)
            outs.append(out)
        for a, b in zip(*outs):
            np.testing.assert_array_equal(a, b)
        assert np.abs(outs[0][0]).max() > 0
    finally:
        numba.set_num_threads(old)


@pytest.mark.parametrize("threads", [1, 2])
def test_scatter_vertices_hub_and_unreferenced_vertices_at_1_and_2_threads(threads):
    """The scatter on its parallel path with a vertex shared by a tenth of the corners, vertices no face uses, and
    two chunks (f0 > 0 on the second): every thread count gives the serial pass's float32 sums bit for bit (each
    vertex adds its corners in face order), and they match numpy's unbuffered add."""
    import numba

    from trisplat.render import kernels as kn

    threads = min(threads, numba.config.NUMBA_NUM_THREADS)
    rng = np.random.default_rng(1)
    V, F = 3_000, 2 * kn.SCATTER_SERIAL_BELOW
    faces = rng.integers(0, V // 2, size=(F, 3)).astype(np.int32)  # vertices V/2.. unreferenced
    hub = rng.random((F, 3)) < 0.1
    faces[hub] = 7
    gp, gr = rng.normal(size=(F, 3, 3)).astype(np.float32), rng.normal(size=(F, 3, 3)).astype(np.float32)
    go = rng.normal(size=(F, 3)).astype(np.float32)

    def run(n_threads):
        old = numba.get_num_threads()
        numba.set_num_threads(n_threads)
        try:
            out = [np.zeros((V, 3), np.float32), np.zeros((V, 3), np.float32), np.zeros(V, np.float32)]
            for f0, f1 in ((0, F // 2), (F // 2, F)):
                kn.scatter_vertices(faces, f0, gp[f0:f1], gr[f0:f1], go[f0:f1], *out)
            return out
        finally:
            numba.set_num_threads(old)

    got, serial = run(threads), run(1)
    for a, b in zip(got, serial):
        np.testing.assert_array_equal(a, b)
    assert not got[0][V // 2:].any() and not got[2][V // 2:].any()
    ref = [np.zeros((V, 3)), np.zeros((V, 3)), np.zeros(V)]
    idx = faces.reshape(-1)
    np.add.at(ref[0], idx, gp.reshape(-1, 3))
    np.add.at(ref[1], idx, gr.reshape(-1, 3))
    np.add.at(ref[2], idx, go.reshape(-1))
    for a, want in zip(got, ref):
        np.testing.assert_allclose(a, want, rtol=1e-4, atol=2e-3)


def test_the_tile_order_visits_every_tile_once_and_spreads_each_threads_share():
    """raster_forward and raster_backward walk tile (k * spread_stride(nt)) mod nt: a permutation of the tiles for
    every count, whose first and second halves (two threads' static shares) each take about half of the image's
    top and bottom halves (in row order a thread got one half of the image)."""
    from trisplat.render import kernels as kn

    for nt in list(range(1, 300)) + [1700, 4096, 20000]:
        s = kn.spread_stride(nt)
        order = (np.arange(nt) * s) % nt
        assert np.array_equal(np.sort(order), np.arange(nt)), nt
        if nt >= 100:
            first = order[: nt // 2]
            assert abs(np.mean(first < nt // 2) - 0.5) < 0.05, (nt, s)
