"""Views keep their source photo's name wherever a user sees one, also when the loader cached a downscaled copy
under a hashed name: render outputs, the run's test renders and mask matching (`extract --masks`)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from trisplat.cli import main as cli_main


@pytest.fixture(scope="module")
def downscaled_run(tmp_path_factory):
    """A capture, and a 'trained' run of it at --downscale 2 whose model is the true mesh."""
    from true_mesh_run import write_true_mesh_run

    capture, run, data = write_true_mesh_run(tmp_path_factory.mktemp("names"), n_train=4, n_test=2, width=40,
                                             height=40, grey=True, downscale=2)
    return capture, run, data


def test_the_cache_renames_images(downscaled_run):
    """The premise: the loader's downscaled copies carry a hash in their names."""
    _, _, data = downscaled_run
    cam = data.cameras[int(data.test_indices[0])]
    assert cam.image_path.stem != "r_0" and cam.image_path.stem.startswith("r_0-")
    assert cam.stem == "r_0" and cam.width == 20


def test_render_names_outputs_after_the_source_photos(downscaled_run, tmp_path):
    _, run, _ = downscaled_run
    out = tmp_path / "renders"
    assert cli_main(["render", str(run), "--split", "test", "--out", str(out), "--supersample", "1"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["r_0.png", "r_1.png"]
    assert Image.open(out / "r_0.png").size == (20, 20)
    # train/r_0.png and test/r_0.png share a stem: with both splits their relative paths name them; r_2 and r_3
    # (training views only) keep their own names
    both = tmp_path / "all"
    assert cli_main(["render", str(run), "--split", "all", "--out", str(both), "--supersample", "1"]) == 0
    assert sorted(p.name for p in both.iterdir()) == sorted(
        ["train_r_0.png", "train_r_1.png", "r_2.png", "r_3.png", "test_r_0.png", "test_r_1.png"])


def test_render_refuses_before_writing_anything(downscaled_run, tmp_path, capsys):
    _, run, _ = downscaled_run
    out = tmp_path / "renders"
    out.mkdir()
    (out / "r_1.png").write_bytes(b"mine")
    assert cli_main(["render", str(run), "--split", "test", "--out", str(out), "--supersample", "1"]) == 1
    assert "r_1.png exists; pass --force" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["r_1.png"]  # r_0.png was not written either
    assert (out / "r_1.png").read_bytes() == b"mine"
    assert cli_main(["render", str(run), "--split", "test", "--out", str(out), "--supersample", "1",
                     "--force"]) == 0
    assert (out / "r_1.png").read_bytes() != b"mine"


def test_masks_named_after_photos_match_a_downscaled_run(downscaled_run, tmp_path):
    _, run, data = downscaled_run
    masks = tmp_path / "masks"
    masks.mkdir()
    for i in range(2):  # full-size masks named like the photos (train/r_0.png -> r_0.png), the whole view white
        Image.fromarray(np.full((40, 40), 255, np.uint8)).save(masks / f"r_{i}.png")
    out = tmp_path / "extract"
    assert cli_main(["extract", str(run), "--masks", str(masks), "--out", str(out)]) == 0
    summary = json.loads((out / "extract.json").read_text())
    assert summary["masks"] == 2 and summary["object_faces"] > 0
