"""One rule for every command: never replace a user's file without --force, and check the inputs before touching
any output (a refusal, or a bad input, changes nothing on disk)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from trisplat.cli import main as cli_main


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A small capture and a 'finished' run of it whose model is the true mesh."""
    from true_mesh_run import write_true_mesh_run

    _, run, _ = write_true_mesh_run(tmp_path_factory.mktemp("overwrite"), n_train=3, n_test=1, width=24, height=24,
                                    grey=True)
    return run


def _snapshot(folder):
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_eval_keeps_the_trainings_evaluation_without_force(run, capsys):
    ev = run / "eval_test"
    ev.mkdir(exist_ok=True)
    (ev / "metrics.json").write_text('{"psnr": 25.98, "written_by": "training"}')
    before = _snapshot(ev)
    assert cli_main(["eval", str(run), "--max-views", "1"]) == 1
    err = capsys.readouterr().err
    assert "would overwrite" in err and "eval_test/metrics.json" in err and "--force" in err and "--out" in err
    assert _snapshot(ev) == before
    assert cli_main(["eval", str(run), "--max-views", "1", "--force"]) == 0
    assert json.loads((ev / "metrics.json").read_text())["split"] == "test"


def test_eval_of_images_too_small_for_lpips_scores_the_rest(run, tmp_path, monkeypatch):
    # with LPIPS weights present, 24x24 views cannot feed AlexNet: LPIPS is null with a note, the rest is scored
    from conftest import shared_data

    weights = shared_data("lpips") / "lpips_alexnet_full_oihw.npz"
    if not weights.is_file():
        pytest.skip(f"LPIPS weights not found at {weights}")
    monkeypatch.setenv("TRISPLAT_LPIPS_WEIGHTS", str(weights))
    out = tmp_path / "ev"
    assert cli_main(["eval", str(run), "--max-views", "1", "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["lpips"] is None and "at least 31x31" in m["lpips_note"] and "24x24" in m["lpips_note"]
    assert m["psnr"] > 10


def test_mesh_refuses_an_existing_output_before_triangulating(run, tmp_path, capsys, monkeypatch):
    import trisplat.mesh.connect as connect

    target = tmp_path / "existing.ply"
    target.write_bytes(b"the user's mesh")
    monkeypatch.setattr(connect, "connect_faces", lambda *a, **k: pytest.fail("triangulated before the check"))
    assert cli_main(["mesh", str(run), "--out", str(target)]) == 1
    assert "would overwrite" in capsys.readouterr().err and target.read_bytes() == b"the user's mesh"
    assert cli_main(["mesh", str(run), "--out", str(tmp_path / "x.stl")]) == 1
    assert "unknown mesh format '.stl'" in capsys.readouterr().err
    monkeypatch.undo()
    assert cli_main(["mesh", str(run), "--out", str(target), "--force"]) == 0
    assert target.read_bytes() != b"the user's mesh"


def test_extract_refuses_to_replace_an_earlier_extraction(run, tmp_path, capsys):
    masks = tmp_path / "masks"
    masks.mkdir()
    Image.fromarray(np.full((24, 24), 255, np.uint8)).save(masks / "r_0.png")
    out = tmp_path / "cut"
    assert cli_main(["extract", str(run), "--masks", str(masks), "--out", str(out)]) == 0
    before = _snapshot(out)
    assert cli_main(["extract", str(run), "--masks", str(masks), "--out", str(out), "--ratio", "0.9"]) == 1
    assert "would overwrite" in capsys.readouterr().err and _snapshot(out) == before
    assert cli_main(["extract", str(run), "--masks", str(masks), "--out", str(out), "--force"]) == 0


def test_train_force_checks_the_capture_before_moving_the_old_run(run, tmp_path, capsys):
    old = tmp_path / "old"
    old.mkdir()
    (old / "config.json").write_text(json.dumps({"data": "somewhere"}))
    (old / "state.json").write_text(json.dumps({"finished": True, "step": 5, "total_steps": 5}))
    before = _snapshot(old)
    assert cli_main(["train", str(tmp_path / "no-such-capture"), "--out", str(old), "--force", "--quiet"]) == 1
    assert "no-such-capture" in capsys.readouterr().err
    assert _snapshot(old) == before and not list(tmp_path.glob("old.old-*"))  # nothing was moved aside


def test_render_and_demo_check_their_options_before_the_long_work(run, tmp_path, capsys, monkeypatch):
    """Cheap checks first: render refuses --device cuda without CUDA, export a bad --faces or --texture-size, before
    loading the model; demo refuses a bad
    --steps / --minutes before generating its scene (a minute of ray casting)."""
    import torch

    import trisplat.run
    import trisplat.synth

    def never(*a, **k):
        raise AssertionError("the long work started before the cheap checks")

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(trisplat.run.Run, "load_model", never)
    assert cli_main(["render", str(run), "--out", str(tmp_path / "r"), "--device", "cuda"]) == 1
    assert "device 'cuda'" in capsys.readouterr().err and not (tmp_path / "r").exists()

    for bad, said in ((["--faces", "0"], "--faces must be at least 1"), (["--texture-size", "-4"], "--texture-size")):
        assert cli_main(["export", str(run), "--out", str(tmp_path / "e"), *bad]) == 1
        assert said in capsys.readouterr().err and not (tmp_path / "e").exists()

    monkeypatch.setattr(trisplat.synth, "write_blender_scene", never)
    for bad, said in ((["--steps", "0"], "--steps must be at least 1"), (["--minutes", "-1"], "--minutes must be > 0")):
        assert cli_main(["demo", "--out", str(tmp_path / "demo"), *bad]) == 1
        assert said in capsys.readouterr().err and not (tmp_path / "demo").exists()
