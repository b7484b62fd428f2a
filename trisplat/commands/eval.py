"""`trisplat eval RUN`: render a run's split, score it (PSNR/SSIM/LPIPS), write metrics.json and report.html."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT, flowing_help


@flowing_help
@dataclass
class EvalConfig:
    """Render a trained run's test (or train) views and write RUN/eval_<split>/metrics.json and report.html."""

    run: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")]
    """run directory written by `trisplat train`"""
    split: Literal["test", "train"] = "test"
    """which views to render"""
    mode: Literal["hard", "soft"] = "hard"
    """hard: the opaque mesh under a z-buffer (what exports show); soft: the training renderer at the run's sigma"""
    out: Annotated[Path | None, NO_DEFAULT_HINT] = None
    """output folder (default RUN/eval_<split>, RUN/eval_<split>_soft in soft mode)"""
    lpips_weights: Annotated[Path | None, NO_DEFAULT_HINT] = None
    """LPIPS .npz (default: $TRISPLAT_LPIPS_WEIGHTS, else ~/.cache/trisplat/lpips_alexnet_full_oihw.npz)"""
    max_views: Annotated[int | None, NO_DEFAULT_HINT] = None
    """evaluate only the first N views of the split (a quick look; default: all)"""
    report: bool = True
    """write report.html (with pictures) next to metrics.json"""
    supersample: Annotated[int | None, NO_DEFAULT_HINT] = None
    """samples per pixel side (anti-aliasing, 1-4; default: the run's eval_supersample, 1 for older runs)"""
    force: bool = False
    """replace an existing evaluation in the output folder (e.g. the one the training wrote)"""
    file: Annotated[Path | None, NO_DEFAULT_HINT] = None
    """score an exported file instead of the model: a .glb (relative paths: in RUN, e.g. mesh.glb) rendered as the
    glTF specification defines it (unlit, base colour texture decoded from sRGB and filtered bilinearly, linear
    COLOR_0, samples averaged in linear light, sRGB output); writes RUN/eval_<split>_file by default"""
    lod: tuple[int, ...] = ()
    """level of detail: export the surface decimated to each of these face counts (e.g. --lod 100000 50000 20000),
    each with a texture re-fitted to the photos, score every GLB as with --file, and add PSNR against face count to
    the report (RUN/eval_<split>_lod/lod.json and psnr_vs_faces.png)"""
    texture_size: Annotated[int | None, NO_DEFAULT_HINT] = None
    """with --lod: texture side of the exported levels (default: the run's texture_size; 0: vertex colours)"""
    up: Literal["auto", "y", "z", "capture"] = "auto"
    """with --file: the up axis the file was exported with (as `trisplat export --up`)"""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """cpu: the run's renderer on the CPU; cuda: the numba-cuda kernels on an NVIDIA GPU (gpu extra and a CUDA build
    of torch; without them: an error naming what is missing, before anything is written); auto: cuda when it can run
    here, else cpu"""


def main(argv: list[str]) -> int:
    cfg = tyro.cli(EvalConfig, args=argv, description=__doc__, prog="trisplat eval", config=CLI_STYLE)
    from trisplat.eval.report import METRICS_JSON, REPORT_HTML, json_safe
    from trisplat.eval.views import evaluate_run
    from trisplat.io.atomic import refuse_to_overwrite
    from trisplat.render.device import resolve_device
    from trisplat.run import open_run

    open_run(cfg.run)  # the input first: a folder that is no run is named as such
    if cfg.lod and cfg.file is not None:
        raise ValueError("--lod exports and scores its own files; it cannot be combined with --file")
    if cfg.lod:
        return _eval_lod(cfg)
    if cfg.file is not None:
        return _eval_file(cfg)
    device = resolve_device(cfg.device)  # before anything is written
    out = cfg.out or cfg.run / (f"eval_{cfg.split}" + ("_soft" if cfg.mode == "soft" else ""))
    refuse_to_overwrite([out / METRICS_JSON, out / REPORT_HTML], cfg.force, "write elsewhere with --out DIR")
    m = evaluate_run(cfg.run, cfg.split, cfg.mode, out_dir=cfg.out, lpips_weights=cfg.lpips_weights,
                     max_views=cfg.max_views, report=cfg.report, supersample=cfg.supersample,
                     device=device)  # fmt: skip
    summary = {k: v for k, v in m.to_dict().items() if k != "views"}
    print(json.dumps(json_safe(summary), indent=2))
    if cfg.report:
        print(f"report: {out / REPORT_HTML}")
    return 0


def _eval_file(cfg: EvalConfig) -> int:
    from trisplat.eval.file_scores import evaluate_file
    from trisplat.eval.report import METRICS_JSON, REPORT_HTML, json_safe
    from trisplat.io.atomic import refuse_to_overwrite

    out = cfg.out or cfg.run / f"eval_{cfg.split}_file"
    refuse_to_overwrite([out / METRICS_JSON, out / REPORT_HTML], cfg.force, "write elsewhere with --out DIR")
    m = evaluate_file(cfg.run, cfg.file, cfg.split, out_dir=out, supersample=cfg.supersample,
                      up=None if cfg.up == "capture" else cfg.up, max_views=cfg.max_views, report=cfg.report,
                      lpips_weights=cfg.lpips_weights)
    summary = {k: v for k, v in m.to_dict().items() if k != "views"}
    print(json.dumps(json_safe(summary), indent=2))
    if cfg.report:
        print(f"report: {out / REPORT_HTML}")
    return 0


def _eval_lod(cfg: EvalConfig) -> int:
    from trisplat.eval.lod import LOD_METRICS, evaluate_lod
    from trisplat.io.atomic import refuse_to_overwrite

    out = cfg.out or cfg.run / f"eval_{cfg.split}_lod"
    refuse_to_overwrite([out / LOD_METRICS], cfg.force, "write elsewhere with --out DIR")
    points = evaluate_lod(cfg.run, cfg.lod, texture_size=cfg.texture_size, split=cfg.split, out_dir=out,
                          supersample=cfg.supersample, max_views=cfg.max_views)
    for p in points:
        print(f"{p.faces:>9} faces  texture {p.texture_size:>5}  {p.glb_bytes / 1e6:7.1f} MB  PSNR {p.psnr:6.2f} dB")
    print(f"levels: {out / LOD_METRICS}")
    return 0
