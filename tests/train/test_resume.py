"""Runs survive being killed: `kill -9` before and after the first periodic checkpoint, then `--resume`; resumed
runs honour or refuse overrides explicitly; outputs are written atomically; checkpoints hold plain tensors only."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from trisplat import run as layout
from trisplat.cli import main as cli_main
from trisplat.train.checkpoint import load_checkpoint

REPO = Path(__file__).resolve().parents[2]
# a tiny run: small images, few triangles, a log line every step
TINY_ARGS = ["--preset", "fast", "--sh-degree", "1", "--init-random-points", "300", "--log-every", "1",
             "--eval-every", "0.5", "--eval-max-views", "1", "--num-renders", "1", "--eval-supersample", "1",
             "--quiet"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from trisplat.synth import demo_mesh, write_blender_scene

    out = tmp_path_factory.mktemp("resume") / "scene"
    return write_blender_scene(out, demo_mesh(), n_train=6, n_test=2, width=40, height=40, samples_per_pixel=1,
                               n_points=0)


def _history(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / layout.HISTORY).read_text().splitlines() if line.strip()]


def _logged_steps(run: Path) -> list[int]:
    return [h["step"] for h in _history(run) if "loss" in h]


def _start(scene: Path, run: Path, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    return subprocess.Popen([sys.executable, "-m", "trisplat", "train", str(scene), "--out", str(run), *TINY_ARGS,
                             *extra], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _kill_when(proc: subprocess.Popen, ready, timeout: float = 240.0) -> None:
    """SIGKILL `proc` as soon as ready() holds (the test fails if the run ends or times out first)."""
    t0 = time.time()
    while not ready():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"the run ended (rc {proc.returncode}) before it could be killed:\n{err.decode()[-2000:]}")
        if time.time() - t0 > timeout:
            proc.kill()
            pytest.fail("the run never reached the point where it is to be killed")
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL


def _resume_to_the_end(scene: Path, run: Path, steps: int) -> None:
    assert cli_main(["train", str(scene), "--out", str(run), "--resume", *TINY_ARGS]) == 0
    state = json.loads((run / layout.STATE).read_text())
    assert state["finished"] is True and state["step"] == steps
    assert json.loads((run / layout.METRICS).read_text())["steps"] == steps
    # every step logged exactly once, in order, though some were computed twice
    assert _logged_steps(run) == list(range(1, steps + 1))
    evals = [h["step"] for h in _history(run) if "test_psnr" in h]
    assert len(evals) == len(set(evals)) == 1  # eval_every 0.5: one intermediate evaluation, not repeated


def test_kill_before_the_first_periodic_checkpoint_then_resume(scene, tmp_path):
    run = tmp_path / "run"
    steps = 300
    proc = _start(scene, run, "--steps", str(steps), "--checkpoint-every-s", "1e9")  # no periodic checkpoint
    _kill_when(proc, lambda: (run / layout.HISTORY).exists() and len(_logged_steps(run)) >= 5)
    assert not json.loads((run / layout.STATE).read_text())["finished"]
    # a plain re-run refuses (it would throw the run away) and names --resume
    assert cli_main(["train", str(scene), "--out", str(run), *TINY_ARGS, "--steps", str(steps)]) == 1
    _resume_to_the_end(scene, run, steps)


def test_kill_after_a_periodic_checkpoint_then_resume(scene, tmp_path):
    run = tmp_path / "run"
    steps = 300
    proc = _start(scene, run, "--steps", str(steps), "--checkpoint-every-s", "0.3")

    def past_a_checkpoint():
        if not (run / layout.HISTORY).exists():
            return False
        state = json.loads((run / layout.STATE).read_text()) if (run / layout.STATE).exists() else {}
        return state.get("step", 0) > 0 and len(_logged_steps(run)) >= state["step"] + 3

    _kill_when(proc, past_a_checkpoint)
    ckpt_step = int(load_checkpoint(run / layout.CHECKPOINT)["step"])
    assert 0 < ckpt_step < max(_logged_steps(run))  # steps after the checkpoint will be replayed
    _resume_to_the_end(scene, run, steps)


def test_resume_with_a_run_stopped_during_initialisation_starts_it_again(scene, tmp_path):
    """Killed after config.json but before any checkpoint: --resume starts over with the saved configuration."""
    run = tmp_path / "run"
    assert cli_main(["train", str(scene), "--out", str(run), *TINY_ARGS, "--steps", "12"]) == 0
    for name in (layout.CHECKPOINT, layout.METRICS, layout.MODEL):
        (run / name).unlink()
    (run / layout.STATE).write_text(json.dumps({"finished": False, "step": 0, "total_steps": 12}))
    assert cli_main(["train", str(scene), "--out", str(run), "--resume", *TINY_ARGS]) == 0
    assert json.loads((run / layout.METRICS).read_text())["steps"] == 12
    assert _logged_steps(run) == list(range(1, 13))


def test_resume_honours_minutes_and_refuses_other_changes(scene, tmp_path, capsys):
    run = tmp_path / "run"
    from trisplat.commands.train import make_train_args, run_training

    args = make_train_args(scene, run, preset="fast", quiet=True, steps=40, sh_degree=1, init_random_points=300,
                           log_every=1, checkpoint_every_s=1e9)
    from trisplat.train.trainer import Trainer

    data, opts = _data_and_options(scene, args.config)
    Trainer(args.config, data, run, show_progress=False, data_options=opts, data_path=str(scene)).train(
        stop_after=12)
    # a setting that changes what is optimised: refused, with the option, both values and the way out named
    rc = cli_main(["train", str(scene), "--out", str(run), "--resume", "--steps", "99", "--sh-degree", "0"])
    err = capsys.readouterr().err
    assert rc == 1 and "--steps (saved 40, given 99)" in err and "--sh-degree (saved 1, given 0)" in err
    assert "--force" in err and json.loads((run / layout.CONFIG).read_text())["steps"] == 40
    # the library path too (steps=40 differs from the preset but equals the saved value: no change)
    with pytest.raises(ValueError, match="--lr-sh-dc"):
        run_training(make_train_args(scene, run, preset="fast", resume=True, quiet=True, steps=40, sh_degree=1,
                                     lr_sh_dc=0.5))
    # the capture is the run's own
    other = tmp_path / "other"
    other.mkdir()
    rc = cli_main(["train", str(other), "--out", str(run), "--resume", "--quiet"])
    assert rc == 1 and "was trained on" in capsys.readouterr().err
    # --minutes is honoured: the rest of the run is planned into the budget (time already spent included)
    assert cli_main(["train", str(scene), "--out", str(run), "--resume", "--minutes", "0.05", "--quiet"]) == 0
    saved = json.loads((run / layout.CONFIG).read_text())
    assert saved["minutes"] == 0.05 and saved["steps"] == 40
    state = json.loads((run / layout.STATE).read_text())
    assert state["finished"] and state["total_steps"] != 40  # the schedule was re-planned from the measured rate


def _data_and_options(scene, cfg):
    from trisplat.data import load_dataset

    opts = {"downscale": cfg.downscale, "background": list(cfg.background), "test_every": cfg.test_every,
            "format": cfg.data_format}
    return load_dataset(scene, **opts), opts


def test_checkpoints_hold_plain_tensors_and_refuse_code(scene, tmp_path):
    from trisplat.commands.train import make_train_args
    from trisplat.train.trainer import Trainer

    args = make_train_args(scene, tmp_path / "run", preset="fast", steps=6, sh_degree=1, init_random_points=300)
    data, _ = _data_and_options(scene, args.config)
    Trainer(args.config, data, tmp_path / "run", show_progress=False).train(stop_after=3)
    ckpt = torch.load(tmp_path / "run" / layout.CHECKPOINT, weights_only=True)  # loads without trusting pickles
    assert ckpt["step"] == 3 and torch.is_tensor(ckpt["generator"])
    # a checkpoint file that would run code when unpickled is refused, and the code never runs
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    evil = tmp_path / "evil.pt"
    torch.save({"step": 1, "params": Payload()}, evil)
    with pytest.raises(ValueError, match=f"{evil}: unreadable checkpoint"):
        load_checkpoint(evil)
    assert not marker.exists()


def test_load_model_prefers_the_checkpoint_to_a_half_written_model(scene, tmp_path):
    from trisplat.commands.train import make_train_args
    from trisplat.train.trainer import Trainer

    run_dir = tmp_path / "run"
    args = make_train_args(scene, run_dir, preset="fast", steps=8, sh_degree=1, init_random_points=300,
                           eval_supersample=1, num_renders=0)
    data, opts = _data_and_options(scene, args.config)
    tr = Trainer(args.config, data, run_dir, show_progress=False, data_options=opts, data_path=str(scene))
    tr.train()
    good = (run_dir / layout.MODEL).read_bytes()
    final = tr.ts.to_scene()
    # a finish interrupted while model.ply was written: the run is unfinished, the file half there
    (run_dir / layout.MODEL).write_bytes(good[: len(good) // 2])
    (run_dir / layout.STATE).write_text(json.dumps({"finished": False, "step": 8, "total_steps": 8}))
    scene_ckpt, norm = layout.open_run(run_dir).load_model()
    ckpt = load_checkpoint(run_dir / layout.CHECKPOINT)
    torch.testing.assert_close(scene_ckpt.positions, ckpt["params"]["positions"])
    np.testing.assert_allclose(norm, data.normalization)
    # a finished run reads model.ply (the final pruning is only there) ...
    (run_dir / layout.MODEL).write_bytes(good)
    (run_dir / layout.STATE).write_text(json.dumps({"finished": True, "step": 8, "total_steps": 8}))
    loaded, _ = layout.open_run(run_dir).load_model()
    assert loaded.num_faces == final.num_faces
    # ... and falls back to the checkpoint, with a warning naming the file, when model.ply is unreadable
    (run_dir / layout.MODEL).write_bytes(good[:100])
    with pytest.warns(UserWarning, match="model.ply: unreadable"):
        loaded, _ = layout.open_run(run_dir).load_model()
    assert loaded.num_faces == ckpt["faces"].shape[0]


@pytest.mark.parametrize("suffix", ["ply", "obj", "glb", "model"])
def test_model_and_mesh_files_are_written_atomically(tmp_path, monkeypatch, suffix):
    """A write that dies half-way leaves the previous file whole and no partial file behind."""
    import plyfile

    from trisplat.io import export_mesh, save_model_ply
    from trisplat.io.mesh_files import load_mesh
    from trisplat.scene.model import TriangleScene

    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2]], np.int32)
    target = tmp_path / ("model.ply" if suffix == "model" else f"mesh.{suffix}")

    def write(p):
        if suffix == "model":
            save_model_ply(target, TriangleScene(torch.tensor(p), torch.zeros(3, 1, 3), torch.zeros(3),
                                                 torch.tensor(faces), 0.0), np.eye(4))
        else:
            export_mesh(target, p, faces, np.full((3, 3), 0.5), up=None)  # keep the frame (GLB: Y-up by default)

    write(pos)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}  # an OBJ brings its MTL

    def dies_half_way(self, stream, *a, **k):
        Path(stream if isinstance(stream, str) else stream.name).write_bytes(b"ply\nformat binary_litt")
        raise OSError("disk full")

    monkeypatch.setattr(plyfile.PlyData, "write", dies_half_way)
    real_write_bytes = Path.write_bytes

    def write_bytes_half(self, data):
        real_write_bytes(self, data[: len(data) // 2])
        raise OSError("disk full")

    monkeypatch.setattr(Path, "write_bytes", write_bytes_half)
    monkeypatch.setattr(Path, "write_text", lambda self, text, *a, **k: write_bytes_half(self, text.encode()))
    with pytest.raises(OSError, match="disk full"):
        write(pos * 2)
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    if suffix != "model":
        np.testing.assert_allclose(load_mesh(target)[0], pos)


def test_resume_with_force_continues_in_place(scene, tmp_path):
    """--force means "start over" only without --resume: together they continue the run, nothing is moved."""
    run = tmp_path / "run"
    from trisplat.commands.train import make_train_args
    from trisplat.train.trainer import Trainer

    args = make_train_args(scene, run, preset="fast", steps=10, sh_degree=1, init_random_points=300,
                           eval_supersample=1, num_renders=0)
    data, opts = _data_and_options(scene, args.config)
    Trainer(args.config, data, run, show_progress=False, data_options=opts, data_path=str(scene)).train(stop_after=4)
    assert cli_main(["train", str(scene), "--out", str(run), "--resume", "--force", "--quiet"]) == 0
    assert json.loads((run / layout.STATE).read_text())["finished"] and not list(tmp_path.glob("run.old-*"))
    assert max(_logged_steps(run)) == 10
