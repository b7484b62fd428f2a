"""Issue 26, item 4: the switch streams its views. It holds one photo at a time (it used to load every training photo
as float32 at once), keeps its depth maps in memory only up to `depth_memory_mb` (the rest on disk, read back one
at a time, with the same result), and says where to make room when the disk is full. The measured peak for 300
photos of 12 MP is in docs/benchmarks.md ("Switch memory", `trisplat bench switch-memory`)."""
from __future__ import annotations

import weakref

import numpy as np
import pytest

from trisplat.train.switch import DepthStore, SurfaceConfig, soup_to_surface

from tests.mesh.test_fusion import fibonacci_cameras
from tests.train.test_switch import _render, layered_sphere_soup

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


@pytest.fixture(scope="module")
def sphere():
    soup = layered_sphere_soup(n=600)
    cams = fibonacci_cameras(12)
    renders = [_render(soup, c) for c in cams]
    return soup, cams, renders


def test_switch_holds_one_photo_at_a_time_and_spilled_depths_give_the_same_surface(sphere):
    soup, cams, renders = sphere
    alive, most, asked = [0], [0], []

    def gone():
        alive[0] -= 1

    def photo(n):
        asked.append(n)
        img = np.zeros((cams[n].height, cams[n].width, 3), np.uint8)
        img[..., 1] = 255  # uint8 photos are read as /255: green
        alive[0] += 1
        most[0] = max(most[0], alive[0])
        weakref.finalize(img, gone)
        return img

    cfg = SurfaceConfig(resolution=40, face_ratio=2.0)
    kept, rep_kept = soup_to_surface(soup, cams, lambda n: renders[n], BOX, cfg, images=photo)
    assert asked == list(range(len(cams))) and most[0] == 1  # each photo loaded once, dropped before the next
    spilled, rep_spilled = soup_to_surface(soup, cams, lambda n: renders[n], BOX,
                                           SurfaceConfig(resolution=40, face_ratio=2.0, depth_memory_mb=0.0),
                                           images=photo)
    assert any(f"{len(cams)} of {len(cams)} depth maps kept on disk" in n for n in rep_spilled.notes)
    assert not any("on disk" in n for n in rep_kept.notes)
    np.testing.assert_array_equal(spilled.positions.numpy(), kept.positions.numpy())
    np.testing.assert_array_equal(spilled.faces.numpy(), kept.faces.numpy())
    np.testing.assert_array_equal(spilled.sh.numpy(), kept.sh.numpy())
    # the photos' colour (uint8 green) is the base colour of the vertices the views see
    from trisplat.scene.sh import sh_dc_to_rgb

    rgb = sh_dc_to_rgb(kept.sh[:, 0, :]).numpy()
    seen = rgb[:, 1] > 0.99
    assert seen.mean() > 0.5 and np.allclose(rgb[seen], [0.0, 1.0, 0.0], atol=1e-5)


def test_depth_store_spills_past_its_budget_and_cleans_up():
    maps = [np.full((30, 40), float(k), np.float32) for k in range(5)]
    with DepthStore(2 * maps[0].nbytes) as store:
        for d in maps:
            store.append(d)
        assert len(store) == 5 and store.spilled == 3
        folder = store._dir.name
        for k, d in enumerate(store):
            assert d.dtype == np.float32 and np.array_equal(d, maps[k])
        assert np.array_equal(store[-1], maps[4]) and len(store[1:3]) == 2
    import os

    assert not os.path.exists(folder)


def test_a_full_disk_names_the_file_and_the_way_out(monkeypatch):
    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "save", full)
    with DepthStore(0) as store, pytest.raises(RuntimeError, match=r"depth map 0 to .*depth_000000\.npy.*TMPDIR"):
        store.append(np.zeros((4, 4), np.float32))
