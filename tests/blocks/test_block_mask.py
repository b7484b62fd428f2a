"""A block's photos of a masked capture (trisplat.blocks.mask, through block_scene_data): the pixels whose true content
lies beyond the block's box, on rays that pass through the box, are made background (the block must not explain
them with a haze inside its box), and the pixels whose content lies in the box are kept. The truth is the synthetic
street's own geometry, ray-cast per pixel."""
import numpy as np
import pytest
import trimesh

from trisplat.blocks.mask import outside_content, ray_box
from trisplat.blocks.partition import partition
from trisplat.blocks.run_ray import block_scene_data
from trisplat.data import load_dataset
from trisplat.synth.raycast import _cast, _intersector, _pixel_rays


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    from trisplat.synth.street import write_street_scene

    return write_street_scene(tmp_path_factory.mktemp("street") / "capture", n_objects=3, views_per_object=6,
                              width=48, height=32, samples_per_pixel=1, n_points=900)


def _content_box(data, block) -> np.ndarray:
    box, full = np.asarray(block.box, dtype=np.float64), np.asarray(data.bounds, dtype=np.float64)
    return np.stack([np.maximum(box[0], full[0]), np.minimum(box[1], full[1])])


def test_pixels_showing_content_beyond_the_block_are_background_and_the_block_keeps_its_own(street):
    data = load_dataset(str(street))
    mesh = trimesh.load(street / "gt_mesh.ply", process=False)
    mesh.apply_transform(np.asarray(data.normalization, dtype=np.float64))  # into the cameras' (normalised) frame
    isect = _intersector(mesh)
    plan = partition(data, 2)
    bg = np.asarray(data.background, dtype=np.float32)
    counts = {"inside": 0, "inside_masked": 0, "beyond": 0, "beyond_masked": 0}
    for block in plan.blocks:
        bd = block_scene_data(data, block)
        box = _content_box(data, block)
        for k, i in enumerate(block.train + block.test):
            cam = data.cameras[i]
            o, d = _pixel_rays(cam, (0.5, 0.5))
            face, loc = _cast(isect, o, d)
            hit = face >= 0
            t_hit = np.where(hit, np.linalg.norm(np.nan_to_num(loc) - o, axis=1), 0.0)
            x = np.nan_to_num(loc)
            # in the box (the ground lies on its floor: a hair of tolerance); clearly out of it (by 5% of its size)
            eps, far = 1e-6 * float(np.ptp(box, axis=0).max()), 0.05 * float(np.ptp(box, axis=0).max())
            in_box = hit & np.all((x >= box[0] - eps) & (x <= box[1] + eps), axis=1)
            out_box = hit & ~np.all((x >= box[0] - far) & (x <= box[1] + far), axis=1)
            # the ray runs through the box before it reaches its content (sampled: no shared code with the mask)
            s = np.linspace(0.02, 0.9, 45)
            along = o[:, None, :] + (s[None, :, None] * t_hit[:, None, None]) * d[:, None, :]
            crosses = np.any(np.all((along >= box[0]) & (along <= box[1]), axis=2), axis=1)
            beyond = out_box & crosses
            alpha0 = np.asarray(data.load_alpha(i)).ravel()
            alpha = np.asarray(bd.load_alpha(k)).ravel()
            img = np.asarray(bd.load_image(k)).reshape(-1, 3)
            masked = (alpha0 > 0.5) & (alpha < 0.5)
            # a masked pixel is the photo's own background: the capture's background colour, alpha 0
            assert np.allclose(img[masked], bg) and np.all(alpha[masked] == 0.0)
            kept = ~masked
            np.testing.assert_array_equal(img[kept], np.asarray(data.load_image(i)).reshape(-1, 3)[kept])
            sure = alpha0 > 0.99
            counts["inside"] += int((in_box & sure).sum())
            counts["inside_masked"] += int((in_box & sure & masked).sum())
            counts["beyond"] += int((beyond & sure).sum())
            counts["beyond_masked"] += int((beyond & sure & masked).sum())
    assert counts["beyond"] > 300 and counts["inside"] > 5000, counts  # the street's blocks see both, plenty
    assert counts["beyond_masked"] >= 0.9 * counts["beyond"], counts
    assert counts["inside_masked"] <= 0.03 * counts["inside"], counts


def test_photos_without_alpha_are_left_whole(street):
    data = load_dataset(str(street))
    plan = partition(data, 2)
    data.alpha_loader = lambda i: None  # as the photos of a real scene: the block keeps a far field for the rest
    b = plan.blocks[0]
    bd = block_scene_data(data, b)
    for k, i in enumerate(b.train[:3]):
        np.testing.assert_array_equal(bd.load_image(k), data.load_image(i))
    # and the switch is there to turn it off
    data2 = load_dataset(str(street))
    bd2 = block_scene_data(data2, b, mask_outside=False)
    np.testing.assert_array_equal(bd2.load_image(0), data2.load_image(b.train[0]))


def test_ray_box_and_the_rays_that_miss_it():
    from trisplat.cameras import Camera
    from trisplat.synth.orbit import look_at

    K = np.array([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]])
    cam = Camera(look_at((0.0, -5.0, 0.0), (0.0, 0.0, 0.0)), K, 16, 16, name="c")
    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    from trisplat.blocks.mask import pixel_rays

    c, d = pixel_rays(cam)
    t_in, t_out = ray_box(c, d, box)
    centre = 8 * 16 + 8  # the ray through pixel (8.5, 8.5), almost the optical axis: enters at y = -1, leaves at 1
    assert t_in[centre] == pytest.approx(4.0, rel=2e-3) and t_out[centre] == pytest.approx(6.0, rel=2e-3)
    # a point on the far side of the box, right behind it: every ray through the box toward it is free there
    pts = np.array([[0.0, 3.0, 0.0]])
    out = outside_content(cam, pts, box, radius=1.0, radius_fill=1.0)
    assert out[8, 8] and out.sum() >= 1
    # a point inside the box: kept; a ray that misses the box: background whatever it shows
    out = outside_content(cam, np.array([[0.0, 0.0, 0.0]]), box, radius=1.0, radius_fill=1.0)
    assert not out[8, 8]
    corner_misses = t_in[0] > t_out[0]  # pixel (0.5, 0.5): 7.5 pixels off axis at focal 20 -> 1.9 units at y = -1
    assert corner_misses and out[0, 0]
