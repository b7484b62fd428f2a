"""Soup to mesh: restricted Delaunay triangulation, cleanup, orientation and statistics.

(`restricted_delaunay` itself is imported from `trisplat.mesh.restricted_delaunay`: re-exporting it here would hide
the module of the same name.)
"""
from trisplat.mesh.cleanup import CleanupConfig, CleanupResult, clean_mesh, weld_vertices
from trisplat.mesh.restricted_delaunay import RDTReport, restricted_delaunay_report
from trisplat.mesh.stats import MeshStats, mesh_statistics

__all__ = [
    "CleanupConfig",
    "CleanupResult",
    "MeshStats",
    "RDTReport",
    "clean_mesh",
    "mesh_statistics",
    "restricted_delaunay_report",
    "weld_vertices",
]
