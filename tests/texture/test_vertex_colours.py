"""Vertex colours fitted to photos: photos of a vertex-coloured sphere (made by the glTF spec renderer from a file
with known COLOR_0) give those colours back, and the file keeps fitted colours only where they beat the model's."""
from __future__ import annotations

import numpy as np
import trimesh

from tests.texture.test_texture_fit import Cam, PhotoData, _look_at, coloured_scene
from trisplat.eval.image_metrics import psnr
from trisplat.eval.spec_render import prepare_asset, render_asset
from trisplat.io import export_mesh
from trisplat.io.gltf import read_glb
from trisplat.mesh.orient import edge_table
from trisplat.texture.vertex_colours import fit_vertex_colors


def _cams(n_az=10, elevations=(-0.5, 0.1, 0.6), size=64):
    f = 1.1 * size
    return [Cam(_look_at(3.0 * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])),
                np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]]), size, size)
            for a in np.linspace(0, 2 * np.pi, n_az, endpoint=False) for e in elevations]


def _photos(tmp_path, mesh, colors, cams, bg):
    export_mesh(tmp_path / "truth.glb", mesh.vertices, mesh.faces, colors, up=None)
    truth = prepare_asset(read_glb(tmp_path / "truth.glb"))
    return [render_asset(truth, c.world_to_camera, c.K, c.width, c.height, bg, 2) for c in cams]


def test_mesh_edges_are_the_unique_undirected_edges():
    e = edge_table(np.array([[0, 1, 2], [2, 1, 3]])).edges
    assert e.tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]


def test_fitted_vertex_colours_recover_the_colours_the_photos_were_made_with(tmp_path):
    """The photos show COLOR_0 as glTF defines it (linear, interpolated in linear light, averaged over 2x2
    samples); fitted from flat grey, the colours come back to within a few 8-bit steps, and the file made with them
    reproduces photos it was not fitted to. A fit in sRGB, with wrong barycentrics or wrong vertex ids would not."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.05, 0.95, (len(mesh.vertices), 3))  # independent colours: no smoothness helps
    bg = (1.0, 1.0, 1.0)
    cams = _cams()
    photos = _photos(tmp_path, mesh, truth, cams, bg)
    held = set(range(2, len(cams), 7))
    fit = [i for i in range(len(cams)) if i not in held]
    grey = np.full_like(truth, 0.5)
    colors, stats = fit_vertex_colors(mesh.vertices, mesh.faces, ((cams[i], photos[i]) for i in fit), bg, grey,
                                      prior=1e-4, smoothness=0.0)
    assert stats.views == len(fit) and stats.seen == len(mesh.vertices) and stats.relative_residual < 1e-3
    assert np.abs(colors - truth).max() < 0.03, np.abs(colors - truth).max()
    export_mesh(tmp_path / "fit.glb", mesh.vertices, mesh.faces, colors, up=None)
    asset = prepare_asset(read_glb(tmp_path / "fit.glb"))
    scores = [psnr(photos[i], render_asset(asset, cams[i].world_to_camera, cams[i].K, 64, 64, bg, 2)) for i in held]
    assert min(scores) > 40.0, scores


def test_the_prior_keeps_what_no_photo_sees(tmp_path):
    """Vertices on the far side of every camera keep the prior's colour; the strong default prior pulls the seen
    ones part of the way towards it (the model's colours), by the documented weight."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    truth = np.tile([[0.8, 0.2, 0.1]], (len(mesh.vertices), 1))
    bg = (1.0, 1.0, 1.0)
    cams = [c for c in _cams(n_az=6, elevations=(0.9,))]  # from high above: the bottom is never seen
    photos = _photos(tmp_path, mesh, truth, cams, bg)
    prior = np.tile([[0.2, 0.6, 0.9]], (len(mesh.vertices), 1))
    colors, stats = fit_vertex_colors(mesh.vertices, mesh.faces, zip(cams, photos), bg, prior)
    bottom = mesh.vertices[:, 2] < -0.9
    assert bottom.any() and stats.seen < len(mesh.vertices)
    np.testing.assert_allclose(colors[bottom], prior[bottom], atol=0.02)
    top = mesh.vertices[:, 2] > 0.9
    # seen squarely by every camera: between the photos and the prior, nearer the photos' colour
    d_truth, d_prior = np.abs(colors[top] - truth[top]).mean(), np.abs(colors[top] - prior[top]).mean()
    assert d_truth < d_prior and d_truth > 0.01


def test_the_file_keeps_the_models_colours_where_the_fitted_ones_lose(tmp_path):
    """choose_colours scores fitted and model colours on held-out views: the fit is kept unless the model's colours
    (which trained on those views) beat it by more than FIT_MAX_HOLDOUT_LOSS_DB."""
    from trisplat.texture.asset import FIT_MAX_HOLDOUT_LOSS_DB, MeshAsset, build_asset, choose_colours, holdout_views

    mesh = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(1)
    truth = rng.uniform(0.05, 0.95, (len(mesh.vertices), 3))
    bg = (1.0, 1.0, 1.0)
    cams = _cams(n_az=8, elevations=(-0.4, 0.2, 0.7), size=48)
    photos = _photos(tmp_path, mesh, truth, cams, bg)

    data = PhotoData(cams, bg, np.arange(len(cams)), photos)
    V = len(mesh.vertices)
    model = np.full((V, 3), 0.5, np.float32)  # a model whose band 0 is flat grey: the fit must win
    scene = coloured_scene(mesh.vertices, mesh.faces, model)
    asset = build_asset(scene, data, texture_size=0, supersample=2)
    rep = asset.colour_report
    held = holdout_views(list(range(len(cams))))
    assert rep["fit_views"] == len(cams) - len(held) and rep["holdout_views"] == len(held)
    assert rep["chosen"] == "fitted" and rep["holdout_psnr_fitted"] > rep["holdout_psnr_model"] + 3.0, rep
    assert asset.texture is None and asset.texture_report is None
    # colours worse than the model's (scrambled between vertices) lose to them: the file gets the model's
    bad = MeshAsset(asset.positions, asset.faces, asset.colors[rng.permutation(V)], None, None, {})
    choose_colours(bad, data, held, 2, 0.01, model_colors=truth.astype(np.float32))
    assert bad.colour_report["chosen"] == "model" and np.array_equal(bad.colors, truth.astype(np.float32))
    # a close call keeps the fit: a flat grey 0.45 against the model's flat 0.5 loses a fraction of a dB
    close = MeshAsset(asset.positions, asset.faces, np.full((V, 3), 0.45, np.float32), None, None, {})
    choose_colours(close, data, held, 2, 0.01, model_colors=model)
    rep = close.colour_report
    assert rep["holdout_psnr_model"] - FIT_MAX_HOLDOUT_LOSS_DB < rep["holdout_psnr_fitted"] < rep["holdout_psnr_model"]
    assert rep["chosen"] == "fitted" and np.allclose(close.colors, 0.45)
    # without a fit, build_asset leaves the model's colours and reports nothing
    plain = build_asset(scene, data, texture_size=0, fit_colours=False)
    assert plain.colour_report is None and np.allclose(plain.colors, model, atol=1e-6)


def test_a_mesh_no_view_sees_keeps_the_models_colours_and_says_why():
    """The fits need photos of the mesh; a mesh no camera sees keeps band 0 and no texture, and the reports say why
    (no crash at the end of a run)."""
    from trisplat.texture.asset import build_asset

    mesh = trimesh.creation.icosphere(subdivisions=1)
    cams = _cams(n_az=4, elevations=(0.0,), size=16)
    far = mesh.vertices + np.array([0.0, 0.0, 50.0])  # above every camera's view

    model = np.full((len(far), 3), 0.3, np.float32)
    scene = coloured_scene(far, mesh.faces, model)
    photos = [np.ones((16, 16, 3), np.float32)] * len(cams)
    data = PhotoData(cams, (1.0, 1.0, 1.0), np.arange(len(cams)), photos)
    for size in (0, 64):  # vertex colours alone, then with the texture (which no view sees either)
        asset = build_asset(scene, data, texture_size=size)
        assert asset.colour_report["chosen"] == "model" and "no view sees the mesh" in asset.colour_report["reason"]
        np.testing.assert_allclose(asset.colors, model, atol=1e-6)
        assert asset.texture is None
        assert size == 0 or "no view sees the mesh" in asset.texture_report["reason"]
    asset = build_asset(scene, data, texture_size=64, fit_colours=False)
    assert asset.texture is None and "no view sees the mesh" in asset.texture_report["reason"]
    from trisplat.texture.asset import choice_message

    assert "no view sees the mesh" in choice_message(asset.texture_report)


def test_a_corrupt_photo_fails_the_fit_naming_it():
    """Only "no view sees the mesh" falls back to the model's colours: a photo that cannot be read stops the fit
    with its own error, whether the texture shares the pass or not."""
    import pytest

    from trisplat.texture.asset import build_asset

    class Corrupt(PhotoData):
        def load_image(self, i):
            if i == 3:
                raise ValueError("photos/0003.png: cannot identify image file")
            return super().load_image(i)

    mesh = trimesh.creation.icosphere(subdivisions=1)
    cams = _cams(n_az=4, elevations=(0.0, 0.4), size=16)
    photos = [np.ones((16, 16, 3), np.float32)] * len(cams)
    scene = coloured_scene(mesh.vertices, mesh.faces, np.full((len(mesh.vertices), 3), 0.3, np.float32))
    for size in (0, 64):
        with pytest.raises(ValueError, match=r"photos/0003\.png: cannot identify"):
            build_asset(scene, Corrupt(cams, (1.0, 1.0, 1.0), np.arange(len(cams)), photos), texture_size=size)


def test_one_pass_over_the_views_feeds_both_fits(tmp_path):
    """build_asset rasterises each view once for the vertex colours and the texture: its colours and texture equal
    those of the two fits made apart (fit_vertex_colors, then texture_mesh with the fitted colours as prior)."""
    from trisplat.texture import texture_mesh
    from trisplat.texture.asset import build_asset

    mesh = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(2)
    truth = rng.uniform(0.05, 0.95, (len(mesh.vertices), 3))
    bg = (1.0, 1.0, 1.0)
    cams = _cams(n_az=6, elevations=(-0.3, 0.5), size=40)  # 12 views: none held out, no choice made
    photos = _photos(tmp_path, mesh, truth, cams, bg)
    data = PhotoData(cams, bg, np.arange(len(cams)), photos)
    model = np.full((len(mesh.vertices), 3), 0.5, np.float32)
    asset = build_asset(coloured_scene(mesh.vertices, mesh.faces, model), data, texture_size=64, supersample=2)
    assert asset.colour_report["fit_rows"].startswith("from the texture fit's pass")
    colors, _ = fit_vertex_colors(mesh.vertices, mesh.faces, zip(cams, photos), bg, model, 2, 0.01)
    np.testing.assert_allclose(asset.colors, colors, atol=1e-6)
    assert np.abs(colors - model).max() > 0.2  # the fit moved them: the comparison is not of two priors
    tex, _ = texture_mesh(np.asarray(mesh.vertices, np.float32), mesh.faces, colors, data, 64, 2, 0.01)
    np.testing.assert_array_equal(asset.texture.image, tex.image)
    np.testing.assert_array_equal(asset.texture.uv_faces, tex.uv_faces)
