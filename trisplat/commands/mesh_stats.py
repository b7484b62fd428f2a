"""`trisplat mesh-stats MESH`: vertex/face ratio, valence, boundary and non-manifold edges, pieces, watertightness."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT, flowing_help
from trisplat.mesh.stats import mesh_statistics


@flowing_help
@dataclass
class MeshStatsConfig:
    """Print the statistics of a mesh file as JSON."""

    mesh: tyro.conf.Positional[Path]
    """mesh file (.ply/.obj/.glb/.stl/... any format trimesh reads); vertices are used as stored"""
    weld_tolerance: Annotated[float | None, NO_DEFAULT_HINT] = None
    """merge vertices closer than this (file units) first, e.g. 0 for exact duplicates of STL/OBJ seams (default: no
    merging)"""
    self_intersections: bool = True
    """count edges crossing non-adjacent faces (BVH test; --no-self-intersections skips it)"""


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V,3] and faces [F,3] of a mesh file, in stored order (no merging)."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    try:
        loaded = trimesh.load(path, process=False, maintain_order=True)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ValueError(f"{path}: cannot read as a mesh ({exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(meshes) if meshes else None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"{path}: contains no triangle faces")
    return np.asarray(loaded.vertices, dtype=np.float64), np.asarray(loaded.faces, dtype=np.int64)


def main(argv: list[str]) -> int:
    cfg = tyro.cli(MeshStatsConfig, args=argv, prog="trisplat mesh-stats", description=__doc__, config=CLI_STYLE)
    v, f = read_mesh(cfg.mesh)
    if cfg.weld_tolerance is not None:
        from trisplat.mesh.cleanup import CleanupConfig, clean_mesh

        res = clean_mesh(v, f, CleanupConfig(weld_tolerance=cfg.weld_tolerance, min_face_area=-1.0,
                                             drop_duplicate_faces=False, orient=False))
        v, f = res.vertices, res.faces
    stats = mesh_statistics(v, f, check_self_intersections=cfg.self_intersections)
    print(json.dumps(stats.to_dict(), indent=2))
    return 0
