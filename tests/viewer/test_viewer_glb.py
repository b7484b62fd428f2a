"""The viewer loads RUN/mesh.glb itself (three.js GLTFLoader) and, put exactly at a test camera, shows what the glTF
specification renderer shows for that camera (headless Chromium, SwiftShader WebGL)."""
from __future__ import annotations

import numpy as np
import pytest

from trisplat.bench import consumers
from trisplat.io.gltf import read_glb
from trisplat.viewer.data import viewer_data_from_run
from trisplat.viewer.headless import find_chromium

MIN_PSNR_DB = 30.0  # measured 41.5 dB (docs/benchmarks.md, "Assets scored as files")


@pytest.fixture(scope="module")
def textured_run(tmp_path_factory):
    return consumers.make_tiny_textured_run(tmp_path_factory.mktemp("glb_run"))


def test_run_view_serves_the_glb_placed_on_the_capture_frame(textured_run):
    data = viewer_data_from_run(textured_run)
    assert data.glb == (textured_run / "mesh.glb").read_bytes()
    scene = data.scene_dict()
    assert scene["glb"] is True and len(scene["test_cameras"]) == 2 and len(scene["cameras"]) == 8
    assert [c["split"] for c in scene["test_cameras"]] == ["test", "test"]
    assert scene["test_cameras"][0]["index"] == 8  # numbered after the training cameras (photo URLs)
    # glb_matrix (row-major, relative to origin) maps the file's Y-up positions onto the capture-frame mesh
    M = np.asarray(scene["glb_matrix"]).reshape(4, 4)
    file_pos = np.concatenate([p.positions for p in read_glb(textured_run / "mesh.glb").primitives])
    np.testing.assert_allclose(file_pos @ M[:3, :3].T + M[:3, 3] + data.origin, data.positions, atol=1e-5)
    np.testing.assert_allclose(data.positions.mean(0), 0.0, atol=0.05)  # the sphere sits at the capture's origin
    assert data.image_png(8)[:4] == b"\x89PNG"  # test photos are served too


def test_viewer_at_a_test_camera_matches_the_spec_render(textured_run):
    if find_chromium() is None:
        pytest.skip("no chromium on PATH: `apt-get install chromium` (scripts/ci_extras.sh does it)")
    shot, reports, stderr = consumers.viewer_render(textured_run, 0)
    assert [r for r in reports if r.get("kind") == "error"] == [], stderr[-2000:]
    ready = next(r for r in reports if r.get("kind") == "ready")
    assert ready["glb"] is True and ready["snapped_split"] == "test" and ready["drawn_triangles"] == ready["faces"]
    view = consumers.camera_view(textured_run, 0)
    ref = consumers.spec_render(textured_run, view, consumers.VIEWER_BACKGROUND, supersample=4)
    assert shot.shape == ref.shape == (300, 400, 3)
    p = consumers.psnr_u8(shot, ref)
    print(f"viewer vs spec render: {p:.2f} dB")
    if p < MIN_PSNR_DB:
        # Chromium's --screenshot is taken when its virtual-time budget runs out; once in a full CI run (loaded
        # machine) it caught the page before the mesh was on screen (10.4 dB) although the page reported every
        # triangle drawn, and the same test passed alone and under load. One more screenshot: a viewer that draws
        # the wrong picture fails both.
        shot, _, stderr = consumers.viewer_render(textured_run, 0)
        p = consumers.psnr_u8(shot, ref)
        print(f"viewer vs spec render, second screenshot: {p:.2f} dB")
    assert p >= MIN_PSNR_DB, f"the viewer's picture of mesh.glb differs from the spec render: {p:.2f} dB"
