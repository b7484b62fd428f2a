"""Browser viewer: a local web page (three.js, vendored) showing a mesh, its training cameras and their photos."""
from trisplat.viewer.data import ViewerData, viewer_data_from_mesh, viewer_data_from_run
from trisplat.viewer.server import ViewerServer

__all__ = ["ViewerData", "ViewerServer", "viewer_data_from_mesh", "viewer_data_from_run"]
