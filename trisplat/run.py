"""The run directory: where `trisplat train` puts everything, and how other commands read it back.

RUN/
  config.json          the TrainConfig (plus the data path and loader options) as JSON
  state.json           {"finished": bool, "step": int, "total_steps": int}
  checkpoints/last.pt  latest good checkpoint (written to a temporary file, then renamed)
  checkpoints/soup.pt  the soup just before the switch to a connected surface (same format as last.pt)
  history.jsonl        one JSON object per logged step: step, wall_s, loss, psnr, faces, vertices, sigma
                       (and test_psnr on evaluation steps)
  model.ply            the full model: every SH coefficient and the opacity, reloadable losslessly
  mesh.ply, mesh.obj (+ mesh.mtl), mesh.glb   the opaque mesh, per-vertex RGB, in the capture's frame (the GLB
                       turned Y-up, as glTF defines)
  metrics.json         final metrics
  exposure.json        per-photo colour corrections (captures without alpha; trisplat.train.exposure)
  intrinsics.json      the refined focal length and principal point (--refine-intrinsics; trisplat.train.intrinsics)
  renders/             a few test renders (hard mode)

`trisplat slam` writes the same config.json, state.json ("step": frames done), model.ply, mesh.ply and metrics.json,
plus trajectory.txt and checkpoint.pt (trisplat.slam.system), under the same rules (prepare_run_dir, move_aside).
"""
from __future__ import annotations

import json
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

CONFIG = "config.json"
STATE = "state.json"
HISTORY = "history.jsonl"
CHECKPOINT = "checkpoints/last.pt"
SOUP_CHECKPOINT = "checkpoints/soup.pt"  # the soup just before the switch to a connected surface
MODEL = "model.ply"
METRICS = "metrics.json"
RENDERS = "renders"


@dataclass
class Run:
    """A trained (or partly trained) run read back from disk."""

    path: Path
    config: dict
    state: dict

    @property
    def data_path(self) -> Path:
        return Path(self.config["data"])

    def history(self) -> list[dict]:
        p = self.path / HISTORY
        if not p.exists():
            return []
        return [json.loads(line) for line in p.read_text().splitlines() if line.strip()]

    def load_model(self):
        """The trained TriangleScene (normalised frame) and the normalisation [4,4], from model.ply or the
        last checkpoint when training has not finished."""
        from trisplat.train.checkpoint import load_scene_from_run

        return load_scene_from_run(self)

    def load_scene_data(self, **overrides):
        """The capture, loaded with the options the run was trained with, with the intrinsics the run refined
        (RUN/intrinsics.json, trisplat.train.intrinsics) when it refined them."""
        from trisplat.data import load_dataset
        from trisplat.train.intrinsics import apply_saved

        opts = dict(self.config.get("data_options", {}))
        opts.update(overrides)
        data = load_dataset(self.data_path, **opts)
        apply_saved(self.path, data)
        return data


def open_run(path: str | Path) -> Run:
    path = Path(path)
    cfg = path / CONFIG
    if not cfg.exists():
        raise FileNotFoundError(f"{path}: not a trisplat run (no {CONFIG}); train one with `trisplat train`")
    try:
        config = json.loads(cfg.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{cfg}: malformed JSON ({exc})") from exc
    state_p = path / STATE
    state = json.loads(state_p.read_text()) if state_p.exists() else {"finished": False, "step": 0}
    return Run(path=path, config=config, state=state)


def prepare_run_dir(out: Path, resume: bool, force: bool, checkpoint: str = CHECKPOINT) -> None:
    """Refuse to clobber a run (checks only: nothing is moved; see `move_aside`). --resume needs a run: its
    checkpoint, or at least its config.json (a run killed before its first checkpoint starts over). The rules of
    every command that writes a run (`trisplat train`, `trisplat slam`); `checkpoint`: the command's checkpoint file
    in the run."""
    out = Path(out)
    if resume:
        if not (out / checkpoint).exists() and not (out / CONFIG).exists():
            raise FileNotFoundError(f"{out}: nothing to resume (no {checkpoint} and no {CONFIG})")
        return
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} is a file, not a run directory")
    if out.exists() and any(out.iterdir()) and not force:
        state = open_run(out).state if (out / CONFIG).exists() else {}
        what = "a finished run" if state.get("finished") else "an unfinished run (use --resume)" if state \
            else "files"
        raise FileExistsError(f"{out} already holds {what}; pass --force to start over (it is moved aside)")


def move_aside(out: Path) -> Path | None:
    """With --force, after the inputs were checked: move a non-empty `out` to OUT.old-TIME (never deleted)."""
    if not (out.exists() and any(out.iterdir())):
        return None
    backup = out.with_name(f"{out.name}.old-{time.strftime('%Y%m%d-%H%M%S')}")
    shutil.move(str(out), str(backup))
    print(f"moved the previous contents of {out} to {backup}", file=sys.stderr)
    return backup
