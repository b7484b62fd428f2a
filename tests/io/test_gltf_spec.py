"""GLB files follow the glTF 2.0 specification: unlit material with a matte fallback, linear COLOR_0, sRGB texture."""
from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import trimesh

from trisplat.io import export_mesh, load_mesh
from trisplat.io.colour import linear_to_srgb, srgb_to_linear
from trisplat.io.gltf import TextureMap, read_glb
from trisplat.io.gltf_validate import find_validator, validate_gltf


def _json(path) -> dict:
    data = path.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20 : 20 + n])


def _textured_sphere():
    m = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(0)
    uv = rng.random((len(m.faces) * 3, 2))
    tex = TextureMap(uv, np.arange(len(m.faces) * 3).reshape(-1, 3), (rng.random((32, 16, 3)) * 255).astype(np.uint8))
    return m, tex


def test_srgb_transfer_is_the_iec_curve_and_inverts():
    x = np.linspace(0, 1, 1001)
    assert np.allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12)
    assert srgb_to_linear(np.array([0.5]))[0] == pytest.approx(0.21404, abs=1e-5)  # the sRGB mid grey
    assert srgb_to_linear(np.array([0.04]))[0] == pytest.approx(0.04 / 12.92)


def test_vertex_colours_are_linear_and_the_material_is_unlit_and_matte(tmp_path):
    m = trimesh.creation.icosphere(subdivisions=2)
    colors = np.random.default_rng(1).random((len(m.vertices), 3))
    export_mesh(tmp_path / "m.glb", m.vertices, m.faces, colors, up="y")
    g = _json(tmp_path / "m.glb")
    mat = g["materials"][0]
    assert "KHR_materials_unlit" in mat["extensions"] and "KHR_materials_unlit" in g["extensionsUsed"]
    assert "KHR_materials_unlit" not in g.get("extensionsRequired", [])  # viewers without it use the fallback
    assert mat["pbrMetallicRoughness"]["metallicFactor"] == 0 and mat["pbrMetallicRoughness"]["roughnessFactor"] == 1
    prim = read_glb(tmp_path / "m.glb").primitives[0]
    srgb8 = np.round(colors * 255) / 255
    # stored: the linear value of each sRGB byte (what the specification says COLOR_0 holds)
    assert np.allclose(prim.color[:, :3], srgb_to_linear(srgb8), atol=1e-6)
    assert not np.allclose(prim.color[:, :3], srgb8, atol=1e-2)
    _, _, back = load_mesh(tmp_path / "m.glb")  # load_mesh hands back display (sRGB) values
    assert np.allclose(back, srgb8, atol=1e-5)


def test_textured_glb_and_obj_carry_the_texture(tmp_path):
    m, tex = _textured_sphere()
    export_mesh(tmp_path / "m.glb", m.vertices, m.faces, np.full((len(m.vertices), 3), 0.5), up=None, texture=tex)
    g = _json(tmp_path / "m.glb")
    assert g["images"][0]["mimeType"] == "image/png"
    assert g["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] == {"index": 0}
    assert "COLOR_0" not in g["meshes"][0]["primitives"][0]["attributes"]  # it would multiply the texture
    prim = read_glb(tmp_path / "m.glb").primitives[0]
    assert np.array_equal(prim.material.image, tex.image)
    # every corner keeps its position and its uv
    corners = prim.positions[prim.faces].reshape(-1, 3)
    assert np.allclose(corners, m.vertices[m.faces].reshape(-1, 3), atol=1e-6)
    assert np.allclose(prim.uv[prim.faces].reshape(-1, 2), tex.uv[tex.uv_faces].reshape(-1, 2), atol=1e-7)
    written = export_mesh(tmp_path / "m.obj", m.vertices, m.faces, None, texture=tex)
    assert (tmp_path / "m.png").is_file() and "map_Kd m.png" in (tmp_path / "m.mtl").read_text()
    assert len(written) == 3
    obj = trimesh.load(tmp_path / "m.obj", process=False)
    assert obj.visual.kind == "texture" and np.asarray(obj.visual.material.image).shape[:2] == (32, 16)


@pytest.mark.parametrize("textured", [True, False])
def test_validator_reports_no_errors_and_no_warnings(tmp_path, textured):
    if find_validator() is None:
        pytest.skip("node or the gltf-validator npm package is missing: run scripts/ci_extras.sh to install it")
    m, tex = _textured_sphere()
    colors = np.random.default_rng(2).random((len(m.vertices), 3))
    export_mesh(tmp_path / "m.glb", m.vertices, m.faces, colors, up="y", texture=tex if textured else None)
    report = validate_gltf(tmp_path / "m.glb")
    assert (report.num_errors, report.num_warnings, report.num_infos, report.num_hints) == (0, 0, 0, 0), report.messages
