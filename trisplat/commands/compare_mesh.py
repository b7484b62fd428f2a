"""`trisplat compare-mesh PRED GT`: Chamfer (accuracy, completeness, mean), F-score and normal consistency, as JSON."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT
from trisplat.eval.geometry import DEFAULT_SAMPLES, DEFAULT_SEED, compare_surfaces, load_surface


@dataclass
class CompareMeshConfig:
    """Compare a predicted mesh with a ground-truth mesh or point cloud (distances in the files' units)."""

    pred: tyro.conf.Positional[Path]
    """predicted mesh (.ply/.obj/.glb/... any format trimesh reads)"""
    gt: tyro.conf.Positional[Path]
    """ground-truth mesh or point cloud (a file with no faces is a point cloud)"""
    threshold: Annotated[float | None, NO_DEFAULT_HINT] = None
    """F-score distance threshold in the files' units (default: 1% of the GT bounding-box diagonal)"""
    samples: int = DEFAULT_SAMPLES
    """points sampled area-uniformly on each mesh"""
    seed: int = DEFAULT_SEED
    """sampling seed"""


def main(argv: list[str]) -> int:
    cfg = tyro.cli(CompareMeshConfig, args=argv, prog="trisplat compare-mesh", description=__doc__, config=CLI_STYLE)
    metrics = compare_surfaces(load_surface(cfg.pred), load_surface(cfg.gt), cfg.threshold, cfg.samples, cfg.seed)
    print(json.dumps(metrics.to_dict(), indent=2))
    return 0
