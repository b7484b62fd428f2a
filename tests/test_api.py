"""The Python API (trisplat.api) end to end on the demo scene: train, scores, renders in every mode, the mesh as a
trimesh, export with the overwrite rule, a run read back from disk; and the same path as the commands."""
from __future__ import annotations

import json

import numpy as np
import pytest

import trisplat.api as ts

# a few dozen steps on 32x32 photos, the switch to a connected surface included; no texture, little scoring
QUICK = dict(steps=40, sh_degree=1, max_vertices=2000, eval_every=0.5, eval_max_views=1, checkpoint_every_s=1e9,
             num_renders=1, eval_supersample=1, texture_size=0)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """The demo scene (trisplat demo's, at 32x32: 8 training and 2 test views) trained through the API."""
    from trisplat.synth import demo_mesh, write_blender_scene

    root = tmp_path_factory.mktemp("api")
    scene = write_blender_scene(root / "scene", demo_mesh(), n_train=8, n_test=2, width=32, height=32,
                                samples_per_pixel=1, n_points=400)
    return ts.train(scene, root / "run", preset="fast", quiet=True, **QUICK), scene


def test_train_returns_the_finished_run_with_its_scores(trained):
    run, scene = trained
    saved = json.loads((run.path / "metrics.json").read_text())
    assert run.metrics == saved and run.psnr == saved["psnr"] and run.file_psnr == saved["file_psnr"]
    assert run.faces == saved["faces"] > 0 and run.wall_s > 0
    assert saved["steps"] == 40 and saved["connected"] is True  # the fast preset's switch happened
    assert json.loads((run.path / "config.json").read_text())["sh_degree"] == 1  # the overrides reached the run
    assert run.psnr > 12.0  # a grey guess of the demo scene scores about 9 dB


def test_render_modes_match_the_runs_own_scores(trained):
    from trisplat.eval.image_metrics import psnr

    run, _ = trained
    cams = run.cameras("test")
    assert len(cams) == 2 and len(run.cameras("train")) == 8
    images = {mode: run.render(0, mode=mode) for mode in ("hard", "soft", "file", "shaded")}
    for mode, img in images.items():
        assert img.shape == (32, 32, 3) and img.dtype == np.float32 and 0.0 <= img.min() and img.max() <= 1.0, mode
    # the scores of metrics.json are these renders against these photos (hard: the model; file: mesh.glb)
    photos = [run.photo(k) for k in range(2)]
    hard = np.mean([10 ** (-psnr(p, run.render(k)) / 10) for k, p in enumerate(photos)])
    file = np.mean([10 ** (-psnr(p, run.render(k, mode="file")) / 10) for k, p in enumerate(photos)])
    assert -10 * np.log10(hard) == pytest.approx(run.psnr, abs=0.05)
    assert -10 * np.log10(file) == pytest.approx(run.file_psnr, abs=0.05)
    shaded = images["shaded"]  # grey: no colour, only light
    assert np.allclose(shaded[..., 0], shaded[..., 1]) and not np.allclose(shaded, shaded.mean())
    assert np.array_equal(run.render(cams[1]), run.render(1))  # a Camera or an index of the split
    with pytest.raises(IndexError, match="2 views"):
        run.render(2)


def test_mesh_and_export(trained, tmp_path):
    import trimesh

    run, _ = trained
    mesh = run.mesh()
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) > 0
    files = run.export(tmp_path / "e", formats=("ply", "glb"))
    assert sorted(p.name for p in files) == ["mesh.glb", "mesh.ply"]
    exported = trimesh.load(tmp_path / "e" / "mesh.ply", process=False)
    assert np.allclose(exported.vertices, mesh.vertices, atol=1e-5) and len(exported.faces) == len(mesh.faces)
    glb = run.mesh("mesh.glb")  # Y-up, the same surface
    assert len(glb.faces) == run.metrics["file_faces"]
    with pytest.raises(FileExistsError, match="would overwrite"):
        run.export(tmp_path / "e", formats=("ply",))


def test_a_run_read_back_is_the_same_run(trained):
    run, _ = trained
    again = ts.load_run(run.path)
    assert again.metrics == run.metrics and again.wall_s is None
    assert np.array_equal(again.render(0), run.render(0))
    with pytest.raises(FileNotFoundError, match="not a trisplat run"):
        ts.load_run(run.path / "eval_test")


def test_the_commands_take_the_apis_path(monkeypatch, tmp_path):
    """`trisplat train` and `trisplat slam` hand their parsed arguments to trisplat.api (one path for both)."""
    from trisplat.cli import main

    seen = {}

    def fake_train(args, explicit):
        seen["train"] = (args.config.steps, explicit)
        return ts.TrainedRun(path=args.out, metrics={}, wall_s=1.0)

    def fake_slam(args, log=print):
        seen["slam"] = args.slam.max_frames
        return ts.SlamRun(path=args.out)

    monkeypatch.setattr(ts, "train_from_args", fake_train)
    monkeypatch.setattr(ts, "slam_from_args", fake_slam)
    assert main(["train", str(tmp_path), "--out", str(tmp_path / "r"), "--steps", "7", "--quiet"]) == 0
    assert main(["slam", str(tmp_path), "--out", str(tmp_path / "s"), "--slam.max-frames", "3"]) == 0
    assert seen == {"train": (7, {"steps"}), "slam": 3}


def test_slam_run_reads_its_trajectory_and_mesh(tmp_path):
    """SlamRun on a folder laid out as `trisplat slam` writes it (TUM trajectory, mesh.ply)."""
    import trimesh

    from trisplat.slam.se3 import write_tum_trajectory

    out = tmp_path / "room"
    out.mkdir()
    (out / "config.json").write_text("{}")
    (out / "metrics.json").write_text(json.dumps({"ate": {"rmse_m": 0.012}}))
    c2w = [np.eye(4), np.eye(4)]
    c2w[1][:3, 3] = [0.1, 0.0, 0.2]
    write_tum_trajectory(out / "trajectory.txt", [0.0, 1.0], c2w)
    trimesh.creation.box().export(out / "mesh.ply")
    room = ts.load_slam_run(out)
    assert room.ate_rmse_m == 0.012 and np.allclose(room.trajectory(), np.stack(c2w))
    assert len(room.mesh().faces) == 12
