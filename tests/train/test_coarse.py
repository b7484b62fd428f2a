"""Coarse-to-fine training (trisplat.train.coarse, schedules.coarse): the coarse view is the full view's image
area-averaged (checked through the renderer's own supersampling), the photo is averaged the same way, the schedule
turns the coarse steps on only early and only on images large enough, and a coarse run learns."""
import dataclasses
import json

import numpy as np
import pytest
import torch

from trisplat import run as layout
from trisplat.train import schedules
from trisplat.train.coarse import coarse_intrinsics, coarse_photo, coarse_size
from trisplat.train.config import make_config

from tests.train.test_trainer import _trainer, tiny_scene  # noqa: F401 (the fixture)


@pytest.mark.parametrize("linear_light", [False, True])
def test_coarse_render_is_the_full_render_area_averaged(tiny_scene, tmp_path, linear_light):  # noqa: F811
    # 2x2 samples of a coarse pixel sit exactly on the 4 full-resolution pixel centres it covers, so a coarse render
    # with supersample 2 is the full render box-filtered: that holds only if K/2 keeps the +0.5 pixel-centre rule
    # and the image is cropped to whole blocks (39 px wide: the last column is left out)
    tr = _trainer(tiny_scene, tmp_path / "r")
    tr.ts.linear_light = linear_light
    tr.data.cameras[0] = dataclasses.replace(tr.data.cameras[0], width=39, height=38)  # a crop: odd width
    full = tr.render(0, 0.3).rgb.detach()
    coarse = tr.render(0, 0.3, coarse=2, supersample=2).rgb.detach()
    assert coarse.shape == (19, 19, 3)
    np.testing.assert_allclose(coarse.numpy(), coarse_photo(full, 2, linear_light).numpy(), atol=2e-5)
    # and not the same as shifting the principal point by a pixel (what a K that ignored the +0.5 rule would give)
    assert np.abs(coarse.numpy() - coarse_photo(torch.roll(full, 1, dims=1), 2, linear_light).numpy()).max() > 0.05


def test_coarse_photo_averages_blocks():
    img = torch.rand(7, 9, 3)
    out = coarse_photo(img, 2)
    assert out.shape == (3, 4, 3)
    torch.testing.assert_close(out[1, 2], img[2:4, 4:6].mean(dim=(0, 1)))
    lin = coarse_photo(img, 2, linear_light=True)
    from trisplat.io.colour import linear_to_srgb, srgb_to_linear

    want = linear_to_srgb(srgb_to_linear(img[2:4, 4:6].numpy().astype(np.float64)).mean(axis=(0, 1)))
    np.testing.assert_allclose(lin[1, 2].numpy(), want, atol=1e-5)
    assert abs(float(lin[1, 2, 0]) - float(out[1, 2, 0])) > 0 or img[2:4, 4:6, 0].std() == 0
    assert coarse_photo(img, 1) is img


def test_coarse_intrinsics_and_size():
    K = torch.tensor([[100.0, 0.0, 40.0], [0.0, 90.0, 30.0], [0.0, 0.0, 1.0]], requires_grad=True)
    Kc = coarse_intrinsics(K, 4)
    torch.testing.assert_close(Kc, torch.tensor([[25.0, 0.0, 10.0], [0.0, 22.5, 7.5], [0.0, 0.0, 1.0]]))
    Kc.sum().backward()  # refined intrinsics keep their gradient through the scaling
    torch.testing.assert_close(K.grad, torch.tensor([[0.25] * 3, [0.25] * 3, [1.0] * 3]))
    assert coarse_size(399, 266, 2) == (199, 133)


def test_schedule_coarse_only_early_and_on_large_images():
    cfg = make_config("default", coarse_until=0.1, coarse_factor=2, supersample_2x_from=0.85)
    assert schedules.coarse(0.05, cfg, 399, 266) == 2
    assert schedules.coarse(0.1, cfg, 399, 266) == 1
    assert schedules.coarse(0.05, cfg, 399, 150) == 1  # 75 px short side at 1/2: below coarse_min_px
    assert schedules.pixel_cost(0.05, cfg, 399, 266) == pytest.approx(0.25)
    assert schedules.pixel_cost(0.9, cfg, 399, 266) == pytest.approx(4.0)  # 2x2 supersampling from 0.85
    assert schedules.coarse(0.05, make_config("default"), 399, 266) == 1  # off unless asked
    with pytest.raises(ValueError, match="coarse_factor"):
        make_config("default", coarse_factor=3)
    with pytest.raises(ValueError, match="coarse_until"):
        make_config("default", coarse_until=1.0)


def test_coarse_run_learns_and_renders_coarse_early(tiny_scene, tmp_path, monkeypatch):  # noqa: F811
    tr = _trainer(tiny_scene, tmp_path / "c", coarse_until=0.5, coarse_min_px=16)
    before = tr.evaluate(0.0)
    sizes = []
    render = tr.render

    def spy(*a, **k):
        out = render(*a, **k)
        sizes.append(tuple(out.rgb.shape[:2]))
        return out

    monkeypatch.setattr(tr, "render", spy)
    tr.train()
    hist = [json.loads(line) for line in (tmp_path / "c" / layout.HISTORY).read_text().splitlines()]
    losses = [h["loss"] for h in hist if "loss" in h]
    # the first half of the 40 steps at 20x20, none after (evaluations render at 40x40)
    assert sizes[:20] == [(20, 20)] * 20 and (20, 20) not in sizes[20:]
    assert np.mean(losses[12:20]) < 0.85 * np.mean(losses[:6])
    assert json.loads((tmp_path / "c" / layout.METRICS).read_text())["psnr"] > before + 1.0
