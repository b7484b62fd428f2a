"""The HTML report on synthetic inputs: its pictures exist and show the inputs, its numbers match metrics.json."""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from html.parser import HTMLParser

import numpy as np
import pytest
from PIL import Image

from trisplat.eval.image_metrics import psnr, ssim
from trisplat.eval.report import (ERROR_MAP_MAX, SplitMetrics, ViewImages, ViewMetrics, error_map, json_safe,
                                  write_metrics, write_report)


class _Page(HTMLParser):
    """Collects <img src>, and the data-value of metric cells keyed by (row name, metric)."""

    def __init__(self):
        super().__init__()
        self.imgs: list[str] = []
        self.cells: dict[tuple[str, str], str] = {}
        self._row = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a["src"])
        if tag == "tr" and "data-name" in a:
            self._row = a["data-name"]
        if tag == "td" and self._row is not None and a.get("class") in ("psnr", "ssim", "lpips"):
            self.cells[(self._row, a["class"])] = a["data-value"]


def _synthetic(seed: int = 0, n: int = 3):
    rng = np.random.default_rng(seed)
    views, images = [], []
    for k in range(n):
        gt = rng.random((24, 32, 3)).astype(np.float32)
        render = gt if k == 0 else np.clip(gt + 0.05 * k * rng.standard_normal(gt.shape), 0, 1).astype(np.float32)
        name = f"r_{k}"
        views.append(ViewMetrics(index=10 + k, name=name, psnr=psnr(gt, render), ssim=ssim(gt, render),
                                 lpips=None if k == 0 else 0.1 * k))
        images.append(ViewImages(name=name, gt=gt, render=render))
    return views, images


@dataclass
class _Stats:
    faces: int
    vertices: int
    watertight: bool

    def to_dict(self):
        return {"faces": self.faces, "vertices": self.vertices, "watertight": self.watertight}


def test_report_pictures_and_numbers_match_metrics_json(tmp_path):
    views, images = _synthetic()
    views[0].lpips = 0.0
    metrics = SplitMetrics(split="test", mode="hard", views=views, render_seconds=1.5)
    history = [{"step": s, "wall_s": 0.5 * s, "psnr": 20 + s / 10, "faces": 100 + s} for s in range(1, 50)]
    history += [{"step": s, "wall_s": 0.5 * s, "test_psnr": 19 + s / 10, "faces": 100 + s} for s in (10, 20, 30)]
    mj = write_metrics(tmp_path, metrics)
    page = write_report(tmp_path, metrics, images, history=history, mesh_stats=_Stats(123, 77, False),
                        config={"steps": 50, "sigma_end": 1e-4}, title="tiny <run>")
    assert page == tmp_path / "report.html"
    text = page.read_text()
    parsed = _Page()
    parsed.feed(text)

    # every picture the page references exists; the view pictures are the inputs (to 8-bit rounding)
    assert len(parsed.imgs) == 1 + 3 * len(images)
    for src in parsed.imgs:
        assert (tmp_path / src).is_file(), src
    for k, vi in enumerate(images):
        gt = np.asarray(Image.open(tmp_path / f"images/{k:03d}_gt.png"), dtype=np.float32) / 255
        rd = np.asarray(Image.open(tmp_path / f"images/{k:03d}_render.png"), dtype=np.float32) / 255
        np.testing.assert_allclose(gt, vi.gt, atol=0.5 / 255 + 1e-6)
        np.testing.assert_allclose(rd, vi.render, atol=0.5 / 255 + 1e-6)
    err0 = np.asarray(Image.open(tmp_path / "images/000_error.png"))
    assert (err0 == err0[0, 0]).all()  # identical view -> uniform "zero error" colour

    # numbers on the page == metrics.json, which == the inputs
    saved = json.loads(mj.read_text())
    assert saved["views"][0]["psnr"] == "inf"
    for v in saved["views"]:
        for key in ("psnr", "ssim", "lpips"):
            assert parsed.cells[(v["name"], key)] == (str(v[key]) if isinstance(v[key], str) else repr(v[key]))
    means = SplitMetrics.from_dict(saved)
    assert means.psnr == math.inf  # one identical view makes the mean PSNR infinite, and the page says so
    assert parsed.cells[("mean", "psnr")] == "inf"
    assert float(parsed.cells[("mean", "ssim")]) == pytest.approx(saved["ssim"], abs=0)
    assert float(parsed.cells[("mean", "lpips")]) == pytest.approx(np.mean([0.0, 0.1, 0.2]), abs=1e-12)
    assert saved["lpips"] == pytest.approx(0.1, abs=1e-12)

    # mesh statistics, config and escaping
    assert re.search(r"<th>faces</th><td>123</td>", text)
    assert re.search(r"<th>watertight</th><td>False</td>", text)
    assert "&quot;sigma_end&quot;: 0.0001" in text
    assert "<title>tiny &lt;run&gt;</title>" in text


def test_metrics_json_round_trip(tmp_path):
    views, _ = _synthetic(1)
    m = SplitMetrics(split="train", mode="soft", views=views, lpips_note="no weights", extra={"sigma": 0.01})
    back = SplitMetrics.from_dict(json.loads(write_metrics(tmp_path, m).read_text()))
    assert back.views == m.views and back.extra == {"sigma": 0.01} and back.lpips_note == "no weights"
    assert back.lpips is None  # one view without LPIPS -> no mean LPIPS rather than a biased one


def test_lpips_note_and_no_history(tmp_path):
    views, images = _synthetic(2, n=2)
    for v in views:
        v.lpips = None
    m = SplitMetrics(split="test", mode="hard", views=views, lpips_note="LPIPS weights not found at /x")
    text = write_report(tmp_path, m, images[:1]).read_text()
    assert "LPIPS not computed: LPIPS weights not found at /x" in text
    assert "training_curves" not in text and not (tmp_path / "images/training_curves.png").exists()
    assert "1 of 2 views shown" in text


def test_report_rejects_images_without_metrics(tmp_path):
    views, images = _synthetic(3, n=2)
    m = SplitMetrics(split="test", mode="hard", views=views[:1])
    with pytest.raises(ValueError, match="'r_1' has no metrics entry"):
        write_report(tmp_path, m, images)


def test_error_map_scale():
    gt = np.zeros((2, 3, 3))
    render = np.zeros((2, 3, 3))
    render[0, 0] = ERROR_MAP_MAX
    render[0, 1] = 2 * ERROR_MAP_MAX  # saturates
    m = error_map(gt, render)
    assert m.dtype == np.uint8 and m.shape == (2, 3, 3)
    assert (m[0, 0] == m[0, 1]).all() and not (m[0, 0] == m[1, 1]).all()
    assert m[1, 1].sum() < 10  # zero error is (near) black


def test_json_safe():
    assert json_safe({"a": [math.inf, -math.inf, 1.5], "b": math.nan}) == {"a": ["inf", "-inf", 1.5], "b": "nan"}
