"""What a finished run leaves behind: model.ply, mesh.{ply,obj,glb}, test renders and metrics.json."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from trisplat import run as layout
from trisplat.render import rasterize_hard
from trisplat.scene.sh import sh_dc_to_rgb


def to_png(img: torch.Tensor | np.ndarray, path: Path) -> None:
    arr = img.detach().cpu().numpy() if torch.is_tensor(img) else np.asarray(img)
    Image.fromarray((np.clip(arr, 0, 1) * 255 + 0.5).astype(np.uint8)).save(path)


def render_hard_view(scene, camera, background) -> torch.Tensor:
    """Opaque z-buffer render of the final mesh, colours from the full SH evaluated per vertex for this camera."""
    from trisplat.scene.sh import eval_sh

    centre = torch.as_tensor(camera.center, dtype=torch.float32)
    colors = eval_sh(scene.sh, scene.positions - centre).clamp(0, 1)
    out = rasterize_hard(scene.positions, scene.faces, colors, torch.as_tensor(camera.world_to_camera, dtype=torch.float32),
                         torch.as_tensor(camera.K, dtype=torch.float32), camera.width, camera.height,
                         background=torch.as_tensor(background, dtype=torch.float32))
    return out.rgb


def image_metrics(pred: torch.Tensor, gt: torch.Tensor, lpips_fn) -> dict:
    from trisplat.eval.image_metrics import psnr, ssim

    p, g = pred.clamp(0, 1).cpu().numpy(), gt.cpu().numpy()
    m = {"psnr": float(psnr(p, g)), "ssim": float(ssim(p, g))}
    if lpips_fn is not None:
        m["lpips"] = float(lpips_fn(p, g))
    return m


def _lpips_or_none():
    try:
        from trisplat.eval.lpips import LPIPS

        return LPIPS()
    except (FileNotFoundError, ImportError):
        return None


def _mean(rows: list[dict], key: str) -> float | None:
    vals = [r[key] for r in rows if key in r and r[key] is not None and math.isfinite(r[key])]
    return float(np.mean(vals)) if vals else None


@torch.no_grad()
def write_outputs(trainer, pruned) -> dict:
    """Everything a finished run leaves in RUN/ (see trisplat/run.py); returns the metrics written."""
    from trisplat.io import export_mesh, save_model_ply

    run_dir, data, cfg = trainer.run_dir, trainer.data, trainer.cfg
    scene = trainer.ts.to_scene()
    normalization = np.asarray(data.normalization, dtype=np.float64)
    save_model_ply(run_dir / layout.MODEL, scene, normalization)
    colors = sh_dc_to_rgb(scene.sh[:, 0]).clamp(0, 1).numpy()
    to_capture = np.linalg.inv(normalization)
    for suffix in ("ply", "obj", "glb"):
        export_mesh(run_dir / f"mesh.{suffix}", scene.positions.numpy(), scene.faces.numpy(), colors,
                    transform=to_capture)

    renders = run_dir / layout.RENDERS
    renders.mkdir(exist_ok=True)
    lpips_fn = _lpips_or_none()
    views = []
    for n, i in enumerate(data.test_indices):
        cam = data.cameras[int(i)]
        gt = trainer.gt(int(i))
        hard = render_hard_view(scene, cam, cfg.background)
        soft = trainer.render(int(i), 1.0).rgb.clamp(0, 1)
        row = {"view": cam.name or str(int(i)), **image_metrics(hard, gt, lpips_fn if n < 50 else None),
               "soft_psnr": float(-10 * math.log10(max(float(((soft - gt) ** 2).mean()), 1e-12)))}
        views.append(row)
        if n < cfg.num_renders:
            stem = Path(cam.image_path).stem if cam.image_path else f"view_{int(i):04d}"
            to_png(hard, renders / f"{stem}.png")
    opac = scene.opacities()
    metrics = {
        "test_views": len(views),
        "psnr": _mean(views, "psnr"), "ssim": _mean(views, "ssim"), "lpips": _mean(views, "lpips"),
        "lpips_net": "alex" if lpips_fn is not None else None,
        "soft_psnr": _mean(views, "soft_psnr"),
        "render_mode": "hard",
        "faces": scene.num_faces, "vertices": scene.num_vertices,
        "vertex_face_ratio": scene.num_vertices / max(scene.num_faces, 1),
        "min_vertex_opacity": float(opac.min()) if opac.numel() else None,
        "sigma_end": cfg.sigma_end, "opacity_floor": scene.opacity_floor,
        "steps": trainer.step, "wall_s": trainer.wall_s,
        "final_prune": None if pruned is None else {"faces_removed": pruned.faces_removed,
                                                    "vertices_removed": pruned.vertices_removed},
        "per_view": views,
    }
    (run_dir / layout.METRICS).write_text(json.dumps(metrics, indent=2))
    return metrics
