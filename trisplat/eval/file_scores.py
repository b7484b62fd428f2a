"""Score an exported file, not the model: render RUN/mesh.glb (or any GLB placed in the run's frame) as the glTF
specification defines it (trisplat.eval.spec_render) from the run's cameras and compare with the photos."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from trisplat.eval.image_metrics import psnr, ssim
from trisplat.eval.report import SplitMetrics, ViewImages, ViewMetrics, write_metrics, write_report
from trisplat.progress import progress_bar

FILE_MODE = "file"
REPORT_MAX_IMAGE_VIEWS = 12


def file_to_normalized(run, data, path: str | Path, up: str | None = "auto") -> np.ndarray:
    """[4,4] from the file's frame to the run's normalised training frame: the inverse of what the export applied
    (io.export_mesh: the inverse normalisation, then the up rotation of io.axes for `up`, 'auto' = Y-up for GLB)."""
    from trisplat.io.axes import capture_up as capture_up_of, up_rotation
    from trisplat.io.mesh_files import resolve_up

    up = resolve_up(up, path)
    capture_up = capture_up_of(data) if up is not None else None
    to_file = up_rotation(up, capture_up) @ np.linalg.inv(np.asarray(data.normalization, np.float64))
    return np.linalg.inv(to_file)


def evaluate_file(run_dir: str | Path, file: str | Path = "mesh.glb", split: str = "test", out_dir: str | Path | None = None,
                  supersample: int | None = None, up: str | None = "auto", max_views: int | None = None,
                  report: bool = True, show_progress: bool = True, lpips_weights: str | Path | None = None,
                  data=None) -> SplitMetrics:
    """Render `file` (a .glb; relative paths are taken in the run folder) per the glTF specification from every
    view of `split` and score it. Writes out_dir/metrics.json (mode 'file') and report.html (default
    RUN/eval_<split>_file). supersample: samples per pixel side (default: the run's eval_supersample)."""
    from trisplat.eval.lpips import MIN_SIZE_PX, load_lpips, lpips
    from trisplat.eval.spec_render import prepare_asset, render_asset
    from trisplat.eval.views import eval_supersample
    from trisplat.io.gltf import read_glb
    from trisplat.run import open_run

    run = open_run(run_dir)
    path = Path(file)
    if not path.is_absolute() and not path.exists():
        path = run.path / path
    if path.suffix.lower() != ".glb":
        raise ValueError(f"{path}: only .glb files are scored by the specification renderer")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    out = Path(out_dir) if out_dir is not None else run.path / f"eval_{split}_file"
    data = run.load_scene_data() if data is None else data
    asset = prepare_asset(read_glb(path), file_to_normalized(run, data, path, up))
    indices = [int(i) for i in (data.test_indices if split == "test" else data.train_indices)]
    if max_views is not None:
        indices = indices[:max_views]
    if not indices:
        raise ValueError(f"{run.data_path}: the {split} split of this capture is empty")
    ss = eval_supersample(run) if supersample is None else int(supersample)
    near = float(run.config.get("near", 0.01))
    lpips_note = None
    try:
        load_lpips(lpips_weights)
    except FileNotFoundError as exc:
        lpips_note = str(exc)
    if lpips_note is None and any(min(data.cameras[i].width, data.cameras[i].height) < MIN_SIZE_PX for i in indices):
        lpips_note = f"views smaller than LPIPS-AlexNet's {MIN_SIZE_PX}x{MIN_SIZE_PX} px minimum"
    shown = set(np.linspace(0, len(indices) - 1, min(len(indices), REPORT_MAX_IMAGE_VIEWS)).round().astype(int))
    views, images, render_s = [], [], 0.0
    for k, i in enumerate(progress_bar(indices, desc=f"eval {split} ({path.name})", unit="view", disable=not show_progress)):
        cam = data.cameras[i]
        t0 = time.perf_counter()
        rgb = render_asset(asset, cam.world_to_camera, cam.K, cam.width, cam.height, data.background, ss, near)
        render_s += time.perf_counter() - t0
        gt = np.asarray(data.load_image(i), dtype=np.float32)
        name = cam.name or f"view_{i:04d}"
        lp = lpips(gt, rgb, lpips_weights) if lpips_note is None else None
        views.append(ViewMetrics(index=i, name=name, psnr=psnr(gt, rgb), ssim=ssim(gt, rgb), lpips=lp))
        if report and k in shown:
            images.append(ViewImages(name=name, gt=gt, render=rgb))
    extra = {"file": str(path), "renderer": "glTF 2.0 specification, unlit, bilinear base level, sRGB",
             "supersample": ss, "faces": int(len(asset.faces)), "vertices": int(len(asset.positions)),
             "textured": any(t is not None for t in asset.texture)}
    if asset.lit_materials:
        extra["note"] = f"{asset.lit_materials} primitive(s) without KHR_materials_unlit were rendered unlit"
    if max_views is not None:
        extra["max_views"] = max_views
    metrics = SplitMetrics(split=split, mode=FILE_MODE, views=views, lpips_note=lpips_note, render_seconds=render_s,
                           extra=extra)
    write_metrics(out, metrics)
    if report:
        write_report(out, metrics, images, title=f"trisplat: {path.name} of {run.path.name} as a glTF viewer shows it "
                                                 f"({split}, {ss}x{ss} samples per pixel)")
    return metrics
