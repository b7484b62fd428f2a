"""Novel-view evaluation of a trained run: render a split, score every view, write metrics.json and report.html."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from trisplat.eval.image_metrics import psnr, ssim
from trisplat.eval.report import SplitMetrics, ViewImages, ViewMetrics, write_metrics, write_report
from trisplat.progress import progress_bar

MODES = ("hard", "soft")
SPLITS = ("test", "train")
REPORT_MAX_IMAGE_VIEWS = 24  # views whose pictures the report shows (evenly spaced); the table lists all of them
REPORT_SHADED_VIEWS = 4  # of those, views also shown as the bare surface (grey, headlight-lit); one hard render each
SHADED_ALBEDO = 0.8  # grey level of a surface facing the camera
SHADED_AMBIENT = 0.15  # share of the light that does not depend on the angle (grazing faces stay visible)


def soft_sigma(run) -> float:
    """The window sharpness to render a run softly with: the sigma the run had reached (state.json), else the
    config's final sigma. TODO(lead): wire a per-run override here if the trainer records a different evaluation
    sigma."""
    if "sigma" in run.state:
        return float(run.state["sigma"])
    if "sigma_end" in run.config:
        return float(run.config["sigma_end"])
    raise ValueError(f"{run.path}: cannot tell the soft-rendering sigma (no 'sigma' in state.json, no 'sigma_end' "
                     "in config.json)")  # fmt: skip


def eval_supersample(run) -> int:
    """Samples per pixel side a run is scored with (its config's eval_supersample; runs from before that setting
    existed were scored with one sample per pixel)."""
    return int(run.config.get("eval_supersample", 1))


def scene_on(scene, device: torch.device | None):
    """The TriangleScene with its tensors on `device` (the scene itself when they are there already, or for None)."""
    return scene if device is None else scene.to(device)


def render_view(scene, camera, mode: str, background, sigma: float | None = None, options: dict | None = None,
                supersample: int = 1, device: torch.device | str | None = None):
    """Render one camera of a TriangleScene: float32 numpy [H,W,3] in [0,1].

    hard: the opaque z-buffer (rasterize_hard); soft: the training renderer at `sigma` with the vertices' opacities.
    Both evaluate the SH colour of each vertex along its view direction, and blend in linear light where the scene
    says so (TriangleScene.linear_light). options: RenderOptions fields the run
    trained with (near, tile_size, backend); the hard renderer takes only `near` from them. supersample: each
    pixel is the mean of s x s samples (anti-aliasing; 1 = one sample at the pixel centre). device: render with the
    scene's tensors there (None: where they are). The run's kernels follow the tensors: the numba-cuda kernels on a
    GPU, the Numba kernels on the CPU, whichever the run trained with ('reference' stays).
    """
    from trisplat import render
    from trisplat.render.device import backend_for

    options = dict(options or {})
    if device is not None:
        scene = scene_on(scene, torch.device(device))
    if options.get("backend", "numba") != "reference":
        options["backend"] = backend_for(scene.positions.device)
    w2c = torch.as_tensor(camera.world_to_camera, dtype=torch.float32)
    K = torch.as_tensor(camera.K, dtype=torch.float32)
    bg = torch.as_tensor(np.asarray(background, dtype=np.float32))
    faces = scene.faces.to(torch.int32)
    with torch.no_grad():
        if mode == "hard":
            near = {"near": options["near"]} if "near" in options else {}
            out = render.rasterize_hard(scene.positions, faces, scene.sh, w2c, K, camera.width, camera.height, bg,
                                        supersample=supersample, linear_light=scene.linear_light, **near)  # fmt: skip
        elif mode == "soft":
            if sigma is None:
                raise ValueError("soft rendering needs sigma")
            options["supersample"] = supersample
            options["linear_light"] = scene.linear_light
            out = render.rasterize(scene.positions, faces, scene.sh, scene.opacities(), sigma, w2c, K, camera.width,
                                   camera.height, background=bg, **options)  # fmt: skip
        else:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    return out.rgb.clamp(0.0, 1.0).cpu().numpy().astype(np.float32)


def render_shaded(scene, camera, background, near: float = 0.01, supersample: int = 1,
                  device: torch.device | str | None = None) -> np.ndarray:
    """The bare surface of a TriangleScene from `camera`: the opaque z-buffer render (render.rasterize_hard) with
    every face a plain grey lit by a headlight (a light at the camera), so shape shows without colour. float32
    numpy [H,W,3] in [0,1].

    A pixel showing a face with unit normal n along the unit ray direction d from the camera gets
    SHADED_ALBEDO * (SHADED_AMBIENT + (1 - SHADED_AMBIENT) * |n . d|) (Lambert, two-sided); empty pixels get
    `background`. supersample s: shaded at s x s samples per pixel, then averaged (anti-aliased edges). device:
    render with the scene's tensors there (None: where they are).
    """
    from trisplat import render
    from trisplat.render.inputs import check_supersample

    s = check_supersample(supersample)
    W, H = camera.width * s, camera.height * s
    K = np.asarray(camera.K, dtype=np.float64).copy()
    K[:2] *= s
    scene = scene_on(scene, device)
    grey = torch.full((scene.positions.shape[0], 3), 0.5, device=scene.positions.device)
    with torch.no_grad():
        out = render.rasterize_hard(scene.positions, scene.faces.to(torch.int32), grey,
                                    torch.as_tensor(camera.world_to_camera, dtype=torch.float32),
                                    torch.as_tensor(K, dtype=torch.float32), W, H, near=near)
    n = out.normal.cpu().numpy().astype(np.float64)  # unit face normal, camera frame
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    lit = SHADED_ALBEDO * (SHADED_AMBIENT + (1 - SHADED_AMBIENT) * np.abs((n * d).sum(-1)))
    covered = out.alpha.cpu().numpy() > 0.5
    img = np.where(covered[..., None], lit[..., None], np.asarray(background, dtype=np.float64)[None, None, :])
    img = img.reshape(camera.height, s, camera.width, s, 3).mean(axis=(1, 3))
    return img.astype(np.float32)


def _render_options(config: dict) -> dict:
    """Renderer settings the run trained with that also matter at evaluation time."""
    return {k: config[k] for k in ("near", "tile_size", "backend") if k in config}


def evaluate_run(
    run_dir: str | Path,
    split: str = "test",
    mode: str = "hard",
    out_dir: str | Path | None = None,
    lpips_weights: str | Path | None = None,
    max_views: int | None = None,
    report: bool = True,
    show_progress: bool = True,
    supersample: int | None = None,
    device: torch.device | str = "cpu",
) -> SplitMetrics:
    """Render `split` of the run at run_dir, score each view (PSNR, SSIM, LPIPS) and write
    out_dir/metrics.json and out_dir/report.html (out_dir defaults to RUN/eval_<split>; soft mode adds _soft).

    LPIPS is None (with a note in the metrics) when the weights file is missing. max_views: evaluate only the first
    N views of the split (quick looks; the metrics say so). supersample: samples per pixel side (default: the
    run's eval_supersample, eval_supersample(run)); the metrics record it. device: 'cpu', 'cuda', 'auto' (as
    `trisplat eval --device`, resolved by render.device.resolve_device) or a torch device: where the views
    are rendered (on a GPU with the numba-cuda kernels); the metrics record a device other than the CPU.
    """
    from trisplat.eval.lpips import MIN_SIZE_PX as LPIPS_MIN_SIZE_PX
    from trisplat.eval.lpips import load_lpips, lpips
    from trisplat.render.device import resolve_device
    from trisplat.run import open_run

    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    dev = resolve_device(device) if isinstance(device, str) else torch.device(device)
    run = open_run(run_dir)
    out = Path(out_dir) if out_dir is not None else run.path / (f"eval_{split}" + ("_soft" if mode == "soft" else ""))
    scene, _normalization = run.load_model()
    on_dev = scene_on(scene, dev)
    data = run.load_scene_data()
    indices = [int(i) for i in (data.test_indices if split == "test" else data.train_indices)]
    if not indices:
        raise ValueError(f"{run.data_path}: the {split} split of this capture is empty")
    if max_views is not None:
        indices = indices[:max_views]
    sigma = soft_sigma(run) if mode == "soft" else None
    options = _render_options(run.config)
    ss = eval_supersample(run) if supersample is None else int(supersample)

    lpips_note = None
    try:
        load_lpips(lpips_weights)
    except FileNotFoundError as exc:
        lpips_note = str(exc)
    small = [i for i in indices if min(data.cameras[i].width, data.cameras[i].height) < LPIPS_MIN_SIZE_PX]
    if lpips_note is None and small:
        c = data.cameras[small[0]]
        lpips_note = (f"LPIPS-AlexNet needs images of at least {LPIPS_MIN_SIZE_PX}x{LPIPS_MIN_SIZE_PX} px; "
                      f"{len(small)} view(s) of this split are smaller (e.g. {c.width}x{c.height})")
    shown = set(np.linspace(0, len(indices) - 1, min(len(indices), REPORT_MAX_IMAGE_VIEWS)).round().astype(int))
    shaded = set(sorted(shown)[:: max(1, -(-len(shown) // REPORT_SHADED_VIEWS))][:REPORT_SHADED_VIEWS]) if report \
        else set()

    from trisplat.train.exposure import apply_correction, load_saved, neighbour_correction

    corrections = load_saved(run.path, len(data.cameras))  # None unless the run learned per-photo colour
    views: list[ViewMetrics] = []
    images: list[ViewImages] = []
    render_s = 0.0
    bar = progress_bar(indices, desc=f"eval {split} ({mode})", unit="view", disable=not show_progress)
    for k, i in enumerate(bar):
        cam = data.cameras[i]
        t0 = time.perf_counter()
        rgb = render_view(on_dev, cam, mode, data.background, sigma, options, ss, device=dev)
        render_s += time.perf_counter() - t0
        gt = np.asarray(data.load_image(i), dtype=np.float32)
        if gt.shape != rgb.shape:
            raise ValueError(f"camera {cam.name or i}: ground truth {gt.shape} and render {rgb.shape} differ")
        name = cam.name or f"view_{i:04d}"
        lp = lpips(gt, rgb, lpips_weights) if lpips_note is None else None
        matched = None if corrections is None else psnr(gt, apply_correction(rgb, neighbour_correction(
            *corrections, i)).astype(np.float32))
        views.append(ViewMetrics(index=i, name=name, psnr=psnr(gt, rgb), ssim=ssim(gt, rgb), lpips=lp,
                                 psnr_exposure_matched=matched))
        bar.set_postfix(psnr=f"{np.mean([v.psnr for v in views]):.2f}")
        if k in shown:
            surface = render_shaded(on_dev, cam, data.background, options.get("near", 0.01), ss) \
                if k in shaded else None
            images.append(ViewImages(name=name, gt=gt, render=rgb, shaded=surface))

    history = run.history()
    extra = {"run": str(run.path), "step": run.state.get("step"), "finished": run.state.get("finished"),
             "train_wall_s": _last(history, "wall_s"), "faces": scene.num_faces,
             "vertices": scene.num_vertices, "supersample": ss}  # fmt: skip
    if corrections is not None:
        extra["psnr_exposure_matched"] = float(np.mean([v.psnr_exposure_matched for v in views]))
        extra["exposure_matched"] = ("PSNR of each render with the colour correction (exposure, white balance) "
                                     + ("its photo had in training" if split == "train" else
                                        "interpolated between the training photos before and after it in the "
                                        "photo order: no pixel of the held-out photo is used")
                                     + "; psnr is the scene's own colour")
    if sigma is not None:
        extra["sigma"] = sigma
    if max_views is not None:
        extra["max_views"] = max_views
    if dev.type != "cpu":
        extra["device"] = str(dev)
    metrics = SplitMetrics(split=split, mode=mode, views=views, lpips_note=lpips_note, render_seconds=render_s,
                           extra=extra)  # fmt: skip
    write_metrics(out, metrics)
    if report:
        write_report(out, metrics, images, history=history,
                     mesh_stats=mesh_statistics_or_none(scene), config=run.config,
                     title=f"trisplat: {run.path.name} ({split}, {mode}, {ss}x{ss} samples per pixel)")  # fmt: skip
    return metrics


def _last(history: list[dict], key: str):
    vals = [h[key] for h in history if key in h]
    return vals[-1] if vals else None


def mesh_statistics_or_none(scene):
    """trisplat.mesh.stats.mesh_statistics of the scene's triangles, or None when that module is not available."""
    try:
        from trisplat.mesh.stats import mesh_statistics
    except ImportError:
        return None
    return mesh_statistics(scene.positions.detach().cpu().numpy(), scene.faces.detach().cpu().numpy())
