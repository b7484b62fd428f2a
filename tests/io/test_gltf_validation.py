"""GLB exports pass the Khronos glTF validator (npm gltf-validator through node) with zero errors."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from trisplat.io import export_mesh
from trisplat.io.gltf_validate import find_validator, validate_gltf


@pytest.fixture
def validator():
    if find_validator() is None:
        pytest.skip("node or the gltf-validator npm package is missing: run scripts/ci_extras.sh to install it")


@pytest.mark.parametrize("coloured", [True, False])
def test_glb_export_has_no_validation_errors(tmp_path, validator, coloured):
    m = trimesh.creation.icosphere(subdivisions=3)
    colors = np.random.default_rng(0).random((len(m.vertices), 3)) if coloured else None
    export_mesh(tmp_path / "m.glb", m.vertices, m.faces, colors, up="y")
    report = validate_gltf(tmp_path / "m.glb")
    assert report.num_errors == 0, report.errors()
    assert report.num_warnings == 0, report.messages
    assert report.num_hints == 0, report.messages  # bufferView targets are set


def test_validator_reports_errors_in_a_broken_file(tmp_path, validator):
    m = trimesh.creation.box()
    data = bytearray(export_mesh(tmp_path / "m.glb", m.vertices, m.faces)[0].read_bytes())
    data[-40:] = b"\xff" * 40  # corrupt the tail of the binary chunk (the index buffer)
    (tmp_path / "bad.glb").write_bytes(bytes(data))
    assert validate_gltf(tmp_path / "bad.glb").num_errors > 0
