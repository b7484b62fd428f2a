"""Render a glTF asset as the glTF 2.0 specification defines it, unlit: what a conforming viewer shows.

Per sample (s x s per pixel): the nearest face (z-buffer, trisplat.texture.raster; back faces culled for
single-sided materials), its attributes interpolated perspective-correctly; base colour = baseColorFactor x COLOR_0
(linear, as stored) x the base colour texture, decoded from sRGB to linear per texel and then filtered bilinearly
(base level, no mipmaps) with the sampler's wrap modes. KHR_materials_unlit: the pixel's linear colour is the base
colour; a material without it is shown unlit too (lighting is outside what a photo comparison can fix), and
`AssetRender.lit_materials` says so. Samples are averaged in linear light (as a multisampled sRGB framebuffer
resolves, and as a camera integrates light), then encoded to sRGB: the values a PNG screenshot holds. The
background is given as an sRGB display colour.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trisplat.io.colour import linear_to_srgb, srgb_to_linear
from trisplat.io.gltf import GltfAsset
from trisplat.texture.raster import surface_samples
from trisplat.texture.sampling import sample_bilinear


@dataclass
class PreparedAsset:
    """An asset's primitives joined into one triangle list, textures decoded to linear once."""

    positions: np.ndarray  # float64 [V,3]
    faces: np.ndarray  # int64 [F,3]
    face_primitive: np.ndarray  # int64 [F]
    single_sided: np.ndarray  # bool [F]
    uv: list  # per primitive: float64 [V_p,2] or None (rows of the joined positions: offset by vertex_offset)
    color: list  # per primitive: float64 [V_p,4] linear or None
    factor: list  # per primitive: float64 [4]
    texture: list  # per primitive: float32 [H,W,3] linear or None
    wrap: list
    vertex_offset: np.ndarray
    lit_materials: int  # primitives whose material is not unlit


def prepare_asset(asset: GltfAsset, transform: np.ndarray | None = None) -> PreparedAsset:
    """Join the primitives (positions mapped by the [4,4] `transform`, e.g. into the frame the cameras live in)."""
    M = np.eye(4) if transform is None else np.asarray(transform, np.float64)
    pos, faces, fprim, single, uv, col, fac, tex, wrap, offs = [], [], [], [], [], [], [], [], [], []
    off, lit = 0, 0
    for k, p in enumerate(asset.primitives):
        m = p.material
        pos.append(p.positions @ M[:3, :3].T + M[:3, 3])
        faces.append(p.faces + off)
        fprim.append(np.full(len(p.faces), k))
        single.append(np.full(len(p.faces), not m.double_sided))
        uv.append(p.uv if m.image is not None else None)
        col.append(p.color)
        fac.append(np.asarray(m.base_color_factor, np.float64))
        tex.append(None if m.image is None or p.uv is None else srgb_to_linear(m.image[..., :3] / np.float32(255.0)))
        wrap.append(m.wrap)
        offs.append(off)
        off += len(p.positions)
        lit += not m.unlit
    if np.linalg.det(M[:3, :3]) < 0:
        faces = [f[:, ::-1] for f in faces]
    return PreparedAsset(np.concatenate(pos), np.concatenate(faces), np.concatenate(fprim), np.concatenate(single),
                         uv, col, fac, tex, wrap, np.asarray(offs), lit)


def vertex_colour_asset(positions, faces, colours) -> PreparedAsset:
    """A mesh with sRGB vertex colours in [0,1] (as a PLY holds them) as the unlit, double-sided asset a viewer
    shows: the colours decoded to linear, then interpolated (what the same mesh written as a GLB holds in COLOR_0)."""
    positions = np.asarray(positions, np.float64)
    faces = np.asarray(faces, np.int64)
    colours = np.asarray(colours, np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or colours.shape != positions.shape:
        raise ValueError(f"positions {positions.shape} and colours {colours.shape} must both be [V,3]")
    lin = np.concatenate([srgb_to_linear(np.clip(colours, 0.0, 1.0)), np.ones((len(colours), 1))], axis=1)
    return PreparedAsset(positions, faces, np.zeros(len(faces), np.int64), np.zeros(len(faces), bool), [None], [lin],
                         [np.ones(4)], [None], [None], np.zeros(1, np.int64), 0)


def mesh_asset(positions, faces, colours, texture=None) -> PreparedAsset:
    """The asset a viewer gets from our exporter's arrays (trisplat.io.export_mesh, in their own frame: no up-axis
    change): vertex colours only (vertex_colour_asset), or with a base-colour TextureMap, through a GLB written and
    read back (what the file holds: 8-bit PNG texels, split seams)."""
    if texture is None:
        return vertex_colour_asset(positions, faces, colours)
    import tempfile
    from pathlib import Path

    from trisplat.io.gltf import read_glb
    from trisplat.io.mesh_files import export_mesh

    with tempfile.TemporaryDirectory(prefix="trisplat-asset-") as tmp:
        path = Path(tmp) / "asset.glb"
        export_mesh(path, positions, faces, colours, up=None, texture=texture)
        return prepare_asset(read_glb(path))


def render_asset(asset: PreparedAsset, world_to_camera: np.ndarray, K: np.ndarray, width: int, height: int,
                 background=(1.0, 1.0, 1.0), supersample: int = 1, near: float = 0.01) -> np.ndarray:
    """float32 [H,W,3] sRGB display values in [0,1] of `asset` seen from the camera (OpenCV axes, the asset's
    frame after prepare_asset's transform)."""
    w2c = np.asarray(world_to_camera, np.float64)
    faces = asset.faces
    keep = np.ones(len(faces), bool)
    if asset.single_sided.any():
        centre = -w2c[:3, :3].T @ w2c[:3, 3]
        tri = asset.positions[faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        front = np.einsum("fi,fi->f", n, centre - tri[:, 0]) > 0
        keep = front | ~asset.single_sided
    kept = np.nonzero(keep)[0]
    ss = surface_samples(asset.positions, faces[kept], w2c, K, width, height, supersample, near)
    s = ss.supersample
    bg_lin = srgb_to_linear(np.asarray(background, np.float64)).astype(np.float32)
    lin = np.empty(ss.face_id.shape + (3,), np.float32)
    lin[:] = bg_lin
    hit = ss.face_id >= 0
    fid = kept[ss.face_id[hit]]
    bary = ss.bary[hit]
    prim = asset.face_primitive[fid]
    out = np.empty((len(fid), 3), np.float32)
    for k in np.unique(prim):
        sel = prim == k
        corners = faces[fid[sel]]  # [n,3] joined vertex rows
        b = bary[sel]
        c = np.tile(asset.factor[k][:3].astype(np.float32), (int(sel.sum()), 1))
        local = corners - asset.vertex_offset[k]
        if asset.color[k] is not None:
            c = c * np.einsum("nk,nkc->nc", b, asset.color[k][local][..., :3]).astype(np.float32)
        if asset.texture[k] is not None:
            uv = np.einsum("nk,nkc->nc", b, asset.uv[k][local])
            c = c * sample_bilinear(asset.texture[k], uv, asset.wrap[k]).astype(np.float32)
        out[sel] = c
    lin[hit] = out
    lin = lin.reshape(height, s, width, s, 3).mean(axis=(1, 3))
    return linear_to_srgb(lin).astype(np.float32)
