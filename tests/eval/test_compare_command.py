"""`trisplat compare`: JSON output with the right numbers; a missing LPIPS file gives null plus instructions."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import shared_data
from PIL import Image

from trisplat.cli import main as cli_main
from trisplat.commands.compare import read_rgb
from trisplat.eval.image_metrics import psnr, ssim


def _write(tmp_path, name, arr):
    p = tmp_path / name
    Image.fromarray(arr).save(p)
    return p


def test_compare_prints_metrics(tmp_path, capsys):
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (40, 48, 3), dtype=np.uint8)
    b = np.clip(a.astype(int) + rng.integers(-20, 21, a.shape), 0, 255).astype(np.uint8)
    pa, pb = _write(tmp_path, "a.png", a), _write(tmp_path, "b.png", b)
    weights = shared_data("lpips") / "lpips_alexnet_full_oihw.npz"
    assert cli_main(["compare", str(pa), str(pb), "--lpips-weights", str(weights)]) == 0
    out = json.loads(capsys.readouterr().out)
    fa, fb = a / 255.0, b / 255.0
    mse = np.mean((fa - fb) ** 2)
    assert out["psnr"] == pytest.approx(10 * math.log10(1 / mse), abs=1e-6)
    assert out["ssim"] == pytest.approx(ssim(fa, fb), abs=1e-9)
    assert 0 < out["lpips"] < 1 and "lpips_note" not in out


def test_compare_reference_pair_and_identical(tmp_path, capsys):
    d = shared_data("lpips")
    w = d / "lpips_alexnet_full_oihw.npz"
    assert cli_main(["compare", str(d / "ex_ref.png"), str(d / "ex_p1.png"), "--lpips-weights", str(w)]) == 0
    assert json.loads(capsys.readouterr().out)["lpips"] == pytest.approx(0.138, abs=5e-4)
    assert cli_main(["compare", str(d / "ex_ref.png"), str(d / "ex_ref.png"), "--lpips-weights", str(w)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["psnr"] == "inf" and out["ssim"] == pytest.approx(1.0, abs=1e-6) and out["lpips"] == 0.0


def test_compare_without_weights_reports_null_and_how_to_fix(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("TRISPLAT_LPIPS_WEIGHTS", raising=False)
    a = np.full((16, 16, 3), 100, np.uint8)
    pa, pb = _write(tmp_path, "a.png", a), _write(tmp_path, "b.png", a + 10)
    missing = tmp_path / "missing.npz"
    assert cli_main(["compare", str(pa), str(pb), "--lpips-weights", str(missing)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["lpips"] is None
    assert str(missing) in out["lpips_note"] and f"trisplat lpips-weights --out {missing}" in out["lpips_note"]
    assert out["psnr"] == pytest.approx(psnr(a / 255.0, (a + 10) / 255.0), abs=1e-5)  # images read as float32


def test_compare_errors_name_the_file(tmp_path, capsys):
    a = _write(tmp_path, "a.png", np.zeros((16, 16, 3), np.uint8))
    b = _write(tmp_path, "b.png", np.zeros((16, 20, 3), np.uint8))
    assert cli_main(["compare", str(a), str(b)]) == 1
    assert "b.png: size 20x16 differs from" in capsys.readouterr().err
    assert cli_main(["compare", str(a), str(tmp_path / "nope.png")]) == 1
    assert "nope.png: no such image file" in capsys.readouterr().err
    (tmp_path / "junk.png").write_text("junk")
    assert cli_main(["compare", str(a), str(tmp_path / "junk.png")]) == 1
    assert "junk.png: not a readable image" in capsys.readouterr().err


def test_read_rgb_composites_alpha_over_background(tmp_path):
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[..., 0] = 255
    rgba[:2, :, 3] = 255  # top half opaque red, bottom half transparent
    p = tmp_path / "a.png"
    Image.fromarray(rgba, "RGBA").save(p)
    img = read_rgb(p)
    np.testing.assert_allclose(img[0, 0], [1, 0, 0])
    np.testing.assert_allclose(img[3, 0], [1, 1, 1])
    np.testing.assert_allclose(read_rgb(p, background=(0, 0, 0))[3, 0], [0, 0, 0])
