"""Synthetic scenes with known truth: procedural meshes, orbit cameras, an independent ray-cast renderer, Blender-format
writer, an RGB-D walk through a room (7-Scenes layout)."""

from trisplat.synth.blender import write_blender_scene
from trisplat.synth.orbit import look_at, orbit_cameras
from trisplat.synth.raycast import RayCastView, Shading, raycast_view, render_face_ids, render_views
from trisplat.synth.rgbd_room import rgbd_room_mesh, room_walk_c2w, write_rgbd_room
from trisplat.synth.scenes import DEMO_SHADING, bake_shading, demo_mesh, spot_mesh, two_object_mesh
from trisplat.synth.surface import surface_colors

__all__ = [
    "DEMO_SHADING",
    "RayCastView",
    "Shading",
    "bake_shading",
    "demo_mesh",
    "look_at",
    "orbit_cameras",
    "raycast_view",
    "render_face_ids",
    "render_views",
    "rgbd_room_mesh",
    "room_walk_c2w",
    "spot_mesh",
    "surface_colors",
    "two_object_mesh",
    "write_blender_scene",
    "write_rgbd_room",
]
