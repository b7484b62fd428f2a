"""The glTF spec renderer shows what the specification defines: sRGB texture decoded, filtered, re-encoded; linear
COLOR_0 encoded; single-sided faces culled; the file's frame mapped back onto the run's cameras."""
from __future__ import annotations

import numpy as np
import pytest

from trisplat.eval.spec_render import prepare_asset, render_asset
from trisplat.io import export_mesh
from trisplat.io.colour import linear_to_srgb, srgb_to_linear
from trisplat.io.gltf import TextureMap, read_glb

# a square [-1,1]^2 at z = 0 seen from z = -2 (OpenCV camera looking along +z), filling the middle of a 40x40 view
W2C = np.eye(4)
W2C[2, 3] = 2.0
K = np.array([[20.0, 0, 20], [0, 20.0, 20], [0, 0, 1]])
QUAD = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
FACES = np.array([[0, 2, 1], [0, 3, 2]])  # counter-clockwise seen from the camera (front side towards it)


def _render(tmp_path, colors=None, texture=None, supersample=1):
    export_mesh(tmp_path / "q.glb", QUAD, FACES, colors, up=None, texture=texture)
    asset = prepare_asset(read_glb(tmp_path / "q.glb"))
    return render_asset(asset, W2C, K, 40, 40, (1.0, 1.0, 1.0), supersample)


def test_vertex_colours_come_out_as_the_srgb_values_written(tmp_path):
    img = _render(tmp_path, colors=np.full((4, 3), 0.3))
    assert np.allclose(img[20, 20], np.round(0.3 * 255) / 255, atol=1e-5)  # decoded then re-encoded
    assert np.allclose(img[1, 1], 1.0)  # background


def test_texture_is_decoded_filtered_in_linear_and_encoded(tmp_path):
    image = np.zeros((2, 2, 3), np.uint8)
    image[:, 1] = 255  # left column black, right column white
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float64)  # v down: the camera's top row is image row 0
    img = _render(tmp_path, texture=TextureMap(uv, FACES.copy(), image))
    # the quad spans pixel columns 10..30; at pixel centre x + 0.5, u = (x + 0.5 - 10) / 20 and the bilinear weight of
    # the white texel column is clip(2u - 0.5, 0, 1): in LINEAR light, so the screen shows its sRGB encoding
    cols = np.arange(10, 30)
    weight = np.clip(2 * (cols + 0.5 - 10) / 20 - 0.5, 0, 1)
    assert np.allclose(img[20, cols, 0], linear_to_srgb(weight), atol=2e-3)
    assert img[20, 20, 0] > 0.7  # filtering the sRGB bytes would give about 0.55 here


def test_single_sided_back_faces_are_culled(tmp_path):
    export_mesh(tmp_path / "q.glb", QUAD, FACES[:, ::-1], np.full((4, 3), 0.3), up=None)
    asset = prepare_asset(read_glb(tmp_path / "q.glb"))
    assert np.allclose(render_asset(asset, W2C, K, 40, 40)[20, 20], 0.3, atol=3e-3)  # ours are double-sided
    asset.single_sided[:] = True
    assert np.allclose(render_asset(asset, W2C, K, 40, 40)[20, 20], 1.0)


def test_supersampled_edges_average_in_linear_light(tmp_path):
    # the quad's left edge at x = -1 -> pixel column 10.0 exactly; shift it half a pixel by moving the camera
    w2c = W2C.copy()
    w2c[0, 3] = 0.05  # 0.05 * 20 / 2 = 0.5 px
    export_mesh(tmp_path / "q.glb", QUAD, FACES, np.zeros((4, 3)), up=None)
    asset = prepare_asset(read_glb(tmp_path / "q.glb"))
    img = render_asset(asset, w2c, K, 40, 40, (1.0, 1.0, 1.0), supersample=2)
    edge = img[20, 10, 0]  # half black, half white samples
    assert edge == pytest.approx(float(linear_to_srgb(np.array([0.5]))[0]), abs=1e-4)
    assert float(srgb_to_linear(np.array([edge]))[0]) == pytest.approx(0.5, abs=1e-4)


def test_vertex_colour_asset_renders_as_its_glb_does(tmp_path):
    """A PLY's sRGB vertex colours in memory render as the same mesh written as a GLB (linear COLOR_0) does: decoded,
    interpolated in linear light, encoded; a black / white gradient is 0.735 (sRGB of 0.5 linear) half-way, not 0.5."""
    from trisplat.eval.spec_render import vertex_colour_asset

    colours = np.array([[0, 0, 0], [1, 1, 1], [1, 1, 1], [0, 0, 0]], np.float64)  # black left, white right
    from_file = _render(tmp_path, colors=colours)
    direct = render_asset(vertex_colour_asset(QUAD, FACES, colours), W2C, K, 40, 40, (1.0, 1.0, 1.0))
    assert np.abs(direct - from_file).max() < 2e-3
    assert abs(direct[20, 20, 0] - linear_to_srgb(0.5 / 20 + 0.5)) < 5e-3  # pixel 20's centre is at u = 0.525
    with pytest.raises(ValueError, match="colours"):
        vertex_colour_asset(QUAD, FACES, colours[:3])


def test_linear_light_model_renders_as_its_vertex_colour_file_does():
    """A model blending in linear light (TriangleScene.linear_light) shows what a glTF viewer shows of its vertex
    colours, edges averaged over supersamples included; blending the sRGB values, as the soup does, does not."""
    import torch

    from trisplat.eval.spec_render import vertex_colour_asset
    from trisplat.render import rasterize, rasterize_hard

    rng = np.random.default_rng(3)
    # a bumpy grid of 8x8 quads, tilted away from the camera, with random saturated vertex colours
    u, v = np.meshgrid(np.linspace(-1.2, 1.2, 9), np.linspace(-1.2, 1.2, 9))
    pos = np.stack([u, v, 0.6 * u + 0.1 * rng.standard_normal(u.shape)], -1).reshape(-1, 3)
    idx = np.arange(81).reshape(9, 9)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)])
    colours = rng.choice([0.02, 0.3, 0.95], size=pos.shape)
    w2c = W2C.copy()
    w2c[0, 3] = 0.013  # edges off the pixel grid
    bg = (0.2, 0.4, 0.9)
    viewer = render_asset(vertex_colour_asset(pos, faces, colours), w2c, K, 40, 40, bg, supersample=2)

    P, F = torch.tensor(pos, dtype=torch.float32), torch.tensor(faces, dtype=torch.int32)
    C = torch.tensor(colours, dtype=torch.float32)
    T, Kt = torch.tensor(w2c, dtype=torch.float32), torch.tensor(K, dtype=torch.float32)

    def psnr(img):
        return float(-10 * np.log10(np.mean((img.detach().numpy().clip(0, 1) - viewer) ** 2)))

    hard = {ll: rasterize_hard(P, F, C, T, Kt, 40, 40, torch.tensor(bg), perspective_correct=True, supersample=2,
                               linear_light=ll).rgb for ll in (True, False)}
    assert psnr(hard[True]) > 50
    assert psnr(hard[False]) < 30  # sRGB blending darkens every mixed colour: visibly another picture
    soft = rasterize(P, F, C, torch.ones(len(P)), 1e-3, T, Kt, 40, 40, background=torch.tensor(bg), supersample=2,
                     perspective_correct=True, linear_light=True, alpha_max=1.0 - 1e-6).rgb
    assert psnr(soft) > 40  # the training renderer with a sharp window and opaque faces: the same picture
