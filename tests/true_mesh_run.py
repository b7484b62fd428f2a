"""A capture of the demo scene and a 'finished' run of it whose model is the true mesh: for tests that need a run
folder (render, eval, export, pictures) without training one."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def write_true_mesh_run(root: Path, n_train: int, n_test: int, width: int, height: int, grey: bool = False,
                        downscale: int | None = None):
    """root/capture (demo_mesh rendered from n_train + n_test views, no sparse points) and root/run: config.json,
    state.json (finished) and model.ply holding the true mesh, opaque, in the normalised frame; its colours the mesh's
    own, or grey (0.5). downscale: the run's loader option. Returns (capture, run, the SceneData the run reads)."""
    from trisplat.data import load_dataset
    from trisplat.io import save_model_ply
    from trisplat.scene.model import TriangleScene
    from trisplat.synth import demo_mesh, write_blender_scene

    mesh = demo_mesh()
    capture = write_blender_scene(root / "capture", mesh, n_train=n_train, n_test=n_test, width=width, height=height,
                                  samples_per_pixel=1, n_points=0)
    options = {} if downscale is None else {"downscale": downscale}
    data = load_dataset(capture, **options)
    N = data.normalization
    run = root / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": str(capture), "data_options": options, "eval_supersample": 1}))
    (run / "state.json").write_text(json.dumps({"finished": True, "step": 1, "total_steps": 1}))
    pos = mesh.vertices @ N[:3, :3].T + N[:3, 3]
    rgb = np.full((len(pos), 3), 0.5) if grey else np.asarray(mesh.visual.vertex_colors, np.float64)[:, :3] / 255.0
    save_model_ply(run / "model.ply", TriangleScene.from_rgb(pos, mesh.faces, rgb, opacity=0.999), N)
    return capture, run, data
