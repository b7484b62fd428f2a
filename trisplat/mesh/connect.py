"""Soup to connected mesh for a TriangleScene: restricted Delaunay of its vertices against its own faces, then cleanup.

This is the MeshSplatting stage-2 switch (ALGORITHM.md section 4): vertices and their attributes are kept, only the
faces are replaced.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from trisplat.mesh.cleanup import CleanupConfig, CleanupResult, clean_mesh
from trisplat.mesh.restricted_delaunay import RDTReport, restricted_delaunay
from trisplat.scene.model import TriangleScene


@dataclass(frozen=True)
class ConnectConfig:
    """Settings of `connect_scene`."""

    min_component_faces: int = 0
    """drop vertex-connected pieces of the new mesh with fewer faces than this (count); 0 keeps all."""
    min_component_area_fraction: float = 0.0
    """drop pieces with less than this fraction of the total area (dimensionless); 0 keeps all."""
    repair_non_manifold_edges: bool = False
    """at edges with more than two faces keep the two best-shaped faces (see `cleanup.non_manifold_excess_faces`)."""
    drop_unreferenced_vertices: bool = False
    """False (the stage-2 switch): the vertex table is unchanged. True: keep only vertices some new face uses
    (the report's vertex_source then maps new vertices to old ones)."""


@dataclass
class ConnectReport:
    """What `connect_scene` did. vertex_source: int64 [V'] old index of each new vertex (identity unless compacted)."""

    rdt: RDTReport
    num_soup_faces: int
    num_faces: int
    num_vertices_before: int
    num_vertices: int
    vertex_source: np.ndarray
    cleanup: CleanupResult | None = field(default=None, repr=False)


def connect_faces(positions: np.ndarray, soup_faces: np.ndarray, config: ConnectConfig = ConnectConfig()
                  ) -> tuple[CleanupResult, RDTReport]:
    """Restricted Delaunay of `positions` [V,3] against the soup (`positions`, `soup_faces` [F,3]), cleaned up:
    degenerate and duplicate faces dropped, small pieces removed per `config`, faces oriented. Vertices are not
    welded (Qhull already leaves exact duplicates out)."""
    positions = np.asarray(positions, dtype=np.float64)
    rep = RDTReport()
    faces = restricted_delaunay(positions, positions, soup_faces, report=rep)
    cleaned = clean_mesh(positions, faces, CleanupConfig(
        weld=False,
        repair_non_manifold_edges=config.repair_non_manifold_edges,
        min_component_faces=config.min_component_faces,
        min_component_area_fraction=config.min_component_area_fraction,
        drop_unreferenced_vertices=config.drop_unreferenced_vertices,
    ))
    return cleaned, rep


def connect_scene(scene: TriangleScene, config: ConnectConfig = ConnectConfig()) -> tuple[TriangleScene, ConnectReport]:
    """The scene with its faces replaced by the restricted Delaunay triangulation of its vertices against its own
    faces (int32, same device). Vertex tensors are the same objects unless `config.drop_unreferenced_vertices`,
    in which case they are indexed by `report.vertex_source`."""
    positions = scene.positions.detach().cpu().numpy()
    soup = scene.faces.detach().cpu().numpy()
    cleaned, rep = connect_faces(positions, soup, config)
    device = scene.faces.device
    faces = torch.as_tensor(cleaned.faces, dtype=torch.int32, device=device)
    if config.drop_unreferenced_vertices:
        idx = torch.as_tensor(cleaned.vertex_source, dtype=torch.long, device=scene.positions.device)
        out = replace(scene, positions=scene.positions.detach()[idx].clone(), sh=scene.sh.detach()[idx].clone(),
                      opacity_logit=scene.opacity_logit.detach()[idx].clone(), faces=faces)
    else:
        out = replace(scene, faces=faces)
    report = ConnectReport(rdt=rep, num_soup_faces=len(soup), num_faces=len(cleaned.faces),
                           num_vertices_before=len(positions), num_vertices=out.num_vertices,
                           vertex_source=cleaned.vertex_source, cleanup=cleaned)
    return out, report
