"""Binary glTF 2.0 (.glb), written and read back as the specification defines it.

Written: one mesh, one triangle primitive, one unlit material (KHR_materials_unlit, with a pbrMetallicRoughness
fallback of metallic 0 / roughness 1 for viewers without the extension, so they show a matte surface, not glTF's
default full metal). Colour is either a baseColorTexture (an sRGB PNG, as the specification requires for base
colour textures) addressed by TEXCOORD_0, or per-vertex COLOR_0 in LINEAR light (float32), converted from our sRGB
display values. The mesh is double-sided (our z-buffer shows both sides of a face).

Read (`read_glb`): every triangle primitive of the default scene with its node transforms, TEXCOORD_0, COLOR_0 and
the material's base colour factor / texture / sampler, as raw data; trisplat.eval.spec_render turns them into
pixels.
"""
from __future__ import annotations

import io
import json
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trisplat.io.atomic import atomic_write_bytes
from trisplat.io.colour import srgb_to_linear

GL_ARRAY_BUFFER, GL_ELEMENT_ARRAY_BUFFER = 34962, 34963
GL_FLOAT, GL_UNSIGNED_BYTE, GL_UNSIGNED_SHORT, GL_UNSIGNED_INT, GL_BYTE, GL_SHORT = 5126, 5121, 5123, 5125, 5120, 5122
GL_LINEAR, GL_LINEAR_MIPMAP_LINEAR = 9729, 9987
GL_CLAMP_TO_EDGE, GL_REPEAT, GL_MIRRORED_REPEAT = 33071, 10497, 33648
MODE_TRIANGLES = 4
UNLIT = "KHR_materials_unlit"
_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_DTYPES = {GL_FLOAT: np.float32, GL_UNSIGNED_BYTE: np.uint8, GL_UNSIGNED_SHORT: np.uint16, GL_UNSIGNED_INT: np.uint32,
           GL_BYTE: np.int8, GL_SHORT: np.int16}


@dataclass(frozen=True)
class TextureMap:
    """A base-colour texture on a mesh: `uv` [U,2] texture coordinates in glTF's convention (u right, v DOWN: (0, 0)
    is the top-left corner of `image`'s first row), `uv_faces` [F,3] the uv row of each face corner (the mesh's
    faces index positions, these index uv, so vertices stay welded where the OBJ format allows it), `image` uint8
    [H,W,3], sRGB-encoded."""

    uv: np.ndarray
    uv_faces: np.ndarray
    image: np.ndarray

    def __post_init__(self):
        if self.uv.ndim != 2 or self.uv.shape[1] != 2:
            raise ValueError(f"uv must be [U,2], got {self.uv.shape}")
        if self.uv_faces.ndim != 2 or self.uv_faces.shape[1] != 3:
            raise ValueError(f"uv_faces must be [F,3], got {self.uv_faces.shape}")
        if self.uv_faces.size and (self.uv_faces.min() < 0 or self.uv_faces.max() >= len(self.uv)):
            raise ValueError("uv_faces index rows outside uv")
        if self.image.dtype != np.uint8 or self.image.ndim != 3 or self.image.shape[2] != 3:
            raise ValueError(f"image must be uint8 [H,W,3], got {self.image.dtype} {self.image.shape}")

    def png_bytes(self) -> bytes:
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(self.image, "RGB").save(buf, format="PNG", optimize=False, compress_level=6)
        return buf.getvalue()


def split_vertices(faces: np.ndarray, texture: TextureMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One vertex per (position, uv) pair, as glTF needs: (position row [N], uv row [N], faces over these [F,3])."""
    faces, uvf = np.asarray(faces, np.int64), np.asarray(texture.uv_faces, np.int64)
    if faces.shape != uvf.shape:
        raise ValueError(f"faces {faces.shape} and uv_faces {uvf.shape} differ")
    pairs = np.stack([faces.ravel(), uvf.ravel()], 1)
    uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return uniq[:, 0], uniq[:, 1], inverse.reshape(-1, 3)


class _Builder:
    """Accumulates bufferViews and accessors in one binary buffer (each view 4-byte aligned)."""

    def __init__(self):
        self.chunks: list[bytes] = []
        self.offset = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        v = {"buffer": 0, "byteOffset": self.offset, "byteLength": len(data)}
        if target is not None:
            v["target"] = target
        pad = b"\x00" * (-len(data) % 4)
        self.chunks.append(data + pad)
        self.offset += len(data) + len(pad)
        self.views.append(v)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, kind: str, target: int, minmax: bool = False) -> int:
        ctype = {np.dtype(np.float32): GL_FLOAT, np.dtype(np.uint32): GL_UNSIGNED_INT}[array.dtype]
        acc = {"bufferView": self.view(np.ascontiguousarray(array).tobytes(), target), "componentType": ctype,
               "count": int(array.shape[0]) if kind != "SCALAR" else int(array.size), "type": kind}
        if minmax:
            a = array.reshape(-1, _COMPONENTS[kind])
            acc["min"], acc["max"] = a.min(0).tolist(), a.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def glb_bytes(positions: np.ndarray, faces: np.ndarray, rgb8: np.ndarray | None = None,
              texture: TextureMap | None = None) -> bytes:
    """A GLB of one mesh (see the module docstring). positions float [V,3] (already Y-up), faces int [F,3]
    (counter-clockwise = front), rgb8 uint8 [V,3] sRGB vertex colours (written as linear COLOR_0; ignored with a
    texture), texture: the base colour (vertices are split along its seams)."""
    positions = np.asarray(positions, np.float32)
    faces = np.asarray(faces, np.int64)
    b = _Builder()
    attributes: dict[str, int] = {}
    pbr: dict = {"metallicFactor": 0.0, "roughnessFactor": 1.0}
    gltf: dict = {"asset": {"version": "2.0", "generator": "trisplat"}}
    if texture is not None:
        pos_rows, uv_rows, faces = split_vertices(faces, texture)
        positions = positions[pos_rows]
        attributes["POSITION"] = b.accessor(positions, "VEC3", GL_ARRAY_BUFFER, minmax=True)
        attributes["TEXCOORD_0"] = b.accessor(np.asarray(texture.uv, np.float32)[uv_rows], "VEC2", GL_ARRAY_BUFFER)
        image_view = b.view(texture.png_bytes())
        gltf["images"] = [{"bufferView": image_view, "mimeType": "image/png"}]
        gltf["samplers"] = [{"magFilter": GL_LINEAR, "minFilter": GL_LINEAR_MIPMAP_LINEAR, "wrapS": GL_CLAMP_TO_EDGE,
                             "wrapT": GL_CLAMP_TO_EDGE}]
        gltf["textures"] = [{"sampler": 0, "source": 0}]
        pbr["baseColorTexture"] = {"index": 0}
    else:
        attributes["POSITION"] = b.accessor(positions, "VEC3", GL_ARRAY_BUFFER, minmax=True)
        if rgb8 is not None:
            linear = srgb_to_linear(np.asarray(rgb8, np.float64) / 255.0).astype(np.float32)
            attributes["COLOR_0"] = b.accessor(linear, "VEC3", GL_ARRAY_BUFFER)
    indices = b.accessor(faces.astype(np.uint32).ravel(), "SCALAR", GL_ELEMENT_ARRAY_BUFFER)
    gltf.update({
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "trisplat"}],
        "meshes": [{"name": "trisplat", "primitives": [{"attributes": attributes, "indices": indices, "material": 0,
                                                         "mode": MODE_TRIANGLES}]}],
        "materials": [{"name": "trisplat_unlit", "pbrMetallicRoughness": pbr, "doubleSided": True,
                       "extensions": {UNLIT: {}}}],
        "extensionsUsed": [UNLIT],
        "accessors": b.accessors, "bufferViews": b.views, "buffers": [{"byteLength": b.offset}],
    })
    # key order as in the specification's examples (asset first); json keeps insertion order
    gltf = {"asset": gltf.pop("asset"), **gltf}
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    binary = b"".join(b.chunks)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
            + struct.pack("<I4s", len(binary), b"BIN\x00") + binary)


def write_glb(path: str | Path, positions, faces, rgb8=None, texture: TextureMap | None = None) -> Path:
    path = Path(path)
    atomic_write_bytes(path, glb_bytes(positions, faces, rgb8, texture))
    return path


# ---------------------------------------------------------------------------------------------------- reading


@dataclass
class GltfMaterial:
    """What an unlit render needs from a glTF material (the specification's defaults when absent)."""

    base_color_factor: np.ndarray = field(default_factory=lambda: np.ones(4))
    image: np.ndarray | None = None  # the base colour texture as stored: uint8 [H,W,C], sRGB-encoded
    texcoord: int = 0
    wrap: tuple[int, int] = (GL_REPEAT, GL_REPEAT)  # (wrapS, wrapT)
    unlit: bool = False
    double_sided: bool = False
    alpha_mode: str = "OPAQUE"


@dataclass
class GltfPrimitive:
    """One triangle primitive in the scene's frame (node transforms applied): positions float64 [V,3], faces
    int64 [F,3], uv float64 [V,2] or None, color float64 [V,4] LINEAR or None, material."""

    positions: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None
    color: np.ndarray | None
    material: GltfMaterial


@dataclass
class GltfAsset:
    primitives: list[GltfPrimitive]
    extensions_used: list[str]


def _parse_glb(data: bytes) -> tuple[dict, bytes]:
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2:
        raise ValueError("not a glTF 2.0 binary file")
    off, gltf, binary = 12, None, b""
    while off < min(length, len(data)):
        clen, ctype = struct.unpack_from("<I4s", data, off)
        chunk = data[off + 8 : off + 8 + clen]
        if ctype == b"JSON":
            gltf = json.loads(chunk)
        elif ctype == b"BIN\x00":
            binary = chunk
        off += 8 + clen
    if gltf is None:
        raise ValueError("GLB without a JSON chunk")
    return gltf, binary


def _view_bytes(gltf: dict, binary: bytes, index: int) -> tuple[bytes, int | None]:
    v = gltf["bufferViews"][index]
    if v.get("buffer", 0) != 0 or "uri" in gltf["buffers"][v.get("buffer", 0)]:
        raise ValueError("only the GLB's own binary buffer is supported")
    start = v.get("byteOffset", 0)
    return binary[start : start + v["byteLength"]], v.get("byteStride")


def _accessor(gltf: dict, binary: bytes, index: int) -> np.ndarray:
    """An accessor as float64 [count, components]; normalized integers mapped to [0, 1] / [-1, 1] as specified."""
    a = gltf["accessors"][index]
    if "sparse" in a or "bufferView" not in a:
        raise ValueError("sparse or buffer-less accessors are not supported")
    dt = np.dtype(_DTYPES[a["componentType"]]).newbyteorder("<")
    nc, count = _COMPONENTS[a["type"]], a["count"]
    raw, stride = _view_bytes(gltf, binary, a["bufferView"])
    elem = dt.itemsize * nc
    stride = stride or elem
    buf = np.frombuffer(raw, np.uint8, count=(count - 1) * stride + elem, offset=a.get("byteOffset", 0))
    rows = np.lib.stride_tricks.as_strided(buf, shape=(count, elem), strides=(stride, 1))
    out = np.ascontiguousarray(rows).view(dt).reshape(count, nc).astype(np.float64)
    if a.get("normalized", False):
        info = np.iinfo(dt)
        out = np.maximum(out / info.max, -1.0)
    return out


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T  # column-major
    T, R, S = np.eye(4), np.eye(4), np.eye(4)
    T[:3, 3] = node.get("translation", [0, 0, 0])
    x, y, z, w = node.get("rotation", [0, 0, 0, 1])
    R[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    S[:3, :3] = np.diag(node.get("scale", [1, 1, 1]))
    return T @ R @ S


def _material(gltf: dict, binary: bytes, index: int | None) -> GltfMaterial:
    if index is None:
        return GltfMaterial()
    m = gltf["materials"][index]
    pbr = m.get("pbrMetallicRoughness", {})
    mat = GltfMaterial(base_color_factor=np.asarray(pbr.get("baseColorFactor", [1, 1, 1, 1]), np.float64),
                       unlit=UNLIT in m.get("extensions", {}), double_sided=bool(m.get("doubleSided", False)),
                       alpha_mode=m.get("alphaMode", "OPAQUE"))
    info = pbr.get("baseColorTexture")
    if info is not None:
        if "KHR_texture_transform" in info.get("extensions", {}):
            raise ValueError("KHR_texture_transform is not supported")
        tex = gltf["textures"][info["index"]]
        img = gltf["images"][tex["source"]]
        if "bufferView" not in img:
            raise ValueError("only images stored in the GLB are supported")
        from PIL import Image

        raw, _ = _view_bytes(gltf, binary, img["bufferView"])
        pil = Image.open(io.BytesIO(raw))
        pil = pil.convert("RGBA" if pil.mode in ("RGBA", "LA", "P") else "RGB")
        mat.image = np.asarray(pil, np.uint8)
        mat.texcoord = int(info.get("texCoord", 0))
        s = gltf.get("samplers", [])[tex["sampler"]] if "sampler" in tex else {}
        mat.wrap = (int(s.get("wrapS", GL_REPEAT)), int(s.get("wrapT", GL_REPEAT)))
    return mat


def read_glb(path: str | Path) -> GltfAsset:
    """Every triangle primitive of a .glb's default scene (see GltfPrimitive), as the specification defines them."""
    path = Path(path)
    gltf, binary = _parse_glb(path.read_bytes())
    required = set(gltf.get("extensionsRequired", []))
    if required:
        raise ValueError(f"{path}: required extensions are not supported: {sorted(required)}")
    scenes = gltf.get("scenes", [{"nodes": list(range(len(gltf.get("nodes", []))))}])
    roots = scenes[gltf.get("scene", 0)].get("nodes", [])
    prims: list[GltfPrimitive] = []
    stack = [(n, np.eye(4)) for n in roots]
    while stack:
        ni, parent = stack.pop()
        node = gltf["nodes"][ni]
        M = parent @ _node_matrix(node)
        stack += [(c, M) for c in node.get("children", [])]
        if "mesh" not in node:
            continue
        for p in gltf["meshes"][node["mesh"]]["primitives"]:
            if p.get("mode", MODE_TRIANGLES) != MODE_TRIANGLES:
                continue
            att = p["attributes"]
            pos = _accessor(gltf, binary, att["POSITION"])
            pos = pos @ M[:3, :3].T + M[:3, 3]
            idx = (_accessor(gltf, binary, p["indices"]).astype(np.int64).ravel() if "indices" in p
                   else np.arange(len(pos)))
            faces = idx.reshape(-1, 3)
            if np.linalg.det(M[:3, :3]) < 0:
                faces = faces[:, ::-1]
            mat = _material(gltf, binary, p.get("material"))
            uv = _accessor(gltf, binary, att[f"TEXCOORD_{mat.texcoord}"]) if f"TEXCOORD_{mat.texcoord}" in att \
                else None
            color = None
            if "COLOR_0" in att:
                color = _accessor(gltf, binary, att["COLOR_0"])
                if color.shape[1] == 3:
                    color = np.column_stack([color, np.ones(len(color))])
            prims.append(GltfPrimitive(positions=pos, faces=faces, uv=uv, color=color, material=mat))
    if not prims:
        raise ValueError(f"{path}: no triangle primitive in the default scene")
    return GltfAsset(primitives=prims, extensions_used=list(gltf.get("extensionsUsed", [])))
