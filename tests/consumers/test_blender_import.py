"""Blender as a real consumer of mesh.glb: bpy's glTF importer reads it without warnings, and Cycles (CPU, unlit as the
file says, 'Standard' view transform) renders a test camera as trisplat's glTF specification renderer does.

bpy 5.0 needs numpy < 2 and lives in its own environment ($TRISPLAT_BPY_PYTHON or .cache/bpy-venv, made by
`bash scripts/ci_extras.sh --blender`); the test skips without it."""
from __future__ import annotations

import pytest

from trisplat.bench import consumers

MIN_PSNR_DB = 35.0  # measured 51.8 dB (docs/benchmarks.md, "Assets scored as files")


def test_blender_imports_without_warnings_and_cycles_matches_the_spec_render(tmp_path):
    if consumers.bpy_python() is None:
        pytest.skip(f"no Python with bpy: run `bash scripts/ci_extras.sh --blender` (makes {consumers.DEFAULT_BPY_PYTHON}) "
                    f"or set {consumers.BPY_PYTHON_ENV}")
    run = consumers.make_tiny_textured_run(tmp_path)
    view = consumers.camera_view(run, 0, shift_px=(6.0, -4.0))  # an off-centre principal point: the lens shift
    image, report = consumers.blender_render(run / "mesh.glb", view, view.background, samples=64)
    assert report["result"] == ["FINISHED"]
    assert report["import_warnings"] == [], report["output"]
    assert report["meshes"] == 1 and report["materials"] == ["trisplat_unlit"]
    assert "ShaderNodeEmission" in report["shader_nodes"] or "ShaderNodeBackground" in report["shader_nodes"]
    ref = consumers.spec_render(run, view, view.background, supersample=4)
    p = consumers.psnr_u8(image, ref)
    print(f"Blender {report['blender']} Cycles vs spec render: {p:.2f} dB")
    assert p >= MIN_PSNR_DB, f"Blender's picture of mesh.glb differs from the spec render: {p:.2f} dB"
