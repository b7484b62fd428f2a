"""The eval report shows the bare surface (grey, headlight-lit hard render) beside the coloured render for a few
views, and its page lays out correctly in headless Chromium (the per-view table rows stay table rows)."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

from trisplat.cameras import Camera
from trisplat.eval.views import SHADED_ALBEDO, SHADED_AMBIENT, REPORT_SHADED_VIEWS, evaluate_run, render_shaded
from trisplat.scene.model import TriangleScene

CHROMIUM_TIMEOUT_S = 120


def _plane(z: float, tilt: float, rgb) -> TriangleScene:
    """Two triangles covering x, y in [-1, 1] at depth z (+ tilt * x), counter-clockwise seen from the camera."""
    pos = np.array([[-1, -1, z - tilt], [1, -1, z + tilt], [1, 1, z + tilt], [-1, 1, z - tilt]], np.float32)
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    return TriangleScene.from_rgb(pos, faces, np.tile(np.asarray(rgb, np.float32), (4, 1)), opacity=0.999)


CAM = Camera(np.eye(4), np.array([[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]]), 32, 32)


def test_shaded_surface_is_grey_headlight_lambert_whatever_the_colours():
    bg = (1.0, 1.0, 1.0)
    red = render_shaded(_plane(2.0, 0.0, (1, 0, 0)), CAM, bg)
    blue = render_shaded(_plane(2.0, 0.0, (0, 0, 1)), CAM, bg)
    np.testing.assert_array_equal(red, blue)  # colour plays no part
    assert np.allclose(red[..., 0], red[..., 1]) and np.allclose(red[..., 1], red[..., 2])  # grey
    # the pixel at the principal point looks straight at a plane facing the camera: full headlight
    assert red[16, 16, 0] == pytest.approx(SHADED_ALBEDO, abs=2e-3)
    # off-axis pixels see it at an angle: |n . d| = 1 / |(x, y, 1)| on the unit ray
    y, x = 16, 7
    d = np.array([(x + 0.5 - 16) / 20, (y + 0.5 - 16) / 20, 1.0])
    expect = SHADED_ALBEDO * (SHADED_AMBIENT + (1 - SHADED_AMBIENT) / np.linalg.norm(d))
    assert red[y, x, 0] == pytest.approx(expect, abs=2e-3)
    # the plane covers |x|, |y| <= 1 at depth 2: pixels beyond 16 +- 10 are background
    assert np.all(red[:, :5] == 1.0) and np.all(red[:5] == 1.0)
    # a tilted plane is darker at the centre, and supersampling averages the samples of each pixel
    tilted = render_shaded(_plane(2.0, 0.8, (1, 0, 0)), CAM, bg)
    assert tilted[16, 16, 0] < red[16, 16, 0] - 0.05
    # with fx = 21 the plane's edge (x = -1 at depth 2) falls in the middle of pixel column 5: at 2x2 samples per
    # pixel that column averages two background and two surface samples
    cam21 = Camera(np.eye(4), np.array([[21.0, 0, 16], [0, 21.0, 16], [0, 0, 1]]), 32, 32)
    one, two = (render_shaded(_plane(2.0, 0.0, (1, 0, 0)), cam21, bg, supersample=s) for s in (1, 2))
    assert two.shape == one.shape == (32, 32, 3)
    assert one[16, 6, 0] < two[16, 5, 0] < 1.0 and two[16, 5, 0] == pytest.approx((1.0 + one[16, 6, 0]) / 2, abs=0.02)


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """A 'finished' run whose model is the true mesh, evaluated on 6 test views."""
    from true_mesh_run import write_true_mesh_run

    _, run, _ = write_true_mesh_run(tmp_path_factory.mktemp("report"), n_train=2, n_test=6, width=32, height=32)
    (run / "history.jsonl").write_text("".join(json.dumps({"step": s, "wall_s": s, "psnr": 20 + s, "faces": 100})
                                               + "\n" for s in (1, 2, 3)))
    m = evaluate_run(run, "test", "hard", show_progress=False)
    return run / "eval_test", m


def test_report_shows_the_surface_beside_the_render_for_a_few_views(evaluated):
    out, m = evaluated
    page = (out / "report.html").read_text()
    shaded = sorted((out / "images").glob("*_shaded.png"))
    assert 1 <= len(shaded) <= REPORT_SHADED_VIEWS < len(m.views)
    for p in shaded:
        stem = p.name[: -len("_shaded.png")]
        # in the view's row of pictures, right after the coloured render
        assert re.search(f"{stem}_render.png'[^<]*>(<figcaption>[^<]*</figcaption></figure>)?\\s*<figure><img "
                         f"src='images/{stem}_shaded.png'", page), stem
        from PIL import Image

        img = np.asarray(Image.open(p)).astype(int)
        assert (np.abs(img[..., 0] - img[..., 1]) <= 1).all()  # grey, though the mesh is coloured
        assert img.min() < 200  # the surface is there, not only background


def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if path := shutil.which(name):
            return path
    pytest.skip("no chromium on PATH: `apt-get install chromium` (scripts/ci_extras.sh does it)")


PROBE = """<script>window.addEventListener('load', () => {
  const tr = document.querySelector('tr.view'), div = document.querySelector('div.view');
  const cells = [...tr.children].map(td => Math.round(td.getBoundingClientRect().top));
  const broken = [...document.images].filter(i => !i.complete || i.naturalWidth === 0).map(i => i.src);
  document.body.setAttribute('data-probe', JSON.stringify({
    tr: getComputedStyle(tr).display, div: getComputedStyle(div).display, cellTops: cells,
    broken: broken, images: document.images.length}));
});</script>"""


def test_report_page_lays_out_in_headless_chromium(evaluated):
    chromium = _chromium()
    out, m = evaluated
    page = (out / "report.html").read_text()
    with tempfile.TemporaryDirectory(prefix="trisplat-report-") as tmp:
        probe = out / "probe.html"
        probe.write_text(page.replace("</body>", PROBE + "</body>"))
        try:
            proc = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                                   f"--user-data-dir={tmp}/profile", "--allow-file-access-from-files",
                                   "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()],
                                  capture_output=True, text=True, timeout=CHROMIUM_TIMEOUT_S)
        finally:
            probe.unlink()
    found = re.search(r"data-probe=\"([^\"]*)\"", proc.stdout)
    assert found, f"chromium gave no probe result (rc {proc.returncode}): {proc.stderr[-2000:]}"
    import html

    probe_result = json.loads(html.unescape(found.group(1)))
    assert probe_result["tr"] == "table-row"  # `.view{display:flex}` made the table rows flex boxes
    assert probe_result["div"] == "flex"
    assert len(set(probe_result["cellTops"])) == 1  # a row's cells side by side
    assert probe_result["broken"] == [] and probe_result["images"] >= 3 * len(m.views)


DEMO_PROBE = """<script>window.addEventListener('load', () => {
  const broken = [...document.images].filter(i => !i.complete || i.naturalWidth === 0).map(i => i.src);
  document.body.setAttribute('data-probe', JSON.stringify({broken: broken, images: document.images.length}));
});</script>"""


def _probe(page_path: Path, script: str) -> dict:
    """Load page_path with `script` appended in headless Chromium and return what the script recorded."""
    import html

    chromium = _chromium()
    probe = page_path.with_name("probe.html")
    probe.write_text(page_path.read_text().replace("</body>", script + "</body>"))
    with tempfile.TemporaryDirectory(prefix="trisplat-page-") as tmp:
        try:
            proc = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                                   f"--user-data-dir={tmp}/profile", "--allow-file-access-from-files",
                                   "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()],
                                  capture_output=True, text=True, timeout=CHROMIUM_TIMEOUT_S)
        finally:
            probe.unlink()
    found = re.search(r"data-probe=\"([^\"]*)\"", proc.stdout)
    assert found, f"chromium gave no probe result (rc {proc.returncode}): {proc.stderr[-2000:]}"
    return json.loads(html.unescape(found.group(1)))


def test_demo_page_pairs_every_render_with_its_ground_truth_in_chromium(tmp_path):
    """The demo's index.html shows each test render beside the photo of the same name: every picture loads."""
    from PIL import Image

    from trisplat.commands.demo import write_page

    out = tmp_path / "demo"
    (out / "scene" / "test").mkdir(parents=True)
    renders = out / "run" / "renders"
    renders.mkdir(parents=True)
    for name in ("r_0", "r_1"):
        Image.new("RGB", (8, 8), (200, 10, 10)).save(out / "scene" / "test" / f"{name}.png")
        Image.new("RGB", (8, 8), (10, 200, 10)).save(renders / f"{name}.png")
    (out / "run" / "metrics.json").write_text(json.dumps({"psnr": 30.0, "ssim": 0.9, "lpips": None, "faces": 10,
                                                          "vertices": 8, "steps": 5, "wall_s": 60.0}))
    page = write_page(out, out / "run")
    result = _probe(page, DEMO_PROBE)
    assert result["images"] == 4 and result["broken"] == []
