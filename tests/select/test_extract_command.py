"""`trisplat extract`: end to end on a run made from the generated two-object scene, and precise errors for bad masks."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from trisplat.synth import orbit_cameras, raycast_view, two_object_mesh, write_blender_scene

pytest.importorskip("trisplat.data")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A capture of the two-object scene and a 'trained' run whose model is the true mesh (normalised frame)."""
    from trisplat.data import load_dataset
    from trisplat.io import save_model_ply
    from trisplat.scene.model import TriangleScene

    root = tmp_path_factory.mktemp("extract")
    mesh, label = two_object_mesh()
    data = write_blender_scene(
        root / "data",
        mesh,
        n_train=8,
        n_test=1,
        width=80,
        height=80,
        samples_per_pixel=1,
        seed=0,
        n_points=0,
        elevation_deg=(-60, 60),
    )
    scene_data = load_dataset(data)
    N = scene_data.normalization
    pos_n = mesh.vertices @ N[:3, :3].T + N[:3, 3]
    colors = mesh.visual.vertex_colors[:, :3] / 255.0
    run = root / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": str(data)}))
    (run / "state.json").write_text(json.dumps({"finished": True, "step": 1, "total_steps": 1}))
    save_model_ply(run / "model.ply", TriangleScene.from_rgb(pos_n, mesh.faces, colors, opacity=0.999), N)
    # masks of the sphere for the 8 training views, drawn on images twice the size (resampled on reading)
    info = json.loads((data / "synth.json").read_text())
    cams = orbit_cameras(8, info["radius"], 160, 160, 40, info["center"], 0, (-60, 60))
    flat = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    white = np.where(label == 1, 255, 0).astype(np.uint8)
    flat.visual = trimesh.visual.ColorVisuals(flat, face_colors=np.c_[white, white, white, np.full_like(white, 255)])
    masks = root / "masks"
    masks.mkdir()
    for i in range(8):
        m = raycast_view(flat, cams[i], background=(0, 0, 0), samples_per_pixel=2).rgba[..., 0] >= 0.5
        Image.fromarray((m * 255).astype(np.uint8)).save(masks / f"r_{i}.png")
    return run, mesh, label, masks


def _face_keys(vertices, faces):
    return {tuple(np.round(np.sort(vertices[f], axis=0).ravel(), 4)) for f in faces}


def test_extract_command_writes_object_and_remainder_in_capture_frame(run_dir, tmp_path):
    from trisplat.commands.extract import main

    run, mesh, label, masks = run_dir
    assert main([str(run), "--masks", str(masks), "--out", str(tmp_path / "out")]) == 0
    obj = trimesh.load(tmp_path / "out" / "object.ply", process=False)
    rest = trimesh.load(tmp_path / "out" / "remainder.ply", process=False)
    assert len(obj.faces) + len(rest.faces) == len(mesh.faces)
    # faces compared by their corner positions in the capture frame (the inverse normalisation was applied)
    got = _face_keys(obj.vertices, obj.faces)
    truth = _face_keys(mesh.vertices, mesh.faces[label == 1])
    iou = len(got & truth) / len(got | truth)
    assert iou >= 0.9, iou
    assert _face_keys(rest.vertices, rest.faces) >= _face_keys(mesh.vertices, mesh.faces[label == 2])
    summary = json.loads((tmp_path / "out" / "extract.json").read_text())
    assert summary["masks"] == 8 and summary["object_faces"] == len(obj.faces)


def _write(path, arr):
    Image.fromarray(arr).save(path)


def test_bad_masks_get_precise_errors(run_dir, tmp_path):
    from trisplat.commands.extract import main

    run, *_ = run_dir
    d = tmp_path / "m"
    d.mkdir()
    with pytest.raises(ValueError, match=r"no mask images \(\*\.png\)"):
        main([str(run), "--masks", str(d)])
    with pytest.raises(FileNotFoundError, match="mask folder not found"):
        main([str(run), "--masks", str(tmp_path / "nope")])
    _write(d / "frame_9.png", np.full((80, 80), 255, np.uint8))
    with pytest.raises(ValueError, match=r"1 mask\(s\) match no view by file stem: frame_9.png .*r_0"):
        main([str(run), "--masks", str(d)])
    (d / "frame_9.png").unlink()
    _write(d / "r_1.png", np.full((50, 80), 255, np.uint8))
    with pytest.raises(ValueError, match=r"r_1.png: mask is 80x50 pixels, but its view's image is 80x80"):
        main([str(run), "--masks", str(d)])
    _write(d / "r_1.png", np.zeros((80, 80), np.uint8))
    with pytest.raises(ValueError, match=r"r_1.png: mask is empty"):
        main([str(run), "--masks", str(d)])
    _write(d / "r_1.png", np.full((80, 80), 255, np.uint8))
    with pytest.raises(ValueError, match=r"--ratio must be in \(0, 1\]"):
        main([str(run), "--masks", str(d), "--ratio", "1.5"])
    with pytest.raises(FileNotFoundError, match="not a trisplat run"):
        main([str(tmp_path), "--masks", str(d)])


def test_read_mask_formats(tmp_path):
    from trisplat.select import read_mask

    m = np.zeros((6, 8), np.uint8)
    m[2:4, 3:6] = 1
    _write(tmp_path / "zero_one.png", m)  # 0/1 label image
    np.testing.assert_array_equal(read_mask(tmp_path / "zero_one.png"), m > 0)
    rgba = np.zeros((6, 8, 4), np.uint8)
    rgba[..., 3] = m * 255  # object in the alpha channel
    _write(tmp_path / "alpha.png", rgba)
    np.testing.assert_array_equal(read_mask(tmp_path / "alpha.png"), m > 0)
    big = np.kron(m, np.ones((2, 2), np.uint8)) * 255  # twice the size: resampled to the view
    _write(tmp_path / "big.png", big)
    np.testing.assert_array_equal(read_mask(tmp_path / "big.png", 8, 6), m > 0)
    (tmp_path / "bad.png").write_text("not an image")
    with pytest.raises(ValueError, match="bad.png: not a readable image"):
        read_mask(tmp_path / "bad.png")
