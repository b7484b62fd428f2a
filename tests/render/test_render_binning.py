"""The CPU renderer's parallel depth sort and tile binning (kernels.depth_order, kernels.bin_faces) against plain
references, at 1 and 2 threads and at several block counts; and whole renders with ties in depth, faces on many
tiles and empty tiles against the torch reference."""
from __future__ import annotations

import numba
import numpy as np
import pytest
import torch
from render_scenes import camera, random_scene, unproject

from trisplat.render import kernel_math, rasterize
from trisplat.render import kernels as kn

THREADS = sorted({1, min(2, numba.config.NUMBA_NUM_THREADS)})
BLOCKS_PER_THREAD = (1, 3, 4, 200)  # 200: more blocks than elements in the small cases (capped at MAX_BLOCKS)


@pytest.fixture(params=THREADS)
def threads(request):
    old = numba.get_num_threads()
    numba.set_num_threads(request.param)
    yield request.param
    numba.set_num_threads(old)


def _numpy_order(ntiles, key):
    """What the renderer did before depth_order: numpy's stable argsort of the int32 bits of the shown faces' keys."""
    shown = np.flatnonzero(ntiles).astype(np.int32)
    return shown[np.argsort(key[shown].view(np.int32), kind="stable")]


def _key_cases():
    rng = np.random.default_rng(3)
    F = 5000
    yield "random", rng.integers(0, 4, F), rng.uniform(0.5, 30.0, F).astype(np.float32)
    yield "ties", rng.integers(0, 2, F), rng.choice(np.float32([1.0, 2.5, 2.5000002, 7.0]), F)
    yield "all equal", np.ones(F, np.int64), np.full(F, 3.25, np.float32)  # every radix pass skipped
    yield "one high digit", np.ones(F, np.int64), rng.choice(np.float32([1.0, 4.0]), F)  # differ in the exponent only
    bits = rng.integers(-2**31, 2**31, F, dtype=np.int64).astype(np.int32)
    yield "any int32 bits", rng.integers(0, 3, F), bits.view(np.float32)  # negative ints too (signed order)
    yield "none shown", np.zeros(F, np.int64), rng.uniform(1, 2, F).astype(np.float32)
    yield "one face", np.array([2]), np.float32([1.5])
    yield "empty", np.zeros(0, np.int64), np.zeros(0, np.float32)
    yield "few", np.array([1, 0, 1, 1, 0, 1]), np.float32([3.0, 1.0, 2.0, 3.0, 9.0, 2.0])


@pytest.mark.parametrize("case", list(_key_cases()), ids=lambda c: c[0])
@pytest.mark.parametrize("bpt", BLOCKS_PER_THREAD)
def test_depth_order_is_numpys_stable_argsort(case, bpt, threads, monkeypatch):
    _, ntiles, key = case
    monkeypatch.setattr(kn, "BLOCKS_PER_THREAD", bpt)
    got = kn.depth_order(ntiles, key)
    want = _numpy_order(ntiles, key)
    assert got.dtype == np.int32
    np.testing.assert_array_equal(got, want)


def _setup(scene, width, height, tile):
    """setup_faces on a test scene: theta, rect, key, ntiles (float32 inputs as the renderer passes them)."""
    pos, faces, col, op, w2c, K = scene
    F = faces.shape[0]
    theta = np.empty((F, kn.N_THETA), np.float32)
    rect = np.empty((F, 4), np.int32)
    key = np.zeros(F, np.float32)
    argmin = np.empty(F, np.int8)
    ntiles = np.empty(F, np.int64)
    kn.setup_faces(pos.numpy().astype(np.float32), faces.numpy().astype(np.int32), w2c.numpy(), K.numpy(),
                   col.numpy().astype(np.float32), op.numpy().astype(np.float32), True, 0.05, 100.0, 0.0, 0.0,
                   width, height, tile, theta, rect, key, argmin, ntiles)
    return theta, rect, key, ntiles


def _reference_lists(theta, rect, ntiles, order, width, height, tile):
    """Per tile, the faces overlapping it (kernel_math.tile_overlap, plain Python) in `order`'s order."""
    ntx, nty = -(-width // tile), -(-height // tile)
    lists = [[] for _ in range(ntx * nty)]
    for f in order:
        ix0, iy0, ix1, iy1 = (int(v) for v in rect[f])
        n = 0
        for ty in range(iy0 // tile, iy1 // tile + 1):
            for tx in range(ix0 // tile, ix1 // tile + 1):
                if kernel_math.tile_overlap(theta[f], ix0, iy0, ix1, iy1, tile, tx, ty):
                    lists[ty * ntx + tx].append(int(f))
                    n += 1
        assert n == ntiles[f]
    return lists


@pytest.mark.parametrize("seed,n_faces,tile,kinds", [(0, 40, 4, True), (1, 200, 8, True), (2, 6, 4, False),
                                                     (3, 0, 8, True)])
@pytest.mark.parametrize("bpt", BLOCKS_PER_THREAD)
def test_bin_faces_against_plain_lists(seed, n_faces, tile, kinds, bpt, threads, monkeypatch):
    """Every tile's list holds exactly its overlapping faces, front to back (ties in face order); the face-major
    arrays and the two index maps agree. With the awkward kinds the scenes have a face over the whole image (on
    every tile) and faces off screen or culled; with a few small faces only, empty tiles."""
    monkeypatch.setattr(kn, "BLOCKS_PER_THREAD", bpt)
    W, H = 40, 32
    theta, rect, key, ntiles = _setup(random_scene(seed, n_faces, kinds=kinds), W, H, tile)
    order = _numpy_order(ntiles, key)
    face_start, pair_face, tile_start, tile_pairs, pos_of = kn.bin_faces(theta, rect, ntiles, order, W, H, tile)
    np.testing.assert_array_equal(face_start, np.concatenate([[0], np.cumsum(ntiles)]))
    np.testing.assert_array_equal(pair_face, np.repeat(np.arange(len(ntiles)), ntiles))
    P = len(pair_face)
    np.testing.assert_array_equal(np.sort(tile_pairs), np.arange(P))
    np.testing.assert_array_equal(pos_of[tile_pairs], np.arange(P))
    ref = _reference_lists(theta, rect, ntiles, order, W, H, tile)
    assert len(tile_start) == len(ref) + 1
    for t, want in enumerate(ref):
        got = pair_face[tile_pairs[tile_start[t]:tile_start[t + 1]]]
        assert got.tolist() == want, f"tile {t}"
    if kinds:
        assert ntiles.max() == len(ref) and (ntiles == 0).any()  # a face on every tile; culled or off-screen faces
    else:
        assert any(not lst for lst in ref)  # empty tiles
    assert max(len(lst) for lst in ref) >= 2


def tie_scene(dtype=torch.float64):
    """Overlapping faces at exactly one view depth (every vertex at z = 2: equal sort keys in float32 and float64)
    in distinct colours, some covering many tiles, plus a few at other depths: the compositing order of the tied
    faces (face order) decides the colours."""
    rng = np.random.default_rng(7)
    w2c, K = camera(dtype=dtype)
    Kn = K.numpy()
    tris = []
    for i in range(12):
        c = rng.uniform([5, 5], [35, 27])
        size = 25.0 if i % 4 == 0 else rng.uniform(6, 14)
        uv = c + rng.normal(size=(3, 2)) * size / 2
        z = np.full(3, 2.0) if i < 9 else np.full(3, 1.5 + 0.5 * (i - 9))
        tris.append(unproject(uv, z, Kn))
    pos = np.concatenate(tris, 0)
    F = len(tris)
    faces = np.arange(3 * F, dtype=np.int32).reshape(F, 3)
    colors = rng.uniform(0, 1, size=(3 * F, 3))
    opac = rng.uniform(0.6, 0.9, size=3 * F)
    t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    return t(pos), torch.tensor(faces), t(colors), t(opac), w2c, K


def _render(scene, backend, tile_size):
    pos, faces, col, op, w2c, K = scene
    P = [pos.clone().requires_grad_(), col.clone().requires_grad_(), op.clone().requires_grad_()]
    out = rasterize(P[0], faces, P[1], P[2], 0.7, w2c, K, 40, 32, backend=backend, tile_size=tile_size)
    g = torch.Generator().manual_seed(1)
    (out.rgb * torch.rand(out.rgb.shape, generator=g, dtype=out.rgb.dtype)).sum().backward()
    return out.rgb.detach(), [p.grad for p in P]


def _assert_matches(ref, got):
    (img_r, g_r), (img_n, g_n) = ref, got
    bad = ((img_r - img_n).abs() > 2e-4).any(-1)
    assert bad.float().mean().item() <= 0.01, f"{int(bad.sum())} pixels differ"
    for a, b in zip(g_r, g_n):
        assert (a - b).abs().max().item() <= 2e-3 * a.abs().max().item()


@pytest.mark.parametrize("tile_size", [4, 16])
def test_ties_in_depth_render_like_the_reference(tile_size, threads):
    scene = tie_scene()
    _assert_matches(_render(scene, "reference", tile_size), _render(scene, "numba", tile_size))


def test_tie_scene_sees_the_tie_order(monkeypatch):
    """The tie scene's colours depend on the order of the tied faces: with the ties reversed the numba render no
    longer matches the reference (so the test above would catch a sort that breaks ties differently)."""
    scene = tie_scene()
    ref = _render(scene, "reference", 8)
    true_order = kn.depth_order

    def ties_reversed(ntiles, key):
        order = true_order(ntiles, key)
        k = key[order]
        out = order.copy()
        i = 0
        while i < len(order):
            j = i
            while j < len(order) and k[j] == k[i]:
                j += 1
            out[i:j] = order[i:j][::-1]
            i = j
        return out

    monkeypatch.setattr(kn, "depth_order", ties_reversed)
    with pytest.raises(AssertionError):
        _assert_matches(ref, _render(scene, "numba", 8))
