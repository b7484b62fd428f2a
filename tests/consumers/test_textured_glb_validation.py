"""A run's textured mesh.glb (baseColorTexture PNG, TEXCOORD_0, KHR_materials_unlit) passes the Khronos glTF validator
with no errors, warnings or hints (tests/io/test_gltf_validation.py covers the untextured exports)."""
from __future__ import annotations

import pytest

from trisplat.bench.consumers import make_tiny_textured_run
from trisplat.io.gltf_validate import find_validator, validate_gltf


def test_textured_run_glb_has_no_validation_messages(tmp_path):
    if find_validator() is None:
        pytest.skip("node or the gltf-validator npm package is missing: run scripts/ci_extras.sh to install it")
    run = make_tiny_textured_run(tmp_path, width=64, height=48, texture_size=128, n_train=4, n_test=1)
    report = validate_gltf(run / "mesh.glb")
    assert report.num_errors == 0, report.errors()
    assert report.num_warnings == 0 and report.num_hints == 0, report.messages
