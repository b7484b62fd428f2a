"""The Warp backend (backend="warp") against the dense reference (forward values and every gradient, on the awkward
scenes of the Numba tests) and against the Numba kernels (a medium scene, soft and hard). In CI these run on Warp's
CPU device (single-threaded: scenes stay small); on a machine with CUDA the device test runs too."""
from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from render_scenes import mesh_scene, random_scene
from test_render_hard import brute_force
from test_render_numba import BOUNDARY_FRACTION, GRAD_RTOL, IMG_ATOL, SCENES, SIGMA

from trisplat.render import rasterize, rasterize_hard
from trisplat.render.warp_backend import INSTALL_HINT, available

needs_warp = pytest.mark.skipif(not available(), reason="warp-lang is not installed (pip install 'trisplat[gpu]'); "
                                                        "the Warp backend tests need it")
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _render(scene, backend, opts, weights_seed, device="cpu", W=40, H=32):
    """Render with `backend`, back-propagate a fixed random linear loss on rgb, alpha, depth and normal."""
    pos, faces, col, op, w2c, K = (t.to(device) for t in scene)
    P = [pos.clone().requires_grad_(), col.clone().requires_grad_(), op.clone().requires_grad_()]
    out = rasterize(P[0], faces, P[1], P[2], SIGMA, w2c, K, W, H, backend=backend, **opts)
    g = torch.Generator().manual_seed(weights_seed)
    loss = sum((t * (torch.rand(t.shape, generator=g, dtype=t.dtype).to(device) - 0.3)).sum()
               for t in (out.rgb, out.alpha, out.depth, out.normal))
    loss.backward()
    return out, [p.grad for p in P]


def _assert_images_close(a, b, atol=IMG_ATOL, fraction=BOUNDARY_FRACTION):
    for name in ("rgb", "alpha", "depth", "normal"):
        x, y = getattr(a, name).detach().cpu(), getattr(b, name).detach().cpu()
        bad = (x - y).abs() > atol
        if bad.ndim == 3:
            bad = bad.any(-1)
        assert bad.float().mean().item() <= fraction, f"{name}: {int(bad.sum())} pixels differ by more than {atol}"


def _assert_grads_close(ga, gb, rtol=GRAD_RTOL, names=("positions", "colors", "opacities")):
    for name, a, b in zip(names, ga, gb):
        a, b = a.cpu(), b.cpu()
        scale = a.abs().max().item()
        assert scale > 0, f"{name}: no gradient"
        err = (a - b).abs().max().item()
        assert err <= rtol * scale, f"{name}: max error {err:.3g} vs scale {scale:.3g}"


@needs_warp
@pytest.mark.parametrize("seed,kind,opts", SCENES)
def test_warp_matches_reference_forward_and_backward(seed, kind, opts):
    """Same scenes, loss and tolerances as the Numba test: images within IMG_ATOL except boundary pixels, per-face
    max weight within IMG_ATOL, face_id, and each gradient within GRAD_RTOL of its largest entry."""
    scene = {"soup": lambda: random_scene(seed, 30), "deep": lambda: random_scene(seed, 200, opacity_range=(0.6, 0.95)),
             "mesh": lambda: mesh_scene(seed)}[kind]()
    ref, gref = _render(scene, "reference", opts, seed)
    wa, gwa = _render(scene, "warp", opts, seed)
    _assert_images_close(ref, wa)
    torch.testing.assert_close(wa.max_weight, ref.max_weight, atol=IMG_ATOL, rtol=0)
    assert (wa.face_id != ref.face_id).float().mean().item() <= BOUNDARY_FRACTION
    _assert_grads_close(gref, gwa)
    assert wa.rgb.dtype == ref.rgb.dtype and wa.rgb.device == ref.rgb.device


GRAD_OUTLIER_FRACTION = 0.002  # vertices whose position gradient may differ more than GRAD_RTOL (see below)
GRAD_OUTLIER_RTOL = 0.1


@needs_warp
def test_warp_matches_numba_on_a_medium_scene():
    """~1,500 random faces of 2-20 px at 160x120 (about 20 faces per pixel): forward images, per-face outputs and
    gradients of the two float32 backends agree. Colour and opacity gradients within GRAD_RTOL everywhere; position
    gradients within GRAD_RTOL for all but GRAD_OUTLIER_FRACTION of the vertices (and within GRAD_OUTLIER_RTOL for
    those): at sigma < 1, dI/dphi ~ ratio^(sigma - 1) is singular at the edges and alpha jumps at alpha_min, so a
    pixel centre that one float32 rounding puts on the other side of the cut changes its faces' position gradient
    by a few percent. (With alpha_min = 0 the largest difference on this scene drops from 2.8% to 1.8%.)"""
    from trisplat.bench.render import random_triangles

    pos, faces, col, op, w2c, K = random_triangles(1500, 160, 120, (2, 20), seed=3)
    scene = tuple(torch.as_tensor(np.asarray(a)) for a in (pos, faces, col, op, w2c, K))
    nb, gnb = _render(scene, "numba", {}, 0, W=160, H=120)
    wa, gwa = _render(scene, "warp", {}, 0, W=160, H=120)
    _assert_images_close(nb, wa, atol=1e-4)
    torch.testing.assert_close(wa.max_weight, nb.max_weight, atol=1e-4, rtol=0)
    assert (wa.face_id != nb.face_id).float().mean().item() <= BOUNDARY_FRACTION
    assert abs(wa.faces_visible - nb.faces_visible) <= 2  # borderline-degenerate faces
    _assert_grads_close(gnb[1:], gwa[1:], names=("colors", "opacities"))
    a, b = gnb[0], gwa[0]
    scale = a.abs().max().item()
    err = (a - b).abs().amax(1) / scale
    assert (err > GRAD_RTOL).float().mean().item() <= GRAD_OUTLIER_FRACTION, f"{int((err > GRAD_RTOL).sum())} vertices"
    assert err.max().item() <= GRAD_OUTLIER_RTOL


@needs_warp
def test_warp_batched_float32_and_empty_inputs():
    pos, faces, col, op, w2c, K = random_scene(13, 20)
    w2c2 = w2c.clone()
    w2c2[:3, 3] = torch.tensor([0.1, -0.05, 0.2], dtype=w2c.dtype)
    both = rasterize(pos.float(), faces, col.float(), op.float(), SIGMA, torch.stack([w2c, w2c2]), K, 40, 32,
                     backend="warp")
    assert both.rgb.dtype == torch.float32 and both.rgb.shape == (2, 32, 40, 3)
    for i, m in enumerate((w2c, w2c2)):
        one = rasterize(pos, faces, col, op, SIGMA, m, K, 40, 32)  # numba, float64 inputs
        torch.testing.assert_close(both.rgb[i].double(), one.rgb, atol=IMG_ATOL, rtol=0)
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    none = rasterize(pos, faces[:0], col, op, SIGMA, w2c, K, 40, 32, bg, backend="warp")
    torch.testing.assert_close(none.rgb, bg.expand(32, 40, 3))
    assert none.faces_visible == 0 and none.pairs_evaluated == 0 and (none.face_id == -1).all()
    behind = pos.clone()
    behind[:, 2] = -1.0  # every face behind the camera: no pairs at all
    out = rasterize(behind.requires_grad_(), faces, col, op, SIGMA, w2c, K, 40, 32, bg, backend="warp")
    out.rgb.sum().backward()
    torch.testing.assert_close(out.rgb, bg.expand(32, 40, 3).to(out.rgb.dtype))
    assert behind.grad is not None and behind.grad.abs().max().item() == 0


@needs_warp
def test_warp_hard_matches_brute_force_and_numba():
    """Random scenes with awkward faces and a deep scene (~30 layers): the nearest face at each pixel centre, its
    colour and depth, as the brute-force z-buffer; max_weight marks the winners; Numba and Warp agree."""
    for seed, n, W, H in ((0, 40, 40, 32), (11, 3000, 64, 48)):
        pos, faces, col, _, w2c, K = random_scene(seed, n, W, H, kinds=seed == 0)
        out = rasterize_hard(pos, faces, col, w2c, K, W, H, backend="warp")
        fid, rgb, depth = brute_force(pos.numpy(), faces.numpy(), col.numpy(), w2c.numpy(), K.numpy(), W, H)
        same = out.face_id.numpy() == fid
        assert same.mean() >= 1 - 0.02 and (fid >= 0).sum() > 300
        np.testing.assert_allclose(out.rgb.numpy()[same], rgb[same], atol=1e-4)
        np.testing.assert_allclose(out.depth.numpy()[same], depth[same], rtol=1e-4)
        assert torch.equal(out.alpha, (out.face_id >= 0).to(out.alpha.dtype))
        winners = np.zeros(faces.shape[0])
        winners[out.face_id.numpy()[out.face_id.numpy() >= 0]] = 1
        np.testing.assert_array_equal(out.max_weight.numpy(), winners)
        nb = rasterize_hard(pos, faces, col, w2c, K, W, H)
        assert (nb.face_id == out.face_id).float().mean().item() >= 1 - 0.02
        torch.testing.assert_close(nb.normal[same], out.normal[same], atol=1e-4, rtol=0)
    # the early stop (faces sorted by nearest vertex) skips most of the deep scene's layers
    assert out.pairs_evaluated < 0.5 * (fid >= 0).sum() * 30


@needs_warp
def test_warp_hard_supersampled_batched_sh_and_perspective():
    from trisplat.scene.sh import rgb_to_sh_dc

    pos, faces, col, _, w2c, K = random_scene(5, 40)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    for kw in ({"supersample": 2}, {"perspective_correct": True}):
        nb = rasterize_hard(pos, faces, col, w2c, K, 40, 32, bg, **kw)
        wa = rasterize_hard(pos, faces, col, w2c, K, 40, 32, bg, backend="warp", **kw)
        close = (nb.rgb - wa.rgb).abs().amax(-1) < 1e-4
        assert close.float().mean().item() >= 1 - 0.04
    b = rasterize_hard(pos, faces, rgb_to_sh_dc(col)[:, None], torch.stack([w2c, w2c]), K, 40, 32, bg, backend="warp")
    a = rasterize_hard(pos, faces, col, w2c, K, 40, 32, bg, backend="warp")
    torch.testing.assert_close(b.rgb[1], a.rgb, atol=1e-5, rtol=0)
    assert torch.equal(b.face_id[0], a.face_id)
    with pytest.raises(ValueError, match="backend"):
        rasterize_hard(pos, faces, col, w2c, K, 40, 32, backend="cuda")


def _cuda_devices() -> int:
    """CUDA devices Warp sees (public API; 0 without warp-lang)."""
    if not available():
        return 0
    import warp as wp

    return int(wp.get_cuda_device_count())


@needs_warp
@pytest.mark.skipif(_cuda_devices() == 0 or not torch.cuda.is_available(),
                    reason="needs a CUDA device seen by both Warp (warp.get_cuda_device_count() = "
                           f"{_cuda_devices()}) and torch (torch.cuda.is_available() = {torch.cuda.is_available()}); "
                           "the CPU-device tests cover the maths")
def test_warp_on_cuda_tensors_stays_on_the_device_and_matches_the_cpu_device():
    scene = random_scene(0, 30)
    cpu, gcpu = _render(scene, "warp", {}, 0)
    gpu, ggpu = _render(scene, "warp", {}, 0, device="cuda")
    assert gpu.rgb.device.type == "cuda" and gpu.face_id.device.type == "cuda" and ggpu[0].device.type == "cuda"
    _assert_images_close(cpu, gpu, atol=1e-5)
    _assert_grads_close(gcpu, ggpu, rtol=1e-4)
    hard = rasterize_hard(*(t.cuda() for t in (scene[0], scene[1], scene[2], scene[4], scene[5])), 40, 32,
                          backend="warp")
    assert hard.rgb.device.type == "cuda"


def test_missing_warp_fails_with_an_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "warp", None)  # import warp -> ImportError
    pos, faces, col, op, w2c, K = random_scene(0, 5, kinds=False)
    with pytest.raises(ImportError, match="trisplat\\[gpu\\]"):
        rasterize(pos, faces, col, op, SIGMA, w2c, K, 40, 32, backend="warp")
    assert "warp-lang" in INSTALL_HINT


def test_device_choices_resolve_to_torch_devices_and_backends(monkeypatch):
    from trisplat.render.warp_backend import backend_for, resolve_device

    assert resolve_device("cpu") == torch.device("cpu") and backend_for(torch.device("cpu")) == "numba"
    assert backend_for(torch.device("cuda", 0)) == "warp"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(ValueError, match="no CUDA device"):
        resolve_device("cuda")
    with pytest.raises(ValueError, match="device must be one of"):
        resolve_device("gpu")


@needs_warp
def test_training_with_the_warp_backend_follows_the_numba_run(tmp_path, monkeypatch):
    """30 steps of the trainer on a tiny generated scene (densify and prune included) with backend='warp' and with
    'numba' from the same start: the per-step losses and the final hard-render PSNR agree closely (the two float32
    backends differ by rounding only). The warp run's SH colour and photometric loss are the Warp kernels (on CPU
    tensors too), the numba run's are not."""
    import json

    import trimesh

    from trisplat import run as layout
    from trisplat.data import load_dataset
    from trisplat.scene import warp_sh
    from trisplat.scene.init import init_soup
    from trisplat.synth import demo_mesh, write_blender_scene
    from trisplat.train import warp_ssim
    from trisplat.train.config import make_config
    from trisplat.train.trainer import Trainer

    calls = {"sh": 0, "loss": 0}
    sh_fwd, loss_fn = warp_sh.WarpSH.forward, warp_ssim.loss_and_grad_warp

    def count(key, fn):
        def wrapped(*a):
            calls[key] += 1
            return fn(*a)
        return wrapped

    monkeypatch.setattr(warp_sh.WarpSH, "forward", staticmethod(count("sh", sh_fwd)))
    monkeypatch.setattr(warp_ssim, "loss_and_grad_warp", count("loss", loss_fn))

    scene_dir = write_blender_scene(tmp_path / "scene", demo_mesh(), n_train=6, n_test=2, width=40, height=40,
                                    samples_per_pixel=1, n_points=0)
    res = {}
    for backend in ("numba", "warp"):
        cfg = make_config("fast", steps=30, sh_degree=1, max_vertices=3000, eval_every=1.0, eval_max_views=2,
                          log_every=1, checkpoint_every_s=1e9, num_renders=0, prune_from=0.6, lr_sh_dc=0.02,
                          lr_opacity=0.05, output="soup", backend=backend)
        opts = {"downscale": 1, "background": list(cfg.background)}
        data = load_dataset(scene_dir, **opts)
        pts, _ = trimesh.sample.sample_surface(demo_mesh(), 400, seed=0)
        pts = (np.c_[pts, np.ones(len(pts))] @ data.normalization.T)[:, :3]
        initial, _ = init_soup(pts, np.full((len(pts), 3), 0.5), seed=0, sh_degree=cfg.sh_degree)
        run = tmp_path / backend
        before = dict(calls)
        Trainer(cfg, data, run, initial=initial, show_progress=False, data_options=opts,
                data_path=str(scene_dir)).train()
        used = {k: calls[k] - before[k] for k in calls}
        if backend == "warp":  # every step (and the warm-up) renders SH colours and takes the loss once
            assert used["sh"] > 30 and used["loss"] > 30, used
        else:
            assert used == {"sh": 0, "loss": 0}, used
        hist = [json.loads(line) for line in (run / layout.HISTORY).read_text().splitlines()]
        res[backend] = (np.array([h["loss"] for h in hist if "loss" in h]),
                        json.loads((run / layout.METRICS).read_text())["psnr"])
    (ln, pn), (lw, pw) = res["numba"], res["warp"]
    assert len(ln) == len(lw) == 30
    np.testing.assert_allclose(lw, ln, rtol=1e-3)
    assert abs(pw - pn) < 0.05


@needs_warp
def test_bench_render_case_runs_with_the_warp_backend():
    """`trisplat bench render --backend warp` measures one case (the per-case worker, small): the pair and visible
    counts it reports are the Warp renderer's on that case's scene, and as many faces are visible as with Numba."""
    from trisplat.bench.render import _run_case, random_triangles

    row = _run_case(64, 48, 300, 2, 20, False, 1, 0.5, backend="warp", device="cpu")
    pos, faces, col, op, w2c, K = (torch.as_tensor(np.asarray(a)) for a in random_triangles(300, 64, 48, (2, 20)))
    with torch.no_grad():
        wa = rasterize(pos, faces, col, op, 0.5, w2c, K, 64, 48, backend="warp")
        nb = rasterize(pos, faces, col, op, 0.5, w2c, K, 64, 48, backend="numba")
    assert row["pairs"] == wa.pairs_evaluated and row["visible"] == wa.faces_visible
    assert abs(wa.faces_visible - nb.faces_visible) <= 2 and nb.faces_visible > 250  # borderline-degenerate faces
    # every pixel-face pair Numba evaluates lies in Warp's bins too (Warp's are coarser)
    assert nb.pairs_evaluated <= wa.pairs_evaluated <= 300 * 64 * 48
    assert all(np.isfinite(row[k]) and row[k] > 0 for k in ("fwd_ms", "fwd_bwd_ms", "hard_ms"))


def test_train_command_refuses_cuda_without_a_gpu_before_touching_the_run(tmp_path, monkeypatch):
    from trisplat.commands.train import make_train_args, run_training

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    out = tmp_path / "run"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    args = make_train_args(tmp_path / "nowhere", out, "fast", force=True)
    args.device = "cuda"
    with pytest.raises(ValueError, match="no CUDA device"):
        run_training(args)
    assert (out / "keep.txt").exists()


def _nvrtc_archs() -> list[int]:
    """The CUDA architectures Warp's NVRTC can compile for (public API; [] for a Warp built without CUDA)."""
    if not available():
        return []
    import warp as wp

    return list(wp.get_cuda_supported_archs())


@needs_warp
@pytest.mark.skipif(90 not in _nvrtc_archs(), reason=f"Warp's NVRTC cannot target sm_90 here: "
                    f"warp.get_cuda_supported_archs() = {_nvrtc_archs()} (a Warp build without CUDA)")
def test_warp_kernels_compile_for_cuda_without_a_gpu(tmp_path):
    """The same kernels through Warp's CUDA code generation and NVRTC, to H100 (sm_90) PTX: no GPU needed, so the
    CUDA path is at least compiled on every CI run even where it cannot be executed."""
    import warp as wp

    from trisplat.render import warp_kernels

    paths = wp.compile_aot_module(warp_kernels, arch=90, module_dir=tmp_path, use_ptx=True)
    ptx = [p for p in paths if str(p).endswith(".ptx")]
    assert ptx and ptx[0].stat().st_size > 10_000
    text = ptx[0].read_text()
    for name in ("raster_forward", "raster_backward", "setup_backward", "hard_pixels"):
        assert name in text
