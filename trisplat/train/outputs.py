"""What a finished run leaves behind: model.ply, mesh.{ply,obj,glb}, test renders, the eval report, metrics.json."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from trisplat import run as layout
from trisplat.io.atomic import atomic_write_text
from trisplat.scene.sh import sh_dc_to_rgb

MESH_FORMATS = ("ply", "obj", "glb")


def image_stem(camera, index: int) -> str:
    """Output name of a render: the source photo's stem (never the cached copy's), so anyone can pair it with the
    ground truth."""
    return camera.stem or f"view_{index:04d}"


def output_stems(cameras, indices) -> dict[int, str]:
    """index -> output file stem for renders of views `indices`: the source photo's stem; views whose photos share
    a stem (a Blender capture's train/r_0.png and test/r_0.png) are named by their relative path instead
    (train_r_0, test_r_0)."""
    stems = {int(i): image_stem(cameras[int(i)], int(i)) for i in indices}
    counts: dict[str, int] = {}
    for s in stems.values():
        counts[s] = counts.get(s, 0) + 1
    for i, s in stems.items():
        if counts[s] > 1 and cameras[i].name:
            stems[i] = str(Path(cameras[i].name).with_suffix("")).replace("/", "_").replace("\\", "_")
    return stems


def write_model_files(run_dir: Path, scene, normalization: np.ndarray, capture_up: np.ndarray | None = None,
                      asset=None) -> None:
    """model.ply (every SH band and opacity, reloadable) and the opaque mesh in the capture's frame (mesh.glb
    turned so that `capture_up`, the capture's up direction, is +Y, as glTF defines; see io.export_mesh).
    asset: a trisplat.texture.asset.MeshAsset (decimated and/or textured) to write instead of the scene's mesh
    with its SH band 0 as vertex colours."""
    from trisplat.io import export_mesh, save_model_ply

    save_model_ply(run_dir / layout.MODEL, scene, normalization)
    if asset is None:
        positions, faces = scene.positions.numpy(), scene.faces.numpy()
        colors, texture = sh_dc_to_rgb(scene.sh[:, 0]).clamp(0, 1).numpy(), None
    else:
        positions, faces, colors, texture = asset.positions, asset.faces, asset.colors, asset.texture
    to_capture = np.linalg.inv(normalization)
    for suffix in MESH_FORMATS:
        export_mesh(run_dir / f"mesh.{suffix}", positions, faces, colors, transform=to_capture,
                    capture_up=capture_up, texture=texture)


def write_outputs(trainer, pruned) -> dict:
    """Everything a finished run leaves in RUN/ (see trisplat/run.py); returns the metrics written.

    The test split is scored with the opaque mesh (hard z-buffer render, the deliverable) and with the soft
    renderer at the final sigma, so the gap between them is on record; both at cfg.eval_supersample samples per
    pixel side, the hard render also at one sample per pixel, on the trainer's device (the GPU's kernels give the
    same images within float32 rounding); the files are written from the scene on the CPU.
    """
    from trisplat.eval.report import write_png
    from trisplat.eval.views import evaluate_run, render_view

    run_dir, data, cfg = trainer.run_dir, trainer.data, trainer.cfg
    scene = trainer.ts.to_scene().to("cpu")
    dev = trainer.device
    normalization = np.asarray(data.normalization, dtype=np.float64)
    from trisplat.io import capture_up

    from trisplat.texture.asset import build_asset

    asset = build_asset(scene, data, texture_size=int(getattr(cfg, "texture_size", 0) or 0),
                        faces=getattr(cfg, "export_faces", None), supersample=cfg.eval_supersample, near=cfg.near,
                        fit_colours=bool(getattr(cfg, "fit_colours", True)))
    write_model_files(run_dir, scene, normalization,
                      capture_up(data), asset)
    from trisplat.texture.asset import choice_message

    if trainer.show_progress and (msg := choice_message(asset.texture_report)) is not None:
        print(msg, file=sys.stderr, flush=True)
    # state.json stays "unfinished" until metrics.json exists, so a crash here is redone by --resume

    renders = run_dir / layout.RENDERS
    renders.mkdir(exist_ok=True)
    shown = [int(i) for i in list(data.test_indices)[: cfg.num_renders]]
    for i, stem in output_stems(data.cameras, shown).items():
        write_png(render_view(scene, data.cameras[i], "hard", cfg.background, supersample=cfg.eval_supersample),
                  renders / f"{stem}.png")

    metrics: dict = {}
    if len(data.test_indices):
        ss = cfg.eval_supersample  # explicit: a config.json written before this setting existed does not name it
        hard = evaluate_run(run_dir, "test", "hard", show_progress=False, supersample=ss, device=dev)
        soft = evaluate_run(run_dir, "test", "soft", report=False, show_progress=False, supersample=ss, device=dev)
        metrics.update({"psnr": hard.psnr, "ssim": hard.ssim, "lpips": hard.lpips, "lpips_net": "alex-v0.1",
                        "soft_psnr": soft.psnr, "soft_ssim": soft.ssim, "test_views": len(hard.views),
                        "supersample": ss, "report": str(Path("eval_test") / "report.html")})
        if "psnr_exposure_matched" in hard.extra:  # a capture whose photos got colour corrections
            metrics["psnr_exposure_matched"] = hard.extra["psnr_exposure_matched"]
        if cfg.eval_supersample != 1:  # the same mesh with one sample per pixel centre (aliased edges), on record
            one = evaluate_run(run_dir, "test", "hard", out_dir=run_dir / "eval_test_1spp", report=False,
                               show_progress=False, supersample=1, device=dev)
            metrics.update({"psnr_1spp": one.psnr, "ssim_1spp": one.ssim, "lpips_1spp": one.lpips})
        metrics.update(_score_file(run_dir, data, ss, hard))
    if asset.texture_report is not None:
        metrics["texture"] = asset.texture_report
    if asset.colour_report is not None:
        metrics["vertex_colours"] = asset.colour_report
    metrics["file_faces"] = int(len(asset.faces))
    opac = scene.opacities()
    metrics.update({
        "render_mode": "hard",
        "faces": scene.num_faces, "vertices": scene.num_vertices,
        "vertex_face_ratio": scene.num_vertices / max(scene.num_faces, 1),
        "min_vertex_opacity": float(opac.min()) if opac.numel() else None,
        "sigma_end": cfg.sigma_end, "opacity_floor": scene.opacity_floor,
        "steps": trainer.step, "wall_s": trainer.wall_s,
        "final_prune": None if pruned is None else {"faces_removed": pruned.faces_removed,
                                                    "vertices_removed": pruned.vertices_removed},
        "output": cfg.output, "connected": bool(trainer.connected),
        "switch_failed": bool(getattr(trainer, "switch_failed", False)),
        "surface_pass": getattr(trainer, "surface_pass", None),
        "mesh": _mesh_summary(scene),
    })
    atomic_write_text(run_dir / layout.METRICS, json.dumps(metrics, indent=2))
    return metrics


def _mesh_summary(scene) -> dict:
    """`trisplat mesh-stats` of the mesh as exported (per-vertex rows as stored; a soup's corners are not welded)."""
    from trisplat.mesh.stats import mesh_statistics

    st = mesh_statistics(scene.positions.numpy(), scene.faces.numpy()).to_dict()
    keep = ("vertex_face_ratio", "connected_components", "largest_component_fraction", "boundary_edges",
            "non_manifold_edges", "self_intersecting_edges", "valence_mean", "watertight", "consistently_oriented")
    return {k: st[k] for k in keep}


def _score_file(run_dir: Path, data, supersample: int, model) -> dict:
    """mesh.glb scored as a glTF viewer shows it (trisplat.eval.file_scores), beside the model's scores; the model's
    report gets a table of both."""
    from trisplat.eval.file_scores import evaluate_file
    from trisplat.eval.report import add_file_scores

    f = evaluate_file(run_dir, run_dir / "mesh.glb", "test", supersample=supersample, show_progress=False, data=data)
    add_file_scores(run_dir / "eval_test" / "report.html", model, f, "../eval_test_file/report.html")
    return {"file_psnr": f.psnr, "file_ssim": f.ssim, "file_lpips": f.lpips, "file": "mesh.glb",
            "file_report": str(Path("eval_test_file") / "report.html")}
