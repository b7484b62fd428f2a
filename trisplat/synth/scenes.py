"""Known meshes for synthetic captures: the built-in procedural demo scene, a two-object scene, and textured Spot.

All are z-up (like the Blender/NeRF-synthetic scenes), in scene units of roughly one, with outward winding.
"""
from __future__ import annotations

import colorsys
import math
from pathlib import Path

import numpy as np
import trimesh

from trisplat.synth.raycast import Shading

# the fixed light baked into the demo's ground truth (view independent, so per-vertex colour can learn it)
DEMO_SHADING = Shading(light_dir=(0.3, 0.2, 1.0), ambient=0.45)


def _rgba(rgb) -> np.ndarray:
    rgb = np.clip(np.asarray(rgb, dtype=np.float64), 0.0, 1.0)
    return np.concatenate([np.round(rgb * 255), np.full(rgb.shape[:-1] + (1,), 255)], -1).astype(np.uint8)


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(h % 1.0, s, v))


def _unmerged(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Each face gets its own three vertices (so colours can jump across edges)."""
    v = mesh.vertices[mesh.faces].reshape(-1, 3)
    f = np.arange(len(v)).reshape(-1, 3)
    return trimesh.Trimesh(v, f, process=False)


def ground_disk(radius: float = 1.2, rings: int = 6, sectors: int = 24, colors=((0.85, 0.78, 0.6), (0.35, 0.55, 0.55)),
                z: float = 0.0) -> trimesh.Trimesh:
    """A flat disk in the plane z = `z`, normal +z, with a crisp polar checker of two colours (unmerged vertices)."""
    tris, cols = [], []
    for i in range(rings):
        r0, r1 = radius * i / rings, radius * (i + 1) / rings
        for j in range(sectors):
            a0, a1 = 2 * math.pi * j / sectors, 2 * math.pi * (j + 1) / sectors
            p = lambda r, a: (r * math.cos(a), r * math.sin(a), z)
            col = colors[(i + j) % 2]
            if i == 0:
                tris.append([p(0, 0), p(r1, a0), p(r1, a1)])
                cols.append(col)
            else:
                tris.append([p(r0, a0), p(r1, a0), p(r1, a1)])
                tris.append([p(r0, a0), p(r1, a1), p(r0, a1)])
                cols += [col, col]
    v = np.asarray(tris, dtype=np.float64).reshape(-1, 3)
    m = trimesh.Trimesh(v, np.arange(len(v)).reshape(-1, 3), process=False)
    m.visual.vertex_colors = _rgba(np.repeat(np.asarray(cols), 3, axis=0))
    return m


def _striped_torus(center, hue: float) -> trimesh.Trimesh:
    """An upright torus (ring axis along y) with 8 alternating colour stripes around the ring."""
    t = trimesh.creation.torus(major_radius=0.3, minor_radius=0.1, major_sections=48, minor_sections=16)
    t = trimesh.Trimesh(t.vertices, t.faces, process=False)
    t.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
    ang = np.arctan2(t.vertices[:, 2], t.vertices[:, 0])
    stripe = (np.floor(ang / (2 * math.pi) * 8) % 2).astype(bool)
    col = np.where(stripe[:, None], _hsv(hue, 0.8, 0.9), _hsv(hue + 0.5, 0.25, 0.95))
    t.visual.vertex_colors = _rgba(col)
    t.apply_translation(center)
    return t


def _coloured_box(center, size: float, yaw: float, hue: float) -> trimesh.Trimesh:
    """A cube with a different flat colour on each of its six sides."""
    b = _unmerged(trimesh.creation.box(extents=(size, size, size)))
    axis = np.argmax(np.abs(b.face_normals), axis=1)
    side = axis * 2 + (b.face_normals[np.arange(len(axis)), axis] > 0)
    palette = np.array([_hsv(hue + k / 6.0, 0.7, 0.85) for k in range(6)])
    b.visual.vertex_colors = _rgba(np.repeat(palette[side], 3, axis=0))
    b.apply_transform(trimesh.transformations.rotation_matrix(yaw, [0, 0, 1]))
    b.apply_translation(center)
    return b


def _gradient_sphere(center, radius: float, hue: float) -> trimesh.Trimesh:
    """An icosphere whose hue sweeps with height and whose brightness alternates in 6 longitude bands."""
    s = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    s = trimesh.Trimesh(s.vertices, s.faces, process=False)
    zn = s.vertices[:, 2] / radius
    lon = np.arctan2(s.vertices[:, 1], s.vertices[:, 0])
    band = (np.floor(lon / (2 * math.pi) * 6) % 2).astype(bool)
    col = np.stack([_hsv(hue + 0.25 * z, 0.75, 0.95 if b else 0.6) for z, b in zip(zn, band)])
    s.visual.vertex_colors = _rgba(col)
    s.apply_translation(center)
    return s


def _gradient_cylinder(center, radius: float, height: float, hue: float) -> trimesh.Trimesh:
    """An upright cylinder shading from dark at the bottom to light at the top."""
    c = trimesh.creation.cylinder(radius=radius, height=height, sections=32)
    c = trimesh.Trimesh(c.vertices, c.faces, process=False)
    t = (c.vertices[:, 2] / height + 0.5)[:, None]
    c.visual.vertex_colors = _rgba((1 - t) * _hsv(hue, 0.9, 0.35) + t * _hsv(hue, 0.3, 1.0))
    c.apply_translation(np.asarray(center) + [0, 0, height / 2])
    return c


def bake_shading(mesh: trimesh.Trimesh, shading: Shading) -> trimesh.Trimesh:
    """A copy whose vertex colours carry `shading`'s fixed light at each vertex (Lambert on the vertex normal):
    the unlit render of the result looks lit, and per-vertex colour can represent it exactly."""
    if mesh.visual.kind != "vertex":
        raise ValueError(f"bake_shading needs vertex colours, the mesh has {mesh.visual.kind!r} visuals")
    light = np.asarray(shading.light_dir, dtype=np.float64)
    light = light / np.linalg.norm(light)
    k = shading.ambient + (1.0 - shading.ambient) * np.clip(mesh.vertex_normals @ light, 0.0, None)
    out = trimesh.Trimesh(mesh.vertices.copy(), mesh.faces.copy(), process=False)
    out.visual.vertex_colors = _rgba(mesh.visual.vertex_colors[:, :3] / 255.0 * k[:, None])
    return out


def demo_mesh(seed: int = 0, shaded: bool = True) -> trimesh.Trimesh:
    """The built-in procedural scene (z-up, about 2.4 units wide, 0.8 high, ~3k faces, vertex colours).

    A striped upright torus, a cube with six flat colours, a banded gradient icosphere and a gradient cylinder on a
    checkered ground disk of radius 1.2 at z = 0. `seed` rotates the arrangement about z and shifts the hues.
    shaded: bake DEMO_SHADING's fixed light into the vertex colours (view independent), so shapes read clearly in
    an unlit render; False gives the flat albedo.
    """
    rng = np.random.default_rng(seed)
    hue = float(rng.uniform(0, 1)) if seed else 0.0
    parts = [
        ground_disk(),
        _striped_torus((-0.45, 0.35, 0.4), hue + 0.0),
        _coloured_box((0.5, 0.3, 0.2), 0.4, yaw=0.5, hue=hue + 0.1),
        _gradient_sphere((0.1, -0.5, 0.3), 0.3, hue + 0.55),
        _gradient_cylinder((-0.55, -0.4, 0.0), 0.13, 0.55, hue + 0.8),
    ]
    mesh = trimesh.util.concatenate(parts)
    if seed:
        mesh.apply_transform(trimesh.transformations.rotation_matrix(float(rng.uniform(0, 2 * math.pi)), [0, 0, 1]))
    return bake_shading(mesh, DEMO_SHADING) if shaded else mesh


def two_object_mesh(ground: bool = False) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Two separate objects a small gap apart, for object extraction: (mesh, label int64 [F]).

    label 1: an icosphere of radius 0.35 centred at (-0.35, 0, 0) (the object to extract);
    label 2: a coloured cube of side 0.5 centred at (0.4, 0, 0); label 0: a ground disk at z = -0.36 if `ground`.
    They occlude each other from views along x.
    """
    sphere = _gradient_sphere((-0.35, 0.0, 0.0), 0.35, 0.6)
    box = _coloured_box((0.4, 0.0, 0.0), 0.5, yaw=0.3, hue=0.05)
    parts, labels = [sphere, box], [1, 2]
    if ground:
        parts.append(ground_disk(radius=1.0, z=-0.36))
        labels.append(0)
    mesh = trimesh.util.concatenate(parts)
    label = np.concatenate([np.full(len(p.faces), lab, dtype=np.int64) for p, lab in zip(parts, labels)])
    return mesh, label


def spot_mesh(path: str | Path, texture: str | Path | None = None, z_up: bool = True) -> trimesh.Trimesh:
    """Keenan Crane's Spot (textured OBJ) as a trimesh with its texture attached.

    path: spot_triangulated.obj. texture: the PNG (default: spot_texture.png beside the OBJ; the OBJ has no .mtl).
    z_up: rotate the y-up original by +90 degrees about x so that it stands on the xy plane like the other scenes.
    """
    from PIL import Image

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: Spot mesh not found")
    tex = Path(texture) if texture is not None else path.with_name("spot_texture.png")
    if not tex.exists():
        raise FileNotFoundError(f"{tex}: texture of {path.name} not found")
    loaded = trimesh.load(path, process=False, force="mesh")
    uv = getattr(loaded.visual, "uv", None)
    if uv is None or len(uv) != len(loaded.vertices):
        raise ValueError(f"{path}: expected per-vertex UV coordinates (vt) for every vertex")
    mesh = trimesh.Trimesh(loaded.vertices, loaded.faces, process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.asarray(uv), image=Image.open(tex).convert("RGB"))
    if z_up:
        mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
    return mesh
