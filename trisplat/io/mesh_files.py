"""Coloured triangle meshes on disk: .ply, .obj (+ .mtl) and .glb writers and readers, registered by suffix."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import struct
from pathlib import Path

import numpy as np
import trimesh
from plyfile import PlyData, PlyElement

from trisplat.io.atomic import atomic_target, atomic_write_text
from trisplat.io.axes import up_rotation
from trisplat.io.gltf import TextureMap, write_glb

MTL_MATERIAL = "default"
GLTF_SUFFIXES = (".glb",)  # formats whose specification fixes the up axis (+Y)


@dataclass(frozen=True)
class MeshFormat:
    """One file format: `write(path, positions, faces, rgb8, texture) -> files written`."""

    suffix: str
    description: str
    write: Callable[[Path, np.ndarray, np.ndarray, np.ndarray | None, TextureMap | None], list[Path]]


def _write_ply(path: Path, positions: np.ndarray, faces: np.ndarray, rgb8: np.ndarray | None,
               texture: TextureMap | None = None) -> list[Path]:
    """PLY has no texture: the vertex colours (sRGB bytes) are written with or without one."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgb8 is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vert = np.empty(len(positions), dtype=fields)
    vert["x"], vert["y"], vert["z"] = positions.T
    if rgb8 is not None:
        vert["red"], vert["green"], vert["blue"] = rgb8.T
    face = np.empty(len(faces), dtype=[("vertex_indices", "<i4", (3,))])
    face["vertex_indices"] = faces
    elements = [
        PlyElement.describe(vert, "vertex"),
        PlyElement.describe(face, "face", len_types={"vertex_indices": "u1"}),
    ]
    with atomic_target(path) as tmp:
        PlyData(elements, text=False, byte_order="<", comments=["trisplat mesh"]).write(str(tmp))
    return [path]


def _write_obj(path: Path, positions: np.ndarray, faces: np.ndarray, rgb8: np.ndarray | None,
               texture: TextureMap | None = None) -> list[Path]:
    """OBJ + MTL. With a texture: `vt` rows (OBJ's v points up: 1 - glTF's v), `f v/vt` corners and map_Kd naming
    a PNG beside the OBJ (sRGB, as MTL viewers read it); vertex colours are then left out (viewers would multiply)."""
    mtl = path.with_suffix(".mtl")
    lines = [f"mtllib {mtl.name}"]
    if texture is not None:
        png = path.with_suffix(".png")
        from PIL import Image

        with atomic_target(png) as tmp:
            Image.fromarray(texture.image, "RGB").save(str(tmp), format="PNG")
        atomic_write_text(
            mtl,
            "# trisplat: base colour texture (sRGB PNG); shown unlit it matches the photos\n"
            f"newmtl {MTL_MATERIAL}\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nNs 1\nd 1\nillum 1\nmap_Kd {png.name}\n"
        )
        lines.insert(0, "# trisplat textured mesh: 'v x y z', 'vt u v' (v up), faces 'f v/vt'")
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in positions.astype(np.float64).tolist()]
        uv = np.asarray(texture.uv, np.float64)
        lines += [f"vt {u:.7f} {1.0 - v:.7f}" for u, v in uv.tolist()]
        lines.append(f"usemtl {MTL_MATERIAL}")
        fv, ft = faces.astype(np.int64) + 1, np.asarray(texture.uv_faces, np.int64) + 1
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for a, b, c, ta, tb, tc in np.column_stack([fv, ft]).tolist()]
        atomic_write_text(path, "\n".join(lines) + "\n")
        return [path, mtl, png]
    atomic_write_text(
        mtl,
        f"# trisplat: colours are per vertex in {path.name}; this material only makes them visible\n"
        f"newmtl {MTL_MATERIAL}\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nNs 1\nd 1\nillum 1\n"
    )
    lines.insert(0, "# trisplat mesh: 'v x y z r g b' with vertex colours in [0, 1] (sRGB)")
    if rgb8 is not None:
        v = np.column_stack([positions.astype(np.float64), rgb8 / 255.0])
        lines += [f"v {x:.9g} {y:.9g} {z:.9g} {r:.6f} {g:.6f} {b:.6f}" for x, y, z, r, g, b in v.tolist()]
    else:
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in positions.astype(np.float64).tolist()]
    lines.append(f"usemtl {MTL_MATERIAL}")
    lines += [f"f {a} {b} {c}" for a, b, c in (faces.astype(np.int64) + 1).tolist()]
    atomic_write_text(path, "\n".join(lines) + "\n")
    return [path, mtl]


def _write_glb(path: Path, positions: np.ndarray, faces: np.ndarray, rgb8: np.ndarray | None,
               texture: TextureMap | None = None) -> list[Path]:
    """glTF 2.0 binary (trisplat.io.gltf): unlit material, baseColorTexture or linear COLOR_0."""
    return [write_glb(path, positions, faces, rgb8, texture)]


FORMATS: dict[str, MeshFormat] = {
    ".ply": MeshFormat(".ply", "binary PLY, per-vertex RGB uchar (sRGB)", _write_ply),
    ".obj": MeshFormat(".obj", "Wavefront OBJ + MTL: map_Kd texture (sRGB PNG), else 'v x y z r g b' (sRGB)", _write_obj),
    ".glb": MeshFormat(".glb", "binary glTF 2.0, unlit: baseColorTexture (sRGB PNG), else COLOR_0 (linear)", _write_glb),
}


def _format_of(path: Path) -> MeshFormat:
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: unknown mesh format {path.suffix!r}; use one of {', '.join(FORMATS)}")
    return fmt


def _check_mesh(positions, faces, colors) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must be [V,3], got {positions.shape}")
    if not np.isfinite(positions).all():
        raise ValueError("positions contain non-finite values")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces must be integer [F,3], got {faces.dtype} {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(positions)):
        raise ValueError(f"faces index vertices outside 0..{len(positions) - 1}")
    if colors is not None:
        colors = np.asarray(colors, dtype=np.float64)
        if colors.shape != positions.shape:
            raise ValueError(f"colors must be [V,3] like positions {positions.shape}, got {colors.shape}")
        if not np.isfinite(colors).all() or colors.min() < 0.0 or colors.max() > 1.0:
            raise ValueError("colors must be finite and in [0, 1]")
    return positions, faces.astype(np.int64), colors


def resolve_up(up: str | None, path: str | Path) -> str | None:
    """The up axis a mesh file gets: 'auto' means 'y' for glTF (.glb) and the capture's own axes (None) for the
    other formats; None, 'y' and 'z' are kept."""
    if up == "auto":
        return "y" if Path(path).suffix.lower() in GLTF_SUFFIXES else None
    return up


def export_mesh(
    path: str | Path,
    positions,
    faces,
    colors=None,
    up: str | None = "auto",
    transform: np.ndarray | None = None,
    capture_up: np.ndarray | None = None,
    texture: TextureMap | None = None,
) -> list[Path]:
    """Write a coloured mesh; the format comes from the suffix (see FORMATS). Returns the files written.

    positions [V,3], faces [F,3] (counter-clockwise = outward), colors [V,3] in [0,1] or None (stored as 8-bit).
    transform: optional [4,4] applied to the positions first (e.g. the inverse scene normalisation).
    up: None keeps the axes; 'y' / 'z' then rotates so that `capture_up` (default: see `up_rotation`) becomes
    +Y / +Z; 'auto' (default) is 'y' for .glb (glTF is Y-up by definition, engines show a Z-up mesh on its side)
    and None for the other formats. A transform that mirrors (negative determinant) flips the winding so normals
    stay outward. texture: a base colour texture over these faces (OBJ: map_Kd + PNG, GLB: baseColorTexture; PLY
    keeps the vertex colours only).
    """
    path = Path(path)
    fmt = _format_of(path)
    up = resolve_up(up, path)
    positions, faces, colors = _check_mesh(positions, faces, colors)
    M = np.eye(4) if transform is None else np.asarray(transform, dtype=np.float64)
    if M.shape != (4, 4) or not np.isfinite(M).all():
        raise ValueError(f"transform must be a finite [4,4] matrix, got shape {M.shape}")
    M = up_rotation(up, capture_up) @ M
    if not np.array_equal(M, np.eye(4)):
        positions = positions @ M[:3, :3].T + M[:3, 3]
        if np.linalg.det(M[:3, :3]) < 0:
            faces = faces[:, ::-1]
            if texture is not None:
                texture = TextureMap(texture.uv, np.asarray(texture.uv_faces)[:, ::-1], texture.image)
    if texture is not None and np.asarray(texture.uv_faces).shape != faces.shape:
        raise ValueError(f"texture uv_faces {np.asarray(texture.uv_faces).shape} and faces {faces.shape} differ")
    rgb8 = None if colors is None else np.round(colors * 255.0).astype(np.uint8)
    if not path.parent.exists():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    return fmt.write(path, positions.astype(np.float32), faces.astype(np.int32), rgb8, texture)


def _read_trimesh(path: Path, **kwargs) -> trimesh.Trimesh:
    try:
        loaded = trimesh.load(str(path), process=False, maintain_order=True, **kwargs)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ValueError(f"{path}: cannot read as {path.suffix} ({exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        if not meshes:
            raise ValueError(f"{path}: contains no triangle mesh")
        mesh = meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
    elif isinstance(loaded, trimesh.Trimesh):
        mesh = loaded
    else:
        raise ValueError(f"{path}: contains no triangle mesh (got {type(loaded).__name__})")
    if len(mesh.faces) == 0:
        raise ValueError(f"{path}: mesh has no faces")
    return mesh


def load_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a mesh file (any of FORMATS, ours or another tool's) in its stored vertex order.

    Returns positions float32 [V,3], faces int32 [F,3], colors float32 [V,3] in [0,1] or None when the file has
    no vertex colours. A GLB/glTF holding several meshes is returned as one (their union, scene transforms applied).
    A textured OBJ without vertex colours gets its texture sampled at the vertices (vertices on UV seams are then
    split, so the vertex count can exceed the file's 'v' lines).
    """
    path = Path(path)
    _format_of(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    if path.suffix.lower() in GLTF_SUFFIXES:
        return _load_glb(path)
    is_obj = path.suffix.lower() == ".obj"
    # trimesh lets an OBJ's material replace its vertex colours: read the geometry and colours without it first
    mesh = _read_trimesh(path, **({"skip_materials": True} if is_obj else {}))
    if is_obj and mesh.visual.kind != "vertex" and b"mtllib" in path.read_bytes():
        textured = _read_trimesh(path)
        if textured.visual.kind == "texture" and getattr(textured.visual.material, "image", None) is not None:
            mesh = textured
            mesh.visual = mesh.visual.to_color()
    colors = None
    if mesh.visual.kind == "vertex":
        colors = (np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0).astype(np.float32)
    return np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.int32), colors


def _load_glb(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A GLB read per the specification (trisplat.io.gltf.read_glb), colours returned as sRGB display values:
    linear COLOR_0 x baseColorFactor encoded, or the base colour texture at each vertex's uv (nearest texel)."""
    from trisplat.io.colour import linear_to_srgb
    from trisplat.io.gltf import read_glb

    try:
        asset = read_glb(path)
    except (ValueError, KeyError, IndexError, struct.error) as exc:
        raise ValueError(f"{path}: cannot read as .glb ({exc})") from exc
    pos, fac, col, offset, any_colour = [], [], [], 0, False
    for p in asset.primitives:
        m = p.material
        linear = np.tile(m.base_color_factor[:3], (len(p.positions), 1))
        if p.color is not None:
            linear = linear * p.color[:, :3]
            any_colour = True
        if m.image is not None and p.uv is not None:
            h, w = m.image.shape[:2]
            x = np.clip((p.uv[:, 0] * w).astype(np.int64), 0, w - 1)
            y = np.clip((p.uv[:, 1] * h).astype(np.int64), 0, h - 1)
            from trisplat.io.colour import srgb_to_linear

            linear = linear * srgb_to_linear(m.image[y, x, :3] / 255.0)
            any_colour = True
        pos.append(p.positions)
        fac.append(p.faces + offset)
        col.append(linear_to_srgb(linear))
        offset += len(p.positions)
    colors = np.concatenate(col).astype(np.float32) if any_colour else None
    return np.concatenate(pos).astype(np.float32), np.concatenate(fac).astype(np.int32), colors
