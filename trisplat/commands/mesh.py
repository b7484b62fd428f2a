"""`trisplat mesh RUN`: restricted Delaunay of a trained run's soup -> connected mesh RUN/mesh_connected.ply + stats."""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT, flowing_help

MESH_FILE = "mesh_connected.ply"
STATS_SUFFIX = "_stats.json"  # the statistics are written beside the mesh, as <mesh stem>_stats.json
STATS_FILE = "mesh_connected" + STATS_SUFFIX


@flowing_help
@dataclass
class MeshConfig:
    """Turn a trained run's triangle soup into a connected mesh (MeshSplatting restricted Delaunay), write it in
    the capture's frame with per-vertex colour, and print its statistics as JSON."""

    run: tyro.conf.Positional[Path]
    """run directory written by `trisplat train`"""
    out: Annotated[Path | None, NO_DEFAULT_HINT] = None
    """output mesh (.ply/.obj/.glb; default: RUN/mesh_connected.ply)"""
    min_component_faces: int = 0
    """drop vertex-connected pieces with fewer faces than this (count); 0 keeps all"""
    min_component_area_fraction: float = 0.0
    """drop pieces with less than this fraction of the total area; 0 keeps all"""
    repair_non_manifold: bool = True
    """at edges with more than two faces keep the two best-shaped faces; --no-repair-non-manifold keeps all"""
    up: Literal["auto", "y", "z", "capture"] = "auto"
    """rotate the export so the capture's up becomes +Y ('y') or +Z ('z'); capture: keep the capture's axes;
    auto: +Y for .glb (glTF defines +Y as up), the capture's axes for .ply and .obj"""
    force: bool = False
    """replace the output mesh (and its statistics file) if they exist"""


def main(argv: list[str]) -> int:
    cfg = tyro.cli(MeshConfig, args=argv, prog="trisplat mesh", description=__doc__, config=CLI_STYLE)
    from trisplat.io import FORMATS, export_mesh
    from trisplat.io.mesh_files import resolve_up
    from trisplat.io.atomic import atomic_write_text, refuse_to_overwrite
    from trisplat.mesh.connect import ConnectConfig, connect_faces
    from trisplat.mesh.stats import mesh_statistics
    from trisplat.run import open_run

    run = open_run(cfg.run)
    out = cfg.out if cfg.out is not None else run.path / MESH_FILE
    if Path(out).suffix.lower() not in FORMATS:
        raise ValueError(f"{out}: unknown mesh format {Path(out).suffix!r}; use one of {', '.join(FORMATS)}")
    if not Path(out).parent.is_dir():
        raise FileNotFoundError(f"{out}: folder {Path(out).parent} does not exist")
    stats_path = Path(out).with_name(Path(out).stem + STATS_SUFFIX)  # RUN/mesh_connected_stats.json by default
    targets = [out, stats_path] + ([Path(out).with_suffix(".mtl")]
                                                      if Path(out).suffix.lower() == ".obj" else [])
    refuse_to_overwrite(targets, cfg.force)  # before the (long) triangulation
    scene, normalization = run.load_model()
    positions = scene.positions.detach().cpu().numpy().astype(np.float64)
    cleaned, rep = connect_faces(positions, scene.faces.detach().cpu().numpy(), ConnectConfig(
        repair_non_manifold_edges=cfg.repair_non_manifold,
        min_component_faces=cfg.min_component_faces,
        min_component_area_fraction=cfg.min_component_area_fraction,
        drop_unreferenced_vertices=True,
    ))
    if len(cleaned.faces) == 0:
        raise ValueError(f"{cfg.run}: the restricted Delaunay triangulation kept no face "
                         f"({rep.num_vertices} vertices, {scene.num_faces} soup faces; {'; '.join(rep.notes)})")
    colors = scene.base_colors().detach().cpu().numpy()[cleaned.vertex_source]
    to_capture = np.linalg.inv(np.asarray(normalization, dtype=np.float64))
    up = None if cfg.up == "capture" else cfg.up
    capture_up = None
    if resolve_up(up, out) is not None:
        from trisplat.io import capture_up as capture_up_of

        try:
            capture_up = capture_up_of(run.load_scene_data())
        except (FileNotFoundError, ValueError) as exc:
            print(f"trisplat mesh: cannot read the capture's cameras ({exc}); assuming a Z-up capture",
                  file=sys.stderr)
    export_mesh(out, cleaned.vertices, cleaned.faces, np.clip(colors, 0.0, 1.0), up=up, transform=to_capture,
                capture_up=capture_up)
    capture_positions = cleaned.vertices @ to_capture[:3, :3].T + to_capture[:3, 3]
    stats = mesh_statistics(capture_positions, cleaned.faces).to_dict()
    report = {
        "mesh": str(out),
        "soup_faces": scene.num_faces,
        "restricted_delaunay": dict(vars(rep)),
        "cleanup": {k: getattr(cleaned, k) for k in ("num_degenerate_faces", "num_duplicate_faces",
                                                     "num_non_manifold_faces", "num_fragments", "num_fragment_faces",
                                                     "num_flipped")},
        "statistics": stats,
    }
    atomic_write_text(stats_path, json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return 0
