"""`trisplat slam --slam.texture-size N`: the surface's mesh.glb gets a base-colour texture fitted to the keyframes'
photos, as training's does, and the held-out frames score the textured file as a glTF viewer shows it."""
from __future__ import annotations

import numpy as np
import pytest

from trisplat.data.rgbd_stream import open_stream
from trisplat.io.gltf import read_glb
from trisplat.slam.system import SlamConfig, evaluate_mesh_frames, run_slam
from trisplat.slam.track import TrackConfig
from tests.slam.rgbd_scene import black_background_copy


def _cfg(**kw) -> SlamConfig:
    args = dict(downscale=1, final_iters=10, checkpoint_every=0, eval_every=3, mesh_resolution=128,
                track=TrackConfig(levels=(2, 1), max_iters=(60, 40)))
    return SlamConfig(**{**args, **kw})


@pytest.mark.slow
def test_slam_textured_glb_is_scored_as_a_viewer_shows_it(rgbd_capture, tmp_path, monkeypatch):
    from trisplat.slam import system

    fitted = []
    real = system.fit_mesh_colours
    monkeypatch.setattr(system, "fit_mesh_colours", lambda *a, **k: fitted.append(real(*a, **k)) or fitted[-1])
    stream = open_stream(black_background_copy(rgbd_capture, tmp_path / "cap"))
    m = run_slam(stream, tmp_path / "run", _cfg(texture_size=256), log=lambda *a, **k: None)
    rep = m["mesh"]["colours"]
    # 14 frames make fewer keyframes than a held-out choice needs (trisplat.texture.asset.HOLDOUT_MIN_VIEWS): the
    # texture is fitted to all of them and kept
    assert rep["file"] == "texture" and rep["texture"]["size"] == 256 and rep["texture"]["fit_views"] >= 2
    glb = read_glb(tmp_path / "run" / "mesh.glb")
    images = [p.material.image for p in glb.primitives if p.material.image is not None]
    assert len(images) == 1 and images[0].shape[:2] == (256, 256) and glb.primitives[0].uv is not None
    (_, texture, _), = fitted
    tex = [texture]
    np.testing.assert_array_equal(images[0][..., :3], texture.image)  # the file holds the fitted texture
    held = m["held_out_glb"]
    assert held["frames"] == m["held_out"]["frames"] >= 2 and held is not m["held_out_mesh"]
    # the textured file is scored, not the vertex colours: scoring the same texture with its texels inverted must
    # lose, and scoring the texture again must give the run's number
    import trimesh

    mesh = trimesh.load(tmp_path / "run" / "mesh.ply", process=False)
    verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    cols = np.asarray(mesh.visual.vertex_colors, np.float64)[:, :3] / 255.0
    from trisplat.slam.trajectory import read_tum_trajectory

    _, est = read_tum_trajectory(tmp_path / "run" / "trajectory.txt")
    frames = m["held_out"]["frame_numbers"]
    ids = list(range(len(est)))
    again = evaluate_mesh_frames(stream, verts, faces, cols, list(est), ids, frames, 1, texture=tex[0])
    assert again["psnr"] == pytest.approx(held["psnr"], abs=0.3)
    import dataclasses

    bad = dataclasses.replace(tex[0], image=255 - tex[0].image)
    worse = evaluate_mesh_frames(stream, verts, faces, cols, list(est), ids, frames, 1, texture=bad)
    assert worse["psnr"] < held["psnr"] - 2.0
    # off by default: no texture, no fit
    assert SlamConfig().texture_size == 0
