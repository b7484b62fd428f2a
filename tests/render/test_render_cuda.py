"""The CUDA backend (backend="cuda", numba-cuda kernels) against the dense reference: forward values and every
gradient on awkward tiny scenes, with the Numba test's tolerances; its binning against the CPU kernels' lists, its
z-buffer against the brute-force oracle, and its errors.

Without a GPU (CI) the kernels run in numba's CUDA simulator (tests/conftest.py turns it on), one Python thread per
CUDA thread: scenes of a few dozen faces at 32x24. On a GPU the same tests render CUDA tensors, and a medium scene
is compared with the Numba kernels too. The simulator runs the kernels as Python, so their CUDA compilation (Numba's
typing and lowering for the GPU) is checked separately (cuda_typecheck.py, in a subprocess).
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from render_scenes import mesh_scene, random_scene, unproject
from test_render_hard import brute_force
from test_render_numba import BOUNDARY_FRACTION, GRAD_RTOL, IMG_ATOL, SIGMA

from trisplat.render import rasterize, rasterize_hard
from trisplat.render.cuda_backend import simulated

ON_GPU = not simulated() and torch.cuda.is_available()
DEVICE = "cuda" if ON_GPU else "cpu"
W, H = 32, 24
pytestmark = pytest.mark.skipif(not (simulated() or ON_GPU), reason=(
    "needs numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1, set by tests/conftest.py when torch sees no GPU) or a GPU; "
    "numba.cuda was imported without the simulator and torch sees no CUDA device"))
sim_only = pytest.mark.skipif(not simulated(), reason="patches kernel code, which only the CUDA simulator runs as Python")


def _render(scene, backend, opts, weights_seed, device="cpu", width=W, height=H, sigma=SIGMA):
    """Render with `backend` on `device`, back-propagate a fixed random linear loss on rgb, alpha, depth and normal."""
    pos, faces, col, op, w2c, K = (t.to(device) for t in scene)
    P = [pos.clone().requires_grad_(), col.clone().requires_grad_(), op.clone().requires_grad_()]
    out = rasterize(P[0], faces, P[1], P[2], sigma, w2c, K, width, height, backend=backend, **opts)
    g = torch.Generator().manual_seed(weights_seed)
    loss = sum((t * (torch.rand(t.shape, generator=g, dtype=t.dtype).to(device) - 0.3)).sum()
               for t in (out.rgb, out.alpha, out.depth, out.normal))
    loss.backward()
    return out, [p.grad.cpu() for p in P]


def _images_close(a, b, atol=IMG_ATOL) -> list[str]:
    """Names of the images where more than BOUNDARY_FRACTION of the pixels differ by more than atol."""
    bad_names = []
    for name in ("rgb", "alpha", "depth", "normal"):
        x, y = getattr(a, name).detach().cpu(), getattr(b, name).detach().cpu()
        bad = (x - y).abs() > atol
        if bad.ndim == 3:
            bad = bad.any(-1)
        if bad.float().mean().item() > BOUNDARY_FRACTION:
            bad_names.append(f"{name}: {int(bad.sum())} pixels differ by more than {atol}")
    return bad_names


def _grads_close(ga, gb, rtol=GRAD_RTOL) -> list[str]:
    """Names of the gradients whose largest error exceeds rtol times their largest entry."""
    bad = []
    for name, a, b in zip(("positions", "colors", "opacities"), ga, gb):
        scale = a.abs().max().item()
        assert scale > 0, f"{name}: no gradient"
        err = (a - b).abs().max().item()
        if err > rtol * scale:
            bad.append(f"{name}: max error {err:.3g} vs scale {scale:.3g}")
    return bad


def _deep_scene(seed: int, layers: int = 6):
    """A random soup behind `layers` large, nearly opaque triangles stacked over the image centre: pixels there turn
    opaque (the early stop at T < transmittance_min) and alphas near the incentres pass the 0.99 cap."""
    pos, faces, col, op, w2c, K = random_scene(seed, 12, W, H, opacity_range=(0.9, 1.0))
    rng = np.random.default_rng(seed)
    tris = [unproject(np.array([[W / 2 - 22, H / 2 - 16], [W / 2 + 24, H / 2 - 12], [W / 2, H / 2 + 22]])
                      + rng.normal(size=(3, 2)), np.full(3, 1.2 + 0.15 * i) + rng.normal(size=3) * 0.05, K.numpy())
            for i in range(layers)]
    n = pos.shape[0]
    new = torch.tensor(np.concatenate(tris), dtype=pos.dtype)
    return (torch.cat([pos, new]), torch.cat([faces, n + torch.arange(3 * layers, dtype=faces.dtype).reshape(-1, 3)]),
            torch.cat([col, torch.tensor(rng.uniform(0, 1, (3 * layers, 3)), dtype=col.dtype)]),
            torch.cat([op, torch.full((3 * layers,), 1.0, dtype=op.dtype)]), w2c, K)


def _scene(kind: str, seed: int):
    return {"soup": lambda: random_scene(seed, 10, W, H), "deep": lambda: _deep_scene(seed),
            "mesh": lambda: mesh_scene(seed, 4, W, H)}[kind]()


SCENES = [  # seed, kind, options: tiles of 8 (several blocks of 2 warps) and 16 (partial tiles at the image's edge)
    (0, "soup", {"tile_size": 8}), (1, "soup", {"tile_size": 16}),
    (2, "mesh", {"perspective_correct": True, "tile_size": 8}), (3, "mesh", {"opacity_mode": "mean", "tile_size": 16}),
    (4, "deep", {"tile_size": 8}),  # opaque layers: early stops, alphas over the 0.99 cap
]


@pytest.mark.parametrize("seed,kind,opts", SCENES)
def test_cuda_matches_reference_forward_and_backward(seed, kind, opts, monkeypatch):
    """The Numba test's loss and tolerances: images within IMG_ATOL except boundary pixels, per-face max weight within
    IMG_ATOL, face_id, each gradient within GRAD_RTOL of its largest entry, against the float64 reference. The deep
    scene runs with shared-memory batches of 8 faces in the simulator (256 on a GPU), so tiles take several."""
    if kind == "deep" and simulated():
        from trisplat.render import cuda_kernels

        monkeypatch.setattr(cuda_kernels, "BATCH", 8)
    scene = _scene(kind, seed)
    sigma = 0.2 if kind == "deep" else SIGMA  # sharp windows: alphas near the incentres pass the cap
    ref, gref = _render(scene, "reference", opts, seed, sigma=sigma)
    out, gout = _render(scene, "cuda", opts, seed, DEVICE, sigma=sigma)
    assert out.rgb.device.type == DEVICE and out.face_id.device.type == DEVICE and out.rgb.dtype == ref.rgb.dtype
    assert not _images_close(ref, out)
    torch.testing.assert_close(out.max_weight.cpu(), ref.max_weight, atol=IMG_ATOL, rtol=0)
    assert (out.face_id.cpu() != ref.face_id).float().mean().item() <= BOUNDARY_FRACTION
    assert not _grads_close(gref, gout)
    nb = rasterize(*scene[:4], sigma, *scene[4:], W, H, **opts)
    assert out.faces_visible == nb.faces_visible > 0 and out.pairs_evaluated >= nb.pairs_evaluated
    if kind == "deep":  # the paths this scene is for were taken: pixels that stopped early, alphas at the cap
        assert (ref.alpha > 1 - 1e-4).sum() > 20, "too few pixels became opaque"
        assert ref.max_weight.max() >= 0.99 * (1 - 1e-9), "no alpha reached the cap"


def _mutant(monkeypatch, name, fn):
    """Replace kernel_math's function `name` in the CUDA kernels (the simulator runs them as Python) by fn(original)."""
    from trisplat.render import cuda_kernels

    original = getattr(cuda_kernels.km, name)
    monkeypatch.setattr(cuda_kernels.km, name, fn(original))


@sim_only
def test_the_parity_checks_fail_for_a_wrong_forward_or_gradient(monkeypatch):
    """The comparisons above are sharp enough: swapping two interpolation weights fails the images, and dropping the
    window's gradient at the arg-max edge (the position gradient through phi) fails the position gradients."""
    scene, opts = _scene("soup", 0), {"tile_size": 8}
    ref, gref = _render(scene, "reference", opts, 0)

    def swapped(fn):
        def barycentric(*a):
            b0, b1, b2, dep, w0, w1, w2 = fn(*a)
            return b0, b1, b2, dep, w1, w0, w2
        return barycentric

    with monkeypatch.context() as m:
        _mutant(m, "barycentric", swapped)
        out, _ = _render(scene, "cuda", opts, 0)
    assert any(name.startswith("rgb") for name in _images_close(ref, out))

    def no_edge_gradient(fn):
        def window_backward(*a):
            gop, ginv, _, _, _ = fn(*a)
            zero = np.float32(0.0)
            return gop, ginv, zero, zero, zero
        return window_backward

    with monkeypatch.context() as m:
        _mutant(m, "window_backward", no_edge_gradient)
        out, gout = _render(scene, "cuda", opts, 0)
    assert not _images_close(ref, out)
    assert [e for e in _grads_close(gref, gout) if e.startswith("positions")]


def test_cuda_binning_matches_the_cpu_kernels_tile_lists():
    """Per-face setup (THETA, boxes, tile counts, arg-min vertices) and the device binning (emit_pairs + a stable
    torch.sort of tile << 32 | depth bits) give every tile the faces of the CPU kernels' bin_faces, in their order."""
    from trisplat.render import kernels as kn
    from trisplat.render.cuda_backend import _Launcher, bin_pairs

    pos, faces, col, op, w2c, K = random_scene(5, 30, W, H)
    tile, F = 8, faces.shape[0]
    args = (pos.float().numpy(), faces.numpy().astype(np.int32), w2c.numpy(), K.numpy(), col.float().numpy(),
            op.float().numpy(), True, 0.01, 1e10, 1e-6, 1e-4, W, H, tile)
    cpu = (np.zeros((F, kn.N_THETA), np.float32), np.zeros((F, 4), np.int32), np.zeros(F, np.float32),
           np.zeros(F, np.int8), np.zeros(F, np.int64))
    kn.setup_faces(*args, *cpu)
    order = np.argsort(cpu[2].view(np.int32), kind="stable").astype(np.int32)
    face_start, pair_face, tile_start, tile_pairs, _ = kn.bin_faces(cpu[0], cpu[1], cpu[4], order, W, H, tile)
    launch = _Launcher(torch.device(DEVICE))
    z = lambda *s, dt=torch.float32: torch.zeros(*s, dtype=dt, device=DEVICE)  # noqa: E731
    gpu = (z(F, kn.N_THETA), z(F, 4, dt=torch.int32), z(F), z(F, dt=torch.int32), z(F, dt=torch.int32))
    t = lambda a: torch.as_tensor(a, device=DEVICE) if isinstance(a, np.ndarray) else a  # noqa: E731
    launch.per_face(launch.kernels.setup_faces, F, *[t(a) for a in args], *gpu)
    np.testing.assert_allclose(gpu[0].cpu().numpy(), cpu[0], rtol=1e-6, atol=1e-6)
    for a, b in zip(gpu[1:], cpu[1:]):
        np.testing.assert_array_equal(a.cpu().numpy(), b)
    tile_faces, ts, ntx = bin_pairs(launch, gpu[0], gpu[1], gpu[4], gpu[2], tile, W, H, False)
    assert ntx == (W + tile - 1) // tile
    np.testing.assert_array_equal(ts.cpu().numpy(), tile_start)
    np.testing.assert_array_equal(tile_faces.cpu().numpy(), pair_face[tile_pairs])
    assert tile_start[-1] > F and (np.diff(tile_start) > 2).sum() > 4  # faces over several tiles, full tiles


def test_cuda_empty_scenes_and_precise_errors(monkeypatch):
    """No faces, and faces all behind the camera: the background, no pairs, zero gradients. Unsupported tile sizes and
    CPU tensors on a real GPU backend are refused with the reason."""
    from trisplat.render import cuda_backend

    pos, faces, col, op, w2c, K = (t.to(DEVICE) for t in random_scene(13, 6, W, H))
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64, device=DEVICE)
    none = rasterize(pos, faces[:0], col, op, SIGMA, w2c, K, W, H, bg, backend="cuda", tile_size=8)
    torch.testing.assert_close(none.rgb, bg.expand(H, W, 3))
    assert none.faces_visible == 0 and none.pairs_evaluated == 0 and (none.face_id == -1).all()
    behind = pos.clone()
    behind[:, 2] = -1.0
    out = rasterize(behind.requires_grad_(), faces, col, op, SIGMA, w2c, K, W, H, bg, backend="cuda", tile_size=8)
    out.rgb.sum().backward()
    torch.testing.assert_close(out.rgb, bg.expand(H, W, 3))
    assert behind.grad is not None and behind.grad.abs().max().item() == 0
    with pytest.raises(ValueError, match="tile_size in \\(8, 16, 24, 32\\)"):
        rasterize(pos, faces, col, op, SIGMA, w2c, K, W, H, backend="cuda", tile_size=12)
    monkeypatch.setattr(cuda_backend, "simulated", lambda: False)
    with pytest.raises(ValueError, match="renders CUDA tensors, got tensors on cpu"):
        rasterize(pos.cpu(), faces.cpu(), col.cpu(), op.cpu(), SIGMA, w2c, K, W, H, backend="cuda")


def test_cuda_hard_matches_brute_force_and_numba():
    """The z-buffer: at each pixel centre the nearest face, its colour and depth, as the brute-force oracle (all but
    boundary pixels); max_weight marks the winners; the Numba z-buffer agrees; supersampling, perspective-correct
    colours and SH colours of a batch of views as with Numba."""
    from trisplat.scene.sh import rgb_to_sh_dc

    pos, faces, col, _, w2c, K = random_scene(0, 24, W, H)
    out = rasterize_hard(*(t.to(DEVICE) for t in (pos, faces, col, w2c, K)), W, H, backend="cuda")
    assert out.rgb.device.type == DEVICE
    fid, rgb, depth = brute_force(pos.numpy(), faces.numpy(), col.numpy(), w2c.numpy(), K.numpy(), W, H)
    got = out.face_id.cpu().numpy()
    same = got == fid
    assert same.mean() >= 1 - 0.02 and (fid >= 0).sum() > 300
    np.testing.assert_allclose(out.rgb.cpu().numpy()[same], rgb[same], atol=1e-4)
    np.testing.assert_allclose(out.depth.cpu().numpy()[same], depth[same], rtol=1e-4)
    assert torch.equal(out.alpha.cpu(), (out.face_id.cpu() >= 0).to(out.alpha.dtype))
    winners = np.zeros(faces.shape[0])
    winners[got[got >= 0]] = 1
    np.testing.assert_array_equal(out.max_weight.cpu().numpy(), winners)
    nb = rasterize_hard(pos, faces, col, w2c, K, W, H)
    assert (nb.face_id == out.face_id.cpu()).float().mean().item() >= 1 - 0.02
    torch.testing.assert_close(nb.normal[torch.from_numpy(same)], out.normal.cpu()[torch.from_numpy(same)], atol=1e-4,
                               rtol=0)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    d = lambda *a: [x.to(DEVICE) for x in a]  # noqa: E731
    K2 = K.clone()
    K2[:2] /= 2  # supersampled at half the size: the simulator's time goes with the pixels
    for kw, Kv, w, h in (({"supersample": 2}, K2, W // 2, H // 2), ({"perspective_correct": True}, K, W, H)):
        ref = rasterize_hard(pos, faces, col, w2c, Kv, w, h, bg, **kw)
        cu = rasterize_hard(*d(pos, faces, col, w2c, Kv), w, h, bg.to(DEVICE), backend="cuda", **kw)
        assert ((ref.rgb - cu.rgb.cpu()).abs().amax(-1) < 1e-4).float().mean().item() >= 1 - 0.04
    b = rasterize_hard(*d(pos, faces, rgb_to_sh_dc(col)[:, None], torch.stack([w2c, w2c]), K), W, H, bg.to(DEVICE),
                       backend="cuda")
    torch.testing.assert_close(b.rgb[1].cpu(), rasterize_hard(pos, faces, col, w2c, K, W, H, bg).rgb, atol=1e-4,
                               rtol=0)


def test_cuda_hard_early_stop_is_exact_and_skips_the_layers_behind():
    """A tile's faces come nearest vertex first and a pixel stops at the first face whose nearest vertex lies behind
    what it shows. A steep face whose nearest vertex comes first but which is farther at the image centre than a
    flat face behind that vertex must not hide it; and on a deep scene (a dozen layers) the stop skips most pairs."""
    Kn = random_scene(0, 1, W, H)[5].numpy()
    steep = unproject(np.array([[W / 2 - 40, H / 2 - 20], [W / 2 + 40, H / 2 - 20], [W / 2, H / 2 + 200]]),
                      np.array([5.0, 5.0, 0.5]), Kn)  # nearest vertex (0.5) far below the image; 2.75 at its centre
    flat = unproject(np.array([[W / 2 - 8, H / 2 - 6], [W / 2 + 8, H / 2 - 6], [W / 2, H / 2 + 6]]), np.full(3, 2.0), Kn)
    pos = torch.tensor(np.concatenate([steep, flat]))
    faces = torch.arange(6, dtype=torch.int32).reshape(2, 3)
    col = torch.tensor([[1.0, 0, 0]] * 3 + [[0, 1.0, 0]] * 3, dtype=torch.float64)
    w2c, K = (torch.as_tensor(a) for a in (np.eye(4), Kn))
    out = rasterize_hard(*(t.to(DEVICE) for t in (pos, faces, col, w2c, K)), W, H, backend="cuda")
    fid = brute_force(pos.numpy(), faces.numpy(), col.numpy(), w2c.numpy(), Kn, W, H)[0]
    assert fid[H // 2, W // 2] == 1 and out.face_id[H // 2, W // 2].item() == 1
    assert (out.face_id.cpu().numpy() == fid).mean() >= 0.98
    pos, faces, col, _, w2c, K = random_scene(11, 160, W, H, kinds=False)
    out = rasterize_hard(*(t.to(DEVICE) for t in (pos, faces, col, w2c, K)), W, H, backend="cuda")
    cam = pos.numpy()  # identity pose: camera frame
    uv = cam[faces.numpy()][..., :2] / cam[faces.numpy()][..., 2:] * Kn[[0, 1], [0, 1]] + Kn[:2, 2]
    lo = np.clip(np.ceil(uv.min(1) - 0.5), 0, [W - 1, H - 1])
    hi = np.clip(np.floor(uv.max(1) - 0.5), 0, [W - 1, H - 1])
    in_boxes = int(np.prod(np.maximum(hi - lo + 1, 0), axis=1).sum())  # every (pixel, face) pair in the face's box
    fid = brute_force(pos.numpy(), faces.numpy(), col.numpy(), w2c.numpy(), Kn, W, H)[0]
    assert (out.face_id.cpu().numpy() == fid).mean() >= 0.98
    assert in_boxes > 8 * W * H and out.pairs_evaluated < 0.5 * in_boxes, (out.pairs_evaluated, in_boxes)


def test_input_checks_on_a_gpu_reduce_there_as_the_numpy_scan_does():
    """rasterize() checks its inputs (NaN/Inf, index and opacity ranges); for GPU tensors the reductions run on the
    GPU and only their three numbers come back (copying 1M faces' arrays to the host would cost more than the
    render). The device path, run here on CPU tensors, gives what the numpy path gives."""
    from trisplat.render.inputs import _scan_on_device, scan

    for t in (torch.tensor([1.0, float("nan"), 3.0, -2.0]), torch.tensor([float("inf"), float("-inf")]),
              torch.tensor([[4, 9], [-3, 2]], dtype=torch.int32), torch.zeros(0), torch.rand(1000, dtype=torch.float64)):
        for bounds in (True, False):
            assert _scan_on_device(t.reshape(-1), bounds) == scan(t, bounds), (t, bounds)


def test_kernel_math_stamp_is_current_in_every_launch_layer():
    """Numba caches a kernel by its own file only: the launch layers use their cache only while their
    KERNEL_MATH_STAMP is kernel_math.py's current stamp (kernel_math's docstring). An edit of kernel_math.py must
    update them, or the CPU kernels recompile at every start."""
    from trisplat.render import cuda_kernels, hard, kernel_math, kernels

    stamp = kernel_math.source_stamp()
    stale = [m.__name__ for m in (kernels, hard, cuda_kernels) if m.KERNEL_MATH_STAMP != stamp]
    assert not stale, f"set KERNEL_MATH_STAMP = {stamp!r} in {stale}"
    assert kernels._CACHE and hard._CACHE and cuda_kernels._CACHE


@pytest.mark.skipif(importlib.util.find_spec("numba_cuda") is None,
                    reason="numba-cuda is not installed (pip install 'trisplat[gpu]'); numba's own older CUDA target "
                           "cannot type the kernels' min/max")
def test_cuda_kernels_type_check_and_lower_for_a_gpu_without_one():
    """Every kernel through numba-cuda's typing and lowering for an H100 (compute capability 9.0), no GPU needed:
    what the simulator, which runs the kernels as Python, cannot check (a type that does not unify, an unsupported
    call)."""
    script = Path(__file__).with_name("cuda_typecheck.py")
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "0"}
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=600)
    lines = proc.stdout.splitlines()
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    if lines and lines[0].startswith("SKIP"):
        pytest.skip(lines[0])
    names = {ln.split()[1] for ln in lines if ln.startswith("OK ")}
    assert names == {"setup_faces", "emit_pairs", "raster_forward", "raster_backward", "setup_backward", "hard_setup",
                     "hard_pixels", "hard_resolve"}, proc.stdout


def test_device_choices_and_the_train_command_without_a_gpu(tmp_path, monkeypatch):
    """--device: cpu -> the Numba kernels; cuda -> the CUDA backend, refused with the reason and the fix when torch
    sees no GPU or numba-cuda is missing; auto -> cpu then. `trisplat train --device cuda` refuses before it touches
    the run folder."""
    import importlib.util as iu

    from trisplat.commands.train import make_train_args, run_training
    from trisplat.render import device as devmod

    assert devmod.resolve_device("cpu") == torch.device("cpu") and devmod.backend_for("cpu") == "numba"
    assert devmod.backend_for(torch.device("cuda", 0)) == "cuda"
    with pytest.raises(ValueError, match="device must be one of"):
        devmod.resolve_device("gpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    find_spec = iu.find_spec
    monkeypatch.setattr(iu, "find_spec", lambda name, *a: None if name == "numba_cuda" else find_spec(name, *a))
    with pytest.raises(ValueError, match="numba-cuda is not installed.*--device cpu.*trisplat\\[gpu\\]"):
        devmod.resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert devmod.resolve_device("auto") == torch.device("cpu")
    with pytest.raises(ValueError, match="torch sees no CUDA device"):
        devmod.resolve_device("cuda")
    out = tmp_path / "run"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    args = make_train_args(tmp_path / "nowhere", out, "fast", force=True)
    args.device = "cuda"
    with pytest.raises(ValueError, match="no CUDA device.*nothing was run"):
        run_training(args)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


@pytest.mark.skipif(not ON_GPU, reason="needs a GPU (torch.cuda.is_available() and numba-cuda, simulator off): the "
                                       "medium scene is far too slow for the CUDA simulator")
def test_cuda_on_a_gpu_matches_numba_on_a_medium_scene():
    """~1,500 random faces of 2-20 px at 160x120 (about 20 faces per pixel) on the GPU against the CPU kernels:
    images, per-face outputs, colour and opacity gradients within GRAD_RTOL; position gradients within GRAD_RTOL for
    all but 0.2% of the vertices (pixel centres that float32 rounding puts on the other side of the alpha_min cut,
    where the window's gradient is singular at sigma < 1), within 10% for those."""
    from trisplat.bench.render import random_triangles

    scene = tuple(torch.as_tensor(np.asarray(a)) for a in random_triangles(1500, 160, 120, (2, 20), seed=3))
    nb, gnb = _render(scene, "numba", {}, 0, width=160, height=120)
    cu, gcu = _render(scene, "cuda", {}, 0, "cuda", width=160, height=120)
    assert not _images_close(nb, cu, atol=1e-4)
    torch.testing.assert_close(cu.max_weight.cpu(), nb.max_weight, atol=1e-4, rtol=0)
    assert abs(cu.faces_visible - nb.faces_visible) <= 2
    assert not [e for e in _grads_close(gnb, gcu) if not e.startswith("positions")]
    scale = gnb[0].abs().max().item()
    err = (gnb[0] - gcu[0]).abs().amax(1) / scale
    assert (err > GRAD_RTOL).float().mean().item() <= 0.002 and err.max().item() <= 0.1
