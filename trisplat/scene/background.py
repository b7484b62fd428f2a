"""The far field's last layer: an opaque background sphere behind everything a real capture's soup holds.

A photo of a room or of the outdoors has content in every pixel; where the soup (or the connected surface and the
far-field soup beyond it) leaves a gap, the renderer would show its flat background colour. The background sphere
closes those gaps the way a skybox does in a game: an icosphere about the origin of the normalised frame, far
enough to lie behind the soup, its faces turned towards the cameras (inside), its vertex colours first the mean of
what the training photos show in each vertex's direction, then optimised with everything else. It is part of the
scene (rendered, textured and exported like the rest), kept as the last rows of the face table.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from trisplat.cameras import Camera
from trisplat.scene.model import TriangleScene
from trisplat.scene.sh import num_sh_bases, rgb_to_sh_dc

# icosphere subdivisions: 5 -> 20,480 faces (10,242 vertices, about 2.1 degrees apart): about a dozen pixels of an
# 800-pixel-wide photo per vertex, as fine as vertex colours need to be for what shows through gaps (the exported
# file's texture is fitted to the photos at a finer resolution anyway)
SPHERE_SUBDIVISIONS = 5
# the sphere lies this much beyond the farthest soup face (the 99.9th percentile of the face centres' distances,
# so one stray face far out does not push it away) and never closer than MIN_RADIUS (normalised units)
RADIUS_MARGIN = 1.1
MIN_RADIUS = 2.0
# vertex opacity of the sphere: opaque (it is the last thing a ray meets)
OPAQUE_LOGIT = 12.0


def background_radius(scene: TriangleScene) -> float:
    """Radius of the background sphere for `scene` (normalised units): beyond nearly all of its faces."""
    if scene.num_faces == 0:
        return MIN_RADIUS
    pos = scene.positions.detach().cpu().numpy().astype(np.float64)
    centres = pos[scene.faces.detach().cpu().numpy().astype(np.int64)].mean(1)
    far = float(np.quantile(np.linalg.norm(centres, axis=1), 0.999))
    return max(MIN_RADIUS, RADIUS_MARGIN * far)


def photo_colours(points: np.ndarray, cameras: Sequence[Camera], load_image: Callable[[int], np.ndarray],
                  fallback: Sequence[float]) -> np.ndarray:
    """float32 [N,3]: the mean colour the photos show at each of `points` [N,3] (world), over every camera that sees
    it in front of it and inside its image (the photo's pixel at its projection; nothing occludes: the sphere is
    behind everything); `fallback` where none does."""
    from trisplat.train.switch import image_colors  # the switch's colouring of a fused surface, without depths

    rgb, count = image_colors(cameras, (load_image(n) for n in range(len(cameras))), None,
                              np.asarray(points, dtype=np.float64), 0.0)
    out = rgb.astype(np.float32)
    out[count == 0] = np.asarray(fallback, dtype=np.float32)
    return out


def background_sphere(radius: float, cameras: Sequence[Camera], load_image: Callable[[int], np.ndarray],
                      fallback: Sequence[float], sh_degree: int, opacity_floor: float = 0.0,
                      subdivisions: int = SPHERE_SUBDIVISIONS) -> TriangleScene:
    """An opaque icosphere of `radius` about the origin, faces wound to face inwards (towards the cameras), colours
    from the photos (photo_colours; SH band 0 only), opacity_floor as the scene's it joins."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=float(radius))
    verts = np.asarray(ico.vertices, dtype=np.float64)
    faces = np.asarray(ico.faces, dtype=np.int64)[:, ::-1].copy()  # outward -> inward
    rgb = photo_colours(verts, cameras, load_image, fallback)
    V = len(verts)
    sh = torch.zeros(V, num_sh_bases(sh_degree), 3)
    sh[:, 0] = rgb_to_sh_dc(torch.as_tensor(rgb))
    return TriangleScene(torch.as_tensor(verts, dtype=torch.float32), sh, torch.full((V,), OPAQUE_LOGIT),
                         torch.as_tensor(faces, dtype=torch.int32), float(opacity_floor))
