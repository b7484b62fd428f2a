"""File formats: coloured meshes (.ply, .obj + .mtl, .glb) by suffix, the full SH model PLY, run exports."""
from trisplat.io.axes import capture_up, estimate_capture_up, up_rotation
from trisplat.io.export_run import EXPORT_FORMATS, export_run, export_targets
from trisplat.io.mesh_files import FORMATS, export_mesh, load_mesh
from trisplat.io.model_ply import load_model_ply, save_model_ply

__all__ = [
    "EXPORT_FORMATS",
    "FORMATS",
    "capture_up",
    "estimate_capture_up",
    "export_mesh",
    "export_run",
    "export_targets",
    "load_mesh",
    "load_model_ply",
    "save_model_ply",
    "up_rotation",
]
