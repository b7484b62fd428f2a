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
  renders/             a few test renders (hard mode)
"""
from __future__ import annotations

import json
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
        """The capture, loaded with the options the run was trained with."""
        from trisplat.data import load_dataset

        opts = dict(self.config.get("data_options", {}))
        opts.update(overrides)
        return load_dataset(self.data_path, **opts)


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
