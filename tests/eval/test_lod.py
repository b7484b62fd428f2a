"""`trisplat eval RUN --lod N...`: each level is a real decimated GLB, scored exactly as `--file` scores it, and a
coarser level of a curved surface scores worse; the report gets one PSNR-against-faces section."""
from __future__ import annotations

import json

import numpy as np
import pytest
from test_eval_command import _make_run

from trisplat.cli import main as cli_main
from trisplat.eval.file_scores import evaluate_file
from trisplat.eval.lod import LOD_METRICS, LOD_PLOT, evaluate_lod
from trisplat.eval.views import evaluate_run
from trisplat.io.gltf import read_glb


@pytest.fixture(scope="module")
def sphere_run(tmp_path_factory):
    run, _ = _make_run(tmp_path_factory.mktemp("lod"), "sphere")
    evaluate_run(run, "test", "hard", report=True)  # the model's report the levels are added to
    return run


def test_levels_are_decimated_files_scored_like_any_file(sphere_run):
    out = sphere_run / "eval_test_lod"
    points = evaluate_lod(sphere_run, [40, 200], texture_size=0, out_dir=out, show_progress=False)
    assert [p.faces_requested for p in points] == [200, 40]  # most faces first, no mesh.glb in this run
    for p in points:
        assert sum(len(prim.faces) for prim in read_glb(p.file).primitives) == p.faces
        assert 0.5 * p.faces_requested <= p.faces <= 1.05 * p.faces_requested
        again = evaluate_file(sphere_run, p.file, "test", out_dir=out / "again", report=False, show_progress=False)
        assert again.psnr == pytest.approx(p.psnr, abs=1e-9)
    # 40 faces cannot hold a sphere's silhouette and colour ramp the way 200 do
    assert points[1].psnr < points[0].psnr - 0.5
    saved = json.loads((out / LOD_METRICS).read_text())
    assert [lv["faces"] for lv in saved["levels"]] == [p.faces for p in points]
    assert (out / LOD_PLOT).stat().st_size > 1000
    page = (sphere_run / "eval_test" / "report.html").read_text()
    assert page.count("<div id='lod'>") == 1 and f"{points[1].faces} (asked 40)" in page
    assert f"glTF spec render, {len(evaluate_run(sphere_run, 'test', 'hard', report=False).views)} views" in page
    evaluate_lod(sphere_run, [100], texture_size=0, out_dir=out, show_progress=False)  # replaces the section
    page = (sphere_run / "eval_test" / "report.html").read_text()
    assert page.count("<div id='lod'>") == 1 and "(asked 100)" in page and "(asked 40)" not in page


def test_lod_command_checks_its_options(sphere_run, tmp_path, capsys):
    with pytest.raises(ValueError, match="at least 1"):
        evaluate_lod(sphere_run, [0, 50], texture_size=0, out_dir=tmp_path / "x", show_progress=False)
    assert cli_main(["eval", str(sphere_run), "--lod", "50", "--file", "mesh.glb"]) != 0
    assert "cannot be combined with --file" in capsys.readouterr().err
    out = tmp_path / "lod"
    assert cli_main(["eval", str(sphere_run), "--lod", "60", "--texture-size", "0", "--out", str(out)]) == 0
    assert "faces" in capsys.readouterr().out
    assert cli_main(["eval", str(sphere_run), "--lod", "60", "--out", str(out)]) != 0
    assert LOD_METRICS in capsys.readouterr().err
    levels = json.loads((out / LOD_METRICS).read_text())["levels"]
    assert len(levels) == 1 and levels[0]["texture_size"] == 0 and np.isfinite(levels[0]["psnr"])
