"""Every run ends well (issue 26, items 2 and 3): every preset whose output is a surface switches to one (a bare
TrainConfig too, and a surface without a switch point is refused by name); a switch that raises, whatever the error,
leaves a run that goes on as a soup, says so, records the failure in its checkpoint at once (a resumed run does not
try the same switch again) and can be finished otherwise with `--resume --output soup` or `--resume --connect-at P`;
the final line says plainly when the result is a soup and why."""
import json
import shutil

import numpy as np
import pytest
import torch

from trisplat import run as layout
from trisplat.cli import main as cli_main
from trisplat.train.checkpoint import load_checkpoint
from trisplat.train.config import PRESETS, SURFACE_SWITCH_AT, TrainConfig, make_config

# a few hundred steps on 40x40 photos: colours learned fast, no soup pruning before the switch (the paper's pruning
# schedule assumes thousands of steps), no texture, little scoring
QUICK = dict(sh_degree=1, max_vertices=3000, eval_every=0.5, eval_max_views=1, checkpoint_every_s=1e9, num_renders=1,
             eval_supersample=1, prune_from=0.6, lr_sh_dc=0.02, lr_opacity=0.05, surface_face_ratio=1.0,
             texture_size=0)
QUICK_ARGS = ["--quiet"]  # a resumed run keeps the saved settings


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """A colour-gradient sphere seen from all around (12 training views, 40x40): one closed object, so the switch's
    surface is one piece; returns (capture folder, mesh)."""
    import trimesh

    from trisplat.synth import write_blender_scene

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    c = (mesh.vertices - mesh.vertices.min(0)) / np.ptp(mesh.vertices, 0)
    mesh.visual.vertex_colors = (np.c_[0.2 + 0.6 * c, np.ones(len(c))] * 255).astype(np.uint8)
    out = tmp_path_factory.mktemp("finish") / "sphere"
    write_blender_scene(out, mesh, n_train=12, n_test=2, width=40, height=40, samples_per_pixel=1, n_points=0,
                        elevation_deg=(-60.0, 80.0))
    return out, mesh


def _trainer(sphere, run_dir, preset="full", **over):
    """A trainer of `preset` with QUICK settings on the sphere, initialised with grey soup triangles on surface
    samples (the geometry roughly right: a few hundred steps then make a soup worth fusing)."""
    import trimesh

    from trisplat.data import load_dataset
    from trisplat.scene.init import init_soup
    from trisplat.train.trainer import Trainer

    scene, mesh = sphere
    cfg = make_config(preset, **{**QUICK, **over})
    opts = {"downscale": 1, "background": list(cfg.background), "test_every": cfg.test_every,
            "format": cfg.data_format}
    data = load_dataset(scene, **opts)
    pts, _ = trimesh.sample.sample_surface(mesh, 400, seed=0)
    pts = (np.c_[pts, np.ones(len(pts))] @ data.normalization.T)[:, :3]
    initial, _ = init_soup(pts, np.full((len(pts), 3), 0.5), seed=0, sh_degree=cfg.sh_degree)
    return Trainer(cfg, data, run_dir, initial=initial, show_progress=False, data_options=opts,
                   data_path=str(scene))


def _history(run) -> list[dict]:
    return [json.loads(line) for line in (run / layout.HISTORY).read_text().splitlines() if line.strip()]


def _pieces(run) -> int:
    from trisplat.commands.mesh_stats import read_mesh
    from trisplat.mesh.stats import mesh_statistics

    v, f = read_mesh(run / "mesh.ply")
    return mesh_statistics(v, f).connected_components


def _done_line(out: str) -> str:
    lines = [line for line in out.splitlines() if line.startswith(("done", "finished"))]
    assert len(lines) == 1, out
    return lines[0]


# ------------------------------------------------------------------------------------------------ item 2: presets
def test_every_surface_preset_and_a_bare_config_switch():
    for name in PRESETS:
        cfg = make_config(name)
        assert cfg.output == "surface" and cfg.switch_at is not None, name
    assert make_config("full").switch_at == SURFACE_SWITCH_AT
    assert TrainConfig().switch_at == SURFACE_SWITCH_AT
    # a surface without a switch point cannot be made; the error names the option and the way to a soup
    with pytest.raises(ValueError, match="connect_at is None but output is 'surface'.*--connect-at.*--output soup"):
        TrainConfig(connect_at=None)
    assert TrainConfig(connect_at=None, output="soup").switch_at is None
    with pytest.raises(ValueError, match=r"\[0, 1\)"):  # a switch at progress 1 never happens (the last step < 1)
        TrainConfig(connect_at=1.0)


def test_connect_at_none_on_the_command_line_is_refused_by_name(sphere, tmp_path, capsys):
    rc = cli_main(["train", str(sphere[0]), "--out", str(tmp_path / "run"), "--connect-at", "None", "--quiet"])
    assert rc == 1 and "--connect-at" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_full_preset_ends_in_one_connected_surface(sphere, tmp_path):
    """--preset full (no connect_at before issue 26: it ended as a soup) at 300 steps on the small sphere."""
    run = tmp_path / "full"
    tr = _trainer(sphere, run, steps=300)
    result = tr.train()
    assert tr.connected
    switch = [h for h in _history(run) if "switch" in h]
    assert [h["step"] for h in switch] == [int(SURFACE_SWITCH_AT * 300)]
    assert _pieces(run) == 1  # the exported mesh is one connected piece
    m = json.loads((run / layout.METRICS).read_text())
    assert m["connected"] and not m["switch_failed"] and m["switch_failure"] is None
    assert m["mesh"]["connected_components"] == 1 and m["mesh"]["non_manifold_edges"] == 0
    assert result.scene.num_vertices < result.scene.num_faces  # welded (a soup has 3 vertices per face)


# ------------------------------------------------------------------------------------- item 3: a failed switch
STEPS = 100  # the switch at 0.6 is step 60


class Killed(BaseException):
    """Stands for the process being killed (not an Exception: the trainer must not catch it)."""


@pytest.fixture(scope="module")
def failed_run(sphere, tmp_path_factory):
    """A run whose switch raised MemoryError at step 60 and that was killed two steps later, before any periodic
    checkpoint (checkpoint_every_s 1e9: last.pt is step 0's). Returns (run folder, what the failed run logged)."""
    import trisplat.train.switch as switch_mod

    run = tmp_path_factory.mktemp("failed") / "run"
    calls = []

    def out_of_memory(*a, **k):
        calls.append(1)
        raise MemoryError("injected: the fusion grid needs 40 GB")

    mp = pytest.MonkeyPatch()
    mp.setattr(switch_mod, "soup_to_surface", out_of_memory)
    try:
        tr = _trainer(sphere, run, steps=STEPS, connect_at=SURFACE_SWITCH_AT)  # (explicit: the old full had none)
        real_step = tr.train_step

        def step():
            if tr.step == 62:
                raise Killed
            return real_step()

        tr.train_step = step
        with pytest.raises(Killed):
            tr.train()
    finally:
        mp.undo()
    assert calls == [1] and tr.switch_failed and not tr.connected
    return run, _history(run)


def _copy(run, dest):
    shutil.copytree(run, dest)
    return dest


def test_a_failed_switch_is_said_and_recorded_in_the_checkpoint_at_once(failed_run):
    run, history = failed_run
    failed = [h for h in history if "switch_failed" in h]
    assert len(failed) == 1 and failed[0]["step"] == 60
    assert failed[0]["error"] == "MemoryError: injected: the fusion grid needs 40 GB"
    # the message says how to go on
    assert "--resume --connect-at" in failed[0]["switch_failed"] and "--resume --output soup" in \
        failed[0]["switch_failed"]
    ckpt = load_checkpoint(run / layout.CHECKPOINT)
    assert ckpt["step"] == 0  # the last good state (no periodic checkpoint) ...
    extra = ckpt["extra"]  # ... with the failure noted, so that a resumed run does not try the same switch again
    assert extra["switch_failed"] and not extra["connected"]
    assert extra["switch_failure"]["step"] == 60 and extra["switch_failure"]["connect_at"] == SURFACE_SWITCH_AT


def test_plain_resume_after_a_failed_switch_does_not_retry_it_and_ends_as_a_soup_saying_why(
        failed_run, sphere, tmp_path, capsys, monkeypatch):
    import trisplat.train.switch as switch_mod

    run = _copy(failed_run[0], tmp_path / "run")
    calls = []
    monkeypatch.setattr(switch_mod, "soup_to_surface", lambda *a, **k: calls.append(1) or 1 / 0)
    assert cli_main(["train", str(sphere[0]), "--out", str(run), "--resume", *QUICK_ARGS]) == 0
    assert calls == []  # the failure was in the checkpoint: the same switch is not tried again (nor forever)
    m = json.loads((run / layout.METRICS).read_text())
    assert not m["connected"] and m["switch_failed"] and m["switch_failure"]["error"].startswith("MemoryError")
    assert m["steps"] == STEPS
    line = _done_line(capsys.readouterr().out)
    assert "a triangle soup, NOT a connected surface: the switch to a surface failed at step 60 " \
           "(MemoryError: injected: the fusion grid needs 40 GB)" in line


def test_resume_with_output_soup_finishes_a_run_whose_switch_failed(failed_run, sphere, tmp_path, capsys):
    run = _copy(failed_run[0], tmp_path / "run")
    assert cli_main(["train", str(sphere[0]), "--out", str(run), "--resume", "--output", "soup", *QUICK_ARGS]) == 0
    assert json.loads((run / layout.CONFIG).read_text())["output"] == "soup"
    m = json.loads((run / layout.METRICS).read_text())
    assert m["steps"] == STEPS and m["output"] == "soup" and not m["connected"]
    scene, _ = layout.open_run(run).load_model()
    assert scene.num_vertices > scene.num_faces and m["mesh"]["connected_components"] > 100  # a soup, in shards
    line = _done_line(capsys.readouterr().out)
    assert "a triangle soup, as --output soup asked after the switch to a surface failed at step 60" in line
    # every step logged once though steps 0-62 were computed twice
    assert [h["step"] for h in _history(run) if "loss" in h] == list(range(10, STEPS + 1, 10))  # log_every 10


def test_resume_with_a_later_connect_at_switches_there(failed_run, sphere, tmp_path, capsys):
    """The switch works again (no injected error): --resume --connect-at 0.9 tries it at step 90 and the run ends as
    one connected surface; the sharpness keeps the schedule the soup trained with (no jump at the resume)."""
    run = _copy(failed_run[0], tmp_path / "run")
    before = {h["step"]: h["sigma"] for h in failed_run[1] if "sigma" in h}
    assert cli_main(["train", str(sphere[0]), "--out", str(run), "--resume", "--connect-at", "0.9",
                     *QUICK_ARGS]) == 0
    history = _history(run)
    assert [h["step"] for h in history if "switch" in h] == [90]
    assert [h["step"] for h in history if "switch_retry" in h] == [0]
    after = {h["step"]: h["sigma"] for h in history if "sigma" in h}
    assert all(after[s] == pytest.approx(v) for s, v in before.items())  # steps replayed with the same sigma
    m = json.loads((run / layout.METRICS).read_text())
    assert m["connected"] and not m["switch_failed"] and m["steps"] == STEPS
    assert _pieces(run) == 1
    assert "(one connected surface" in _done_line(capsys.readouterr().out)
    # once switched, how the run is finished can no longer change
    rc = cli_main(["train", str(sphere[0]), "--out", str(run), "--resume", "--output", "soup", "--quiet"])
    assert rc == 1 and "already switched to a connected surface" in capsys.readouterr().err


@pytest.mark.parametrize("error", ["numba", "os", "index"])
def test_any_error_of_the_switch_leaves_the_soup_training(sphere, tmp_path, monkeypatch, error):
    """Not only ValueError/MemoryError/RuntimeError: a Numba typing error, an OSError, a plain bug (IndexError).
    The soup the switch started from is what training goes on with."""
    import trisplat.train.switch as switch_mod

    def raises(*a, **k):
        if error == "numba":
            from numba.core.errors import TypingError

            raise TypingError("injected: no matching definition")
        if error == "os":
            raise OSError(28, "No space left on device")
        return [][0]

    monkeypatch.setattr(switch_mod, "soup_to_surface", raises)
    tr = _trainer(sphere, tmp_path / "run", steps=12, connect_at=0.5, num_renders=0)
    soup_faces = []
    real = tr._connect

    def connect():
        soup_faces.append(tr.ts.faces.clone())
        real()

    tr._connect = connect
    tr.finish = lambda: {}
    result = tr.train()
    assert result.steps == 12 and tr.switch_failed and not tr.connected
    assert torch.equal(result.scene.faces, soup_faces[0])  # the soup went on (no training changes the faces)


def test_keyboard_interrupt_in_the_switch_is_not_swallowed(sphere, tmp_path, monkeypatch):
    import trisplat.train.switch as switch_mod

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(switch_mod, "soup_to_surface", interrupted)
    tr = _trainer(sphere, tmp_path / "run", steps=12, connect_at=0.5)
    with pytest.raises(KeyboardInterrupt):
        tr.train()
    assert not tr.switch_failed


# ------------------------------------------------------------------------------- item 3: resume rules, no training
def _saved(**over) -> dict:
    return {**json.loads(json.dumps(make_config("full").to_dict())), "data": "x", "data_options": {}, **over}


def test_resume_config_lets_how_the_run_is_finished_change_until_it_switched(tmp_path):
    from trisplat.commands.train import resume_config

    given = make_config("full", connect_at=0.9)
    cfg = resume_config(tmp_path, _saved(), given, {"connect_at"})
    assert cfg.connect_at == 0.9 and cfg.steps == 30_000
    cfg = resume_config(tmp_path, _saved(), make_config("full", output="soup"), {"output"})
    assert cfg.output == "soup" and cfg.switch_at is None
    # a run whose checkpoint has switched: refused, naming the options
    (tmp_path / layout.CHECKPOINT).parent.mkdir(parents=True)
    torch.save({"step": 7, "extra": {"connected": True}}, tmp_path / layout.CHECKPOINT)
    with pytest.raises(ValueError, match="already switched.*--connect-at and --output can no longer change"):
        resume_config(tmp_path, _saved(), make_config("full", connect_at=0.9, output="soup"),
                      {"connect_at", "output"})
    # other settings are still refused, and the message lists what a resumed run accepts
    with pytest.raises(ValueError, match=r"--sh-degree \(saved 3, given 1\).*--output, --connect-at"):
        resume_config(tmp_path, _saved(), make_config("full", sh_degree=1), {"sh_degree"})


def test_a_saved_surface_run_without_a_switch_point_resumes_once_given_one(tmp_path):
    """A `full` run started before issue 26 (connect_at null, output surface): a plain resume says what to give."""
    from trisplat.commands.train import resume_config

    legacy = _saved(connect_at=None)
    with pytest.raises(ValueError, match=r"config.json: connect_at is None.*--connect-at P.*--output soup"):
        resume_config(tmp_path, legacy, make_config("full"), set())
    assert resume_config(tmp_path, legacy, make_config("full", connect_at=0.7), {"connect_at"}).switch_at == 0.7
    assert resume_config(tmp_path, legacy, make_config("full", output="soup"), {"output"}).switch_at is None
