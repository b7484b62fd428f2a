"""The blocks merged into one connected surface, written as a normal run folder.

Each block's final model (its model.ply, in the block's frame) is brought back to the scene's normalised frame and
clipped to its cell (the faces whose centroid lies in the cell: the margins, trained by two blocks, keep one
block's faces only). The clipped pieces meet along the cell borders with cracks and small overlaps; they are
rendered together from every training view of the scene and their depth fused into one TSDF
(trisplat.mesh.fusion, the switch's own code: trisplat.train.switch.soup_to_surface), whose zero surface is one
welded, consistently oriented surface across the seams, coloured from the photos. The fused grid has the voxel
size of the finest block (capped by `max_voxels`: the merge's memory grows with the scene's volume, see
docs/benchmarks.md). The surface is then finished like any trained run (the final surface pass, model.ply, mesh
files, test renders, metrics.json) by the same Trainer, on the whole capture, so `trisplat eval / view / export`
work on the merged folder as on any run. blocks.json there records the plan and every block's summary.
"""
from __future__ import annotations

import json
import resource
import sys
import time
from functools import reduce
from pathlib import Path

import numpy as np
import torch

from trisplat import run as layout

MERGE_MAX_VOXELS = 64_000_000  # trisplat.mesh.fusion.MAX_VOXELS: the dense grid's cap
BLOCKS_JSON = "blocks.json"


def clipped_block(run_dir: Path, block, plan, scene_normalization: np.ndarray):
    """(the block's model in the scene's normalised frame, clipped to its cell; its voxel size there (the
    block's fusion voxel, estimated from its box and image size), its box's longest side)."""
    from trisplat.io import load_model_ply
    from trisplat.scene.model import TriangleScene
    from trisplat.train.switch import sub_scene

    from trisplat.blocks.partition import in_rect

    path = Path(run_dir) / layout.MODEL
    if not path.is_file():
        raise FileNotFoundError(f"{path}: block {block.index} has no model (did its run finish?)")
    scene, Nb = load_model_ply(path)
    T = np.asarray(scene_normalization, dtype=np.float64) @ np.linalg.inv(Nb)
    if not np.allclose(T[:3, :3], T[0, 0] * np.eye(3), atol=1e-9 * abs(T[0, 0])):
        raise ValueError(f"{path}: the block's frame is not a translation and scale of the scene's")
    pos = scene.positions.detach().to(torch.float64).numpy() @ T[:3, :3].T + T[:3, 3]
    moved = TriangleScene(torch.as_tensor(pos, dtype=torch.float32), scene.sh, scene.opacity_logit, scene.faces,
                          scene.opacity_floor)
    f = scene.faces.numpy().astype(np.int64)
    keep = in_rect(plan.ground(pos[f].mean(1)), block.cell) if len(f) else np.zeros(0, bool)
    metrics = Path(run_dir) / layout.METRICS
    sky = int(json.loads(metrics.read_text()).get("background_faces") or 0) if metrics.is_file() else 0
    if sky:  # the block's background sphere (the last face rows, trisplat.scene.background) is the block's, not the
        keep[len(f) - sky:] = False  # scene's: dropped
    return sub_scene(moved, keep)


def merge_blocks(plan, data, block_dirs: list[Path], out: Path, cfg, data_path: str, data_options: dict,
                 block_results: list[dict] | None = None, show_progress: bool = True,
                 max_voxels: int = MERGE_MAX_VOXELS) -> dict:
    """Merge the finished blocks (their run folders, in plan order) into the run folder `out` on the whole capture
    `data`; returns its metrics (metrics.json, plus a `blocks` entry)."""
    from trisplat import render
    from trisplat.io.atomic import atomic_write_text
    from trisplat.train.switch import SurfaceConfig, append_scene, far_field_mask, soup_to_surface, sub_scene
    from trisplat.train.trainer import Trainer

    say = (lambda m: print(f"merge: {m}", file=sys.stderr, flush=True)) if show_progress else None
    t0 = time.perf_counter()
    N = np.asarray(data.normalization, dtype=np.float64)
    parts = [clipped_block(d, b, plan, N) for b, d in zip(plan.blocks, block_dirs)]
    kept = [p.num_faces for p in parts]
    parts = [p for p in parts if p.num_faces]
    if not parts:
        raise ValueError("merge: no block has faces inside its cell: nothing to merge")
    union = reduce(append_scene, parts)
    train = [int(i) for i in data.train_indices]
    masked = data.load_alpha(train[0]) is not None
    boxes = np.asarray([b.box for b in plan.blocks], dtype=np.float64)
    box = np.stack([boxes[:, 0].min(0), boxes[:, 1].max(0)])
    if masked and data.bounds is not None:
        b = np.asarray(data.bounds, dtype=np.float64)
        lo, hi = np.maximum(box[0], b[0]), np.minimum(box[1], b[1])
        if (hi > lo).all():
            box = np.stack([lo, hi])
    # the blocks' fusion voxel (trainer: min(surface_resolution, 2 x image side) voxels along the block's longest
    # side); the merge fuses at the finest of them, as far as max_voxels allows
    side = max(max(data.cameras[i].width, data.cameras[i].height) for i in train)
    res_block = int(min(cfg.surface_resolution, max(2 * side, 32)))
    block_sides = (boxes[:, 1] - boxes[:, 0]).max(1)
    voxel = float(block_sides.min()) / res_block
    longest = float((box[1] - box[0]).max())
    resolution = int(np.ceil(longest / voxel))
    max_depth = cfg.surface_max_depth * float(block_sides.mean()) / longest  # the blocks' shell thickness, absolute
    scfg = SurfaceConfig(resolution=resolution, max_voxels=int(max_voxels), face_ratio=1.0,
                         max_depth_fraction=max_depth, max_faces=int(cfg.surface_max_faces) * len(plan.blocks),
                         opacity=cfg.surface_opacity, unseen_faces=cfg.surface_unseen_faces, empty_is_free=masked)
    bg = torch.tensor(cfg.background, dtype=torch.float32)

    def draw(n: int):
        cam = data.cameras[train[n]]
        return render.rasterize_hard(union.positions, union.faces, union.sh,
                                     torch.as_tensor(cam.world_to_camera, dtype=torch.float32),
                                     torch.as_tensor(cam.K, dtype=torch.float32), cam.width, cam.height, bg,
                                     near=cfg.near)

    if say:
        say(f"{len(parts)} blocks clipped to their cells ({', '.join(map(str, kept))} faces); fusing their depth in "
            f"{len(train)} training views at {resolution} voxels along the scene's longest side")
    surface, report = soup_to_surface(union, [data.cameras[i] for i in train], draw, box, scfg, say,
                                      images=lambda n: data.load_image(train[n]))
    far = far_field_mask(union, box) if not masked else np.zeros(union.num_faces, bool)
    if far.any():
        surface = append_scene(surface, sub_scene(union, far))
    merge_s = time.perf_counter() - t0
    if say:
        say(report.summary())
    trainer = Trainer(cfg, data, out, initial=surface, show_progress=False, data_options=data_options,
                      data_path=data_path)
    trainer.connected, trainer.switched_p, trainer.far_faces = True, cfg.connect_at, int(far.sum())
    trainer.ts.linear_light = cfg.surface_linear_light  # a connected surface, rendered as a viewer shows it
    trainer.save_checkpoint()
    metrics = trainer.finish()
    metrics["blocks"] = {"count": len(plan.blocks), "grid": list(plan.grid), "clipped_faces": kept,
                         "merge_s": round(merge_s, 2), "finish_s": round(time.perf_counter() - t0 - merge_s, 2),
                         "fusion": report.to_dict(), "far_field_faces": int(far.sum()),
                         "merge_peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
                         "results": block_results or []}
    atomic_write_text(Path(out) / layout.METRICS, json.dumps(metrics, indent=2))
    atomic_write_text(Path(out) / BLOCKS_JSON, json.dumps({"plan": plan.to_dict(), "results": block_results or [],
                                                           "merge": metrics["blocks"]}, indent=2))
    return metrics
