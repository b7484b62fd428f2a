"""Pictures for the docs (trisplat.eval.pictures, scripts/make_doc_pictures.py): small JPEGs of what a run's file
shows and of its bare geometry, from the run's own cameras; a capture's photo only when the capture is synthetic."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from trisplat.eval import pictures as P

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished run of the demo scene whose model is the true mesh (48x32 views), with mesh.glb exported."""
    from true_mesh_run import write_true_mesh_run

    from trisplat.io.export_run import export_run

    _, run, _ = write_true_mesh_run(tmp_path_factory.mktemp("pictures"), n_train=3, n_test=2, width=48, height=32)
    (run / "metrics.json").write_text(json.dumps({"psnr": 30.0, "file_psnr": 29.5}))
    export_run(run, formats=("glb",), fit_colours=False)
    return run


def _pixels(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), np.float64) / 255.0


def test_run_pictures_show_the_file_and_the_shape(run, tmp_path):
    from trisplat.api import load_run

    pics = P.run_pictures(run, "demo", tmp_path, view=1, width=40)
    assert [p.kind for p in pics] == ["file", "shaded", "photo"]  # synthetic capture: its photo is the project's own
    for p in pics:
        assert (tmp_path / p.file).stat().st_size == p.bytes < 20_000 and (p.width, p.height) == (40, 27)
        assert p.view == "test/r_1.png"
    r = load_run(run)
    photo, file = _pixels(tmp_path / "demo_photo.jpg"), _pixels(tmp_path / "demo_file.jpg")
    assert np.abs(photo - file).mean() < 0.06  # the true mesh, as the file shows it, is the photo
    shaded = _pixels(tmp_path / "demo_shaded.jpg")
    assert np.abs(shaded - shaded[..., :1]).max() < 0.05  # grey
    background = (shaded > 0.97).all(-1)  # white around the object, as where the photo shows the background
    assert 0.2 < background.mean() < 0.95
    assert "29.50 dB" in pics[0].note and r.file_psnr == 29.5


def test_no_photo_of_a_capture_that_is_not_the_projects(run, tmp_path):
    other = tmp_path / "run"
    shutil.copytree(run, other)
    capture = tmp_path / "capture"
    shutil.copytree(json.loads((run / "config.json").read_text())["data"], capture)
    (capture / "synth.json").unlink()
    (other / "config.json").write_text(json.dumps({"data": str(capture), "data_options": {}, "eval_supersample": 1}))
    pics = P.run_pictures(other, "real", tmp_path / "pics")
    assert [p.kind for p in pics] == ["file", "shaded"] and not (tmp_path / "pics" / "real_photo.jpg").exists()


def test_slam_pictures_from_a_tracked_frame(rgbd_capture, tmp_path):
    """A slam run laid out as `trisplat slam` writes it (trajectory in the first frame's camera frame, mesh.ply in the
    same frame): the mesh, seen from frame k's pose, covers what frame k's depth saw."""
    import trimesh

    from trisplat.data.rgbd_stream import open_stream
    from trisplat.slam.se3 import write_tum_trajectory
    from trisplat.synth.scenes import demo_mesh

    stream = open_stream(rgbd_capture)
    ref = np.array([f.reference_c2w for f in stream.frames])
    to_map = np.linalg.inv(ref[0])  # world -> the first frame's camera frame
    out = tmp_path / "room"
    out.mkdir()
    (out / "config.json").write_text(json.dumps({"capture": str(rgbd_capture), "downscale": 1}))
    write_tum_trajectory(out / "trajectory.txt", list(range(len(ref))), [to_map @ c for c in ref])
    mesh = demo_mesh(seed=0)
    mesh.apply_transform(to_map)
    trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=mesh.visual.vertex_colors).export(out / "mesh.ply")
    pics = P.slam_pictures(out, "room", tmp_path / "pics", frame=5, width=stream.width)
    assert [p.kind for p in pics] == ["file", "shaded"] and pics[0].view == "frame 5"
    from trisplat.data.rgbd_stream import load_frame

    _, depth = load_frame(stream, 5, 1)
    seen = np.asarray(depth) > 0
    covered = (_pixels(tmp_path / "pics" / "room_shaded.jpg") < 0.97).any(-1)
    assert (seen & covered).sum() / (seen | covered).sum() > 0.9


def test_script_writes_the_pictures_and_their_index(run, tmp_path):
    out = tmp_path / "docs_pictures"
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "make_doc_pictures.py"), f"demo={run}:0",
                           "--out", str(out), "--width", "32"], capture_output=True, text=True, cwd=REPO,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "NUMBA_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr
    index = json.loads((out / P.PICTURES_JSON).read_text())
    assert [p["file"] for p in index] == ["demo_file.jpg", "demo_photo.jpg", "demo_shaded.jpg"]
    assert all(p["run"] == str(run) and p["view"] == "test/r_0.png" and p["width"] == 32 for p in index)
    assert "KB of pictures in all" in done.stdout
