"""`trisplat bench walk RUN`: can a physics engine stand on the run's mesh? (trisplat.eval.walk)

Spheres (1% of the camera sphere's radius by default) are dropped from just above the upward-facing surfaces the
cameras see (floor, rug, table tops), onto the run's mesh as one static concave triangle mesh in PyBullet, the
background sphere left out; after a few simulated seconds each either stands on the surface (the mesh straight below
it) or fell through. Writes walk.json and walk.md (with the counts) and walk.png (a map from above: where spheres
stood, where they fell through) into --out.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from trisplat.bench.common import BenchTable
from trisplat.commands.style import CLI_STYLE


@dataclass
class WalkArgs:
    """Spheres dropped on the run's mesh in a physics engine: how many stand on it, where the others fell through."""

    run: Annotated[Path, tyro.conf.Positional]
    """run folder written by `trisplat train` or `trisplat slam` (its model and its cameras are read)"""
    drops: int = 200
    """spheres dropped"""
    radius: float = 0.01
    """sphere radius, in units of the normalised frame (the cameras lie within its unit sphere)"""
    settle_s: float = 3.0
    """simulated seconds before the spheres are checked"""
    seed: int = 0
    """which surface points are chosen"""
    out: Path = Path("bench_results")
    """folder for walk.json, walk.md and walk.png"""


def main(argv: list[str]) -> int:
    args = tyro.cli(WalkArgs, args=argv, prog="trisplat bench walk", description=__doc__, config=CLI_STYLE)
    from trisplat.eval.walk import WalkConfig, plot_walk, walk_check
    from trisplat.run import METRICS, open_run

    run = open_run(args.run)
    scene, _ = run.load_model()
    data = run.load_scene_data()
    metrics = json.loads((run.path / METRICS).read_text()) if (run.path / METRICS).exists() else {}
    sky = int(metrics.get("background_faces") or 0)
    positions = scene.positions.detach().cpu().numpy().astype(np.float64)
    faces = scene.faces.detach().cpu().numpy().astype(np.int64)[: scene.num_faces - sky]
    cameras = [data.cameras[int(i)] for i in list(data.train_indices) + list(data.test_indices)]
    cfg = WalkConfig(drops=args.drops, radius=args.radius, settle_s=args.settle_s, seed=args.seed)
    rep = walk_check(positions, faces, cameras, cfg)
    args.out.mkdir(parents=True, exist_ok=True)
    plot_walk(rep, positions[np.unique(faces)], args.out / "walk.png")
    table = BenchTable("walk", ["run", "faces", "upward pixels", "dropped", "stand on the surface", "fell through",
                                "share standing", "at rest"])
    d = rep.to_dict()
    table.add(str(args.run), rep.faces, rep.candidates, len(rep.drops), d["on_surface"], d["fell_through"],
              round(rep.fraction, 4), d["at_rest"])
    table.notes.append(f"up {np.round(rep.up, 3).tolist()} (the cameras' mean up), sphere radius {rep.radius:g}, "
                       f"{args.settle_s:g} s simulated, background sphere ({sky} faces) left out; map: walk.png")
    (args.out / "walk_drops.json").write_text(json.dumps(d, indent=1))
    md = table.write(args.out, "trisplat bench walk " + " ".join(argv))
    print(md.read_text())
    return 0 if len(rep.drops) else 1
