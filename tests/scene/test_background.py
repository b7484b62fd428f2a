"""The background sphere of a real capture's far field (trisplat.scene.background): coloured from the photos in each
vertex's direction, facing the cameras, and rendering what the photos show behind everything."""
import numpy as np
import pytest
import torch

from trisplat.cameras import Camera
from trisplat.render.hard import rasterize_hard
from trisplat.scene.background import background_radius, background_sphere, photo_colours
from trisplat.scene.model import TriangleScene
from trisplat.synth.orbit import look_at

W, H = 96, 64


def _sky(d: np.ndarray) -> np.ndarray:
    """The colour the world shows in direction d (unit vectors [...,3]): smooth, different in every channel."""
    return (0.5 + 0.4 * d).astype(np.float32)


def _camera(eye, target) -> Camera:
    f = 0.5 * W / np.tan(np.radians(35))
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    return Camera(world_to_camera=look_at(eye, target), K=K, width=W, height=H, name="c")


def _photo(cam: Camera) -> np.ndarray:
    """What `cam` sees of an infinitely far _sky: the colour of each pixel centre's ray direction."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(cam.K).T @ cam.world_to_camera[:3, :3]
    return _sky(rays / np.linalg.norm(rays, axis=-1, keepdims=True))


@pytest.fixture(scope="module")
def ring():
    """Eight cameras near the origin looking out horizontally (z up), so straight up and down are never seen."""
    cams = []
    for k in range(8):
        a = 2 * np.pi * k / 8
        eye = 0.02 * np.array([np.cos(a), np.sin(a), 0.0])
        cams.append(_camera(eye, eye + np.array([np.cos(a), np.sin(a), 0.0])))
    return cams, [_photo(c) for c in cams]


def test_photo_colours_are_what_the_photos_show_in_each_direction(ring):
    cams, photos = ring
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d[:, 2] *= 0.3  # mostly near the horizon, where the cameras look
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    fallback = (0.1, 0.2, 0.3)
    got = photo_colours(50.0 * d, cams, lambda n: photos[n], fallback)
    seen = np.abs(d[:, 2]) < 0.3
    # a far point's colour is its direction's, up to the pixel it falls in (0.4 * about one pixel's angle)
    assert np.abs(got[seen] - _sky(d[seen])).max() < 0.02
    up = photo_colours(np.array([[0, 0, 50.0], [0, 0, -50.0]]), cams, lambda n: photos[n], fallback)
    np.testing.assert_allclose(up, [fallback, fallback])


def test_background_sphere_faces_the_cameras_and_renders_the_photos(ring):
    cams, photos = ring
    sky = background_sphere(20.0, cams, lambda n: photos[n], (0.5, 0.5, 0.5), sh_degree=2, opacity_floor=0.9)
    pos = sky.positions.numpy().astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(pos, axis=1), 20.0, rtol=1e-5)
    tri = pos[sky.faces.numpy()]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (np.einsum("ij,ij->i", normal, tri.mean(1)) < 0).all()  # every face is wound to face inwards
    assert sky.sh.shape[1] == 9 and torch.all(sky.sh[:, 1:] == 0)
    assert float(sky.opacities().min()) > 0.999 and sky.opacity_floor == 0.9
    # a view between two training cameras: the sphere shows what the photos show in its directions
    a = 2 * np.pi * 0.5 / 8
    cam = _camera((0, 0, 0), (np.cos(a), np.sin(a), 0.0))
    out = rasterize_hard(sky.positions, sky.faces, sky.sh, torch.as_tensor(cam.world_to_camera, dtype=torch.float32),
                         torch.as_tensor(cam.K, dtype=torch.float32), W, H, torch.zeros(3))
    assert float(out.alpha.min()) > 0.99  # no gap anywhere
    # (rows within 20 degrees of the horizon: the training photos' corners reach no higher)
    err = (out.rgb.numpy() - _photo(cam))[8:-8]
    psnr = -10 * np.log10(np.mean(err**2))
    assert psnr > 35.0, psnr


def test_background_radius_lies_beyond_the_scene_but_not_beyond_a_stray_face():
    rng = np.random.default_rng(1)
    pos = rng.uniform(-3, 3, size=(3000, 3)).astype(np.float32)
    pos[-3:] = [[400, 0, 0], [401, 0, 0], [400, 1, 0]]  # one stray face far out
    faces = np.arange(3000).reshape(-1, 3)
    sc = TriangleScene(torch.as_tensor(pos), torch.zeros(3000, 1, 3), torch.zeros(3000), torch.as_tensor(faces,
                       dtype=torch.int32))
    centres = np.linalg.norm(pos[faces[:-1]].mean(1), axis=1)
    r = background_radius(sc)
    assert centres.max() < r < 2 * centres.max()
    small = TriangleScene(torch.as_tensor(pos[:3] * 0.01), torch.zeros(3, 1, 3), torch.zeros(3),
                          torch.as_tensor([[0, 1, 2]], dtype=torch.int32))
    assert background_radius(small) == 2.0  # MIN_RADIUS
