"""Visual hull carving and the `hull` initialisation: a sphere's silhouettes carve a ball, samples sit on its surface
with outward normals, colours come from the images, and inconsistent or missing masks are clear errors."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_data

from trisplat.data.types import SceneData
from trisplat.scene import hull as vh
from trisplat.scene.init import init_hull, init_soup, initial_scene
from trisplat.synth.orbit import orbit_cameras

RADIUS = 0.5


def sphere_views(n=24, size=64, colour_split=True):
    """Cameras around a sphere of RADIUS at the origin; exact silhouettes (alpha) and images whose object pixels
    are red where the sphere's visible point has z > 0 and blue below (background white)."""
    cams = orbit_cameras(n, 3.0, size, size, fov_deg=30.0, elevation_deg=(-60.0, 60.0))
    masks, images = [], []
    for cam in cams:
        v, u = np.mgrid[0:size, 0:size] + 0.5
        rays = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
        rays = rays @ cam.world_to_camera[:3, :3]  # camera -> world directions
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        o = cam.center
        b = rays @ o
        disc = b * b - (o @ o - RADIUS**2)
        hit = disc >= 0
        t = -b - np.sqrt(np.maximum(disc, 0))
        p = o + t[..., None] * rays
        img = np.ones((size, size, 3))
        if colour_split:
            img[hit & (p[..., 2] > 0)] = [1, 0, 0]
            img[hit & (p[..., 2] <= 0)] = [0, 0, 1]
        masks.append(hit.astype(np.float32))
        images.append(img.astype(np.float32))
    return cams, masks, images


def sphere_scene(masks_override=None) -> SceneData:
    cams, masks, images = sphere_views()
    if masks_override is not None:
        masks = masks_override(masks)
    return SceneData(cameras=cams, train_indices=np.arange(len(cams)), test_indices=np.array([], dtype=np.int64),
                     bounds=np.array([[-0.75] * 3, [0.75] * 3]), image_loader=lambda i: images[i],
                     alpha_loader=lambda i: masks[i], format="blender")


def test_carve_keeps_the_ball_and_removes_the_outside():
    cams, masks, _ = sphere_views()
    hull = vh.carve(cams, masks, np.array([[-0.75] * 3, [0.75] * 3]), resolution=48)
    ijk = np.argwhere(np.ones_like(hull.occupied))
    r = np.linalg.norm(hull.centers(ijk), axis=1).reshape(hull.occupied.shape)
    assert hull.views == len(cams)
    assert hull.occupied[r < RADIUS - hull.voxel].all()  # nothing inside the object is carved (dilated masks)
    assert not hull.occupied[r > 1.25 * RADIUS].any()  # 24 views around the ball leave little of the box
    # a view without a mask carves nothing; carving with it skipped matches carving without it
    again = vh.carve(cams + [cams[0]], masks + [None], np.array([[-0.75] * 3, [0.75] * 3]), resolution=48)
    assert np.array_equal(again.occupied, hull.occupied) and again.views == hull.views


def test_surface_samples_on_the_sphere_with_outward_normals():
    cams, masks, _ = sphere_views()
    hull = vh.carve(cams, masks, np.array([[-0.75] * 3, [0.75] * 3]), resolution=48)
    pts, normals = vh.surface_samples(hull, 2000, np.random.default_rng(0))
    r = np.linalg.norm(pts, axis=1)
    assert np.abs(r - RADIUS).max() < 0.25 * RADIUS and abs(np.median(r) - RADIUS) < 2 * hull.voxel
    radial = pts / r[:, None]
    assert np.median(np.sum(normals * radial, axis=1)) > 0.95  # outward, not inward
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=1e-6)


def test_mean_colours_come_from_the_images():
    cams, masks, images = sphere_views()
    pts = np.array([[0, 0, RADIUS], [0, 0, -RADIUS], [0.0, 0.0, 10.0]])  # top (red), bottom (blue), outside every view
    cols = vh.mean_colors(cams, images, masks, pts)
    np.testing.assert_allclose(cols[0], [1, 0, 0], atol=0.15)
    np.testing.assert_allclose(cols[1], [0, 0, 1], atol=0.15)
    np.testing.assert_allclose(cols[2], [0.5, 0.5, 0.5])  # never seen on the object


def test_soup_with_normals_lies_in_the_tangent_planes():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(200, 3))
    normals = rng.normal(size=(200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    scene, _ = init_soup(pts, normals=normals, seed=0)
    p = scene.positions.numpy().reshape(-1, 3, 3)
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(fn * normals, axis=1)), 1.0, atol=1e-4)
    np.testing.assert_allclose(p.mean(1), pts, atol=1e-5)  # centred on their points
    with pytest.raises(ValueError, match="differ in length"):
        init_soup(pts, normals=normals[:10])


def test_hull_init_and_auto_choice():
    data = sphere_scene()
    scene, report = initial_scene(data, random_points=500, sh_degree=1)
    assert report.method == "hull" and scene.num_faces == 500
    c = scene.positions.numpy()[scene.faces.numpy()].mean(1)
    assert np.abs(np.linalg.norm(c, axis=1) - RADIUS).max() < 0.25 * RADIUS  # on the sphere, not in the box
    # colours: triangles above the equator start red, those below blue
    from trisplat.scene.sh import C0

    rgb = (scene.sh[:, 0].numpy() * C0 + 0.5)[scene.faces.numpy()[:, 0]]
    top, bottom = c[:, 2] > 0.2, c[:, 2] < -0.2
    assert (rgb[top, 0] > rgb[top, 2]).mean() > 0.9 and (rgb[bottom, 2] > rgb[bottom, 0]).mean() > 0.9


def test_hull_init_errors():
    with pytest.raises(ValueError, match="alpha channel"):
        init_hull(sphere_scene(lambda m: [None] * len(m)), 100)
    # masks of some other object (a tiny blob off-centre in each view) leave nothing: a clear error
    def wrong(masks):
        out = []
        for i, m in enumerate(masks):
            w = np.zeros_like(m)
            w[(5 * i) % 60: (5 * i) % 60 + 2, 3:5] = 1
            out.append(w)
        return out

    with pytest.raises(ValueError, match="disagree"):
        init_hull(sphere_scene(wrong), 100)
    # without alpha, auto falls back to random points in the box
    _, report = initial_scene(sphere_scene(lambda m: [None] * len(m)), random_points=50)
    assert report.method == "random"


def test_lego_uses_the_visual_hull(tmp_path):
    from trisplat.data import load_dataset

    lego = load_dataset(shared_data("lego"), downscale=4, cache_dir=tmp_path, prepare="lazy")
    cam0 = lego.cameras[int(lego.train_indices[0])]
    assert lego.load_alpha(int(lego.train_indices[0])).shape == (cam0.height, cam0.width)
    scene, report = initial_scene(lego, random_points=1000, sh_degree=0)
    assert report.method == "hull" and scene.num_faces == 1000
    # every initial triangle centre projects onto the object in the held-out views (dilated by 2 px)
    from scipy import ndimage

    c = scene.positions.numpy()[scene.faces.numpy()].mean(1).astype(np.float64)
    for i in lego.test_indices[:5]:
        cam = lego.cameras[int(i)]
        u, v, z = vh._project(cam, c)
        m = ndimage.binary_dilation(lego.load_alpha(int(i)) >= 0.5, iterations=2)
        ok = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        assert m[np.floor(v[ok]).astype(int), np.floor(u[ok]).astype(int)].mean() > 0.97
