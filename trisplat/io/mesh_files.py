"""Coloured triangle meshes on disk: .ply, .obj (+ .mtl) and .glb writers and readers, registered by suffix."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from plyfile import PlyData, PlyElement

from trisplat.io.atomic import atomic_target, atomic_write_bytes, atomic_write_text
from trisplat.io.axes import up_rotation

MTL_MATERIAL = "default"
GLTF_SUFFIXES = (".glb",)  # formats whose specification fixes the up axis (+Y)
GL_ARRAY_BUFFER, GL_ELEMENT_ARRAY_BUFFER = 34962, 34963  # glTF bufferView.target values


@dataclass(frozen=True)
class MeshFormat:
    """One file format: `write(path, positions, faces, rgb8) -> files written`, `read(path) -> trimesh`."""

    suffix: str
    description: str
    write: Callable[[Path, np.ndarray, np.ndarray, np.ndarray | None], list[Path]]


def _write_ply(path: Path, positions: np.ndarray, faces: np.ndarray, rgb8: np.ndarray | None) -> list[Path]:
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


def _write_obj(path: Path, positions: np.ndarray, faces: np.ndarray, rgb8: np.ndarray | None) -> list[Path]:
    mtl = path.with_suffix(".mtl")
    atomic_write_text(
        mtl,
        f"# trisplat: colours are per vertex in {path.name}; this material only makes them visible\n"
        f"newmtl {MTL_MATERIAL}\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nNs 1\nd 1\nillum 1\n"
    )
    lines = ["# trisplat mesh: 'v x y z r g b' with vertex colours in [0, 1]", f"mtllib {mtl.name}"]
    if rgb8 is not None:
        v = np.column_stack([positions.astype(np.float64), rgb8 / 255.0])
        lines += [f"v {x:.9g} {y:.9g} {z:.9g} {r:.6f} {g:.6f} {b:.6f}" for x, y, z, r, g, b in v.tolist()]
    else:
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in positions.astype(np.float64).tolist()]
    lines.append(f"usemtl {MTL_MATERIAL}")
    lines += [f"f {a} {b} {c}" for a, b, c in (faces.astype(np.int64) + 1).tolist()]
    atomic_write_text(path, "\n".join(lines) + "\n")
    return [path, mtl]


def _write_glb(path: Path, positions: np.ndarray, faces: np.ndarray, rgb8: np.ndarray | None) -> list[Path]:
    colors = None if rgb8 is None else np.column_stack([rgb8, np.full(len(rgb8), 255, np.uint8)])
    mesh = trimesh.Trimesh(positions, faces, vertex_colors=colors, process=False)
    atomic_write_bytes(path, _with_buffer_view_targets(mesh.export(file_type="glb")))
    return [path]


def _with_buffer_view_targets(glb: bytes) -> bytes:
    """Set bufferView.target (vertex data / indices) in a GLB's JSON chunk, which trimesh leaves out and the
    glTF validator hints about."""
    magic, version, _ = struct.unpack_from("<4sII", glb, 0)
    json_len, json_type = struct.unpack_from("<I4s", glb, 12)
    if magic != b"glTF" or json_type != b"JSON":
        raise ValueError("trimesh wrote a GLB without a leading JSON chunk")
    gltf = json.loads(glb[20 : 20 + json_len])
    views, accessors = gltf.get("bufferViews", []), gltf.get("accessors", [])
    for mesh in gltf.get("meshes", []):
        for prim in mesh.get("primitives", []):
            for acc in prim.get("attributes", {}).values():
                views[accessors[acc]["bufferView"]]["target"] = GL_ARRAY_BUFFER
            if "indices" in prim:
                views[accessors[prim["indices"]]["bufferView"]]["target"] = GL_ELEMENT_ARRAY_BUFFER
    chunk = json.dumps(gltf, separators=(",", ":")).encode()
    chunk += b" " * (-len(chunk) % 4)
    rest = glb[20 + json_len :]
    header = struct.pack("<4sII", magic, version, 12 + 8 + len(chunk) + len(rest))
    return header + struct.pack("<I4s", len(chunk), b"JSON") + chunk + rest


FORMATS: dict[str, MeshFormat] = {
    ".ply": MeshFormat(".ply", "binary PLY, per-vertex RGB uchar", _write_ply),
    ".obj": MeshFormat(".obj", "Wavefront OBJ ('v x y z r g b') with an MTL holding one default material", _write_obj),
    ".glb": MeshFormat(".glb", "binary glTF 2.0, vertex colours in COLOR_0", _write_glb),
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
) -> list[Path]:
    """Write a coloured mesh; the format comes from the suffix (see FORMATS). Returns the files written.

    positions [V,3], faces [F,3] (counter-clockwise = outward), colors [V,3] in [0,1] or None (stored as 8-bit).
    transform: optional [4,4] applied to the positions first (e.g. the inverse scene normalisation).
    up: None keeps the axes; 'y' / 'z' then rotates so that `capture_up` (default: see `up_rotation`) becomes
    +Y / +Z; 'auto' (default) is 'y' for .glb (glTF is Y-up by definition, engines show a Z-up mesh on its side)
    and None for the other formats. A transform that mirrors (negative determinant) flips the winding so normals
    stay outward.
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
    rgb8 = None if colors is None else np.round(colors * 255.0).astype(np.uint8)
    if not path.parent.exists():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    return fmt.write(path, positions.astype(np.float32), faces.astype(np.int32), rgb8)


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
