"""A block's own capture (trisplat.blocks.run_ray.block_scene_data) and the storage of block outputs (Store: a folder
in place, or an fsspec URL through a local scratch copy)."""
import json

import numpy as np
import pytest

from trisplat.blocks.partition import partition
from trisplat.blocks.run_ray import Store, block_scene_data, block_similarity
from trisplat.data.normalize import apply_to_points

from tests.blocks.test_partition import _street_data


def test_block_frame_maps_the_box_onto_the_unit_cube_and_keeps_every_pixel():
    data = _street_data()
    data.image_loader = lambda i: np.full((48, 64, 3), i / 100.0, np.float32)
    plan = partition(data, 3, up=np.array([0.0, 0.0, 1.0]))
    b = plan.blocks[1]
    bd = block_scene_data(data, b)
    box = apply_to_points(block_similarity(b.box), np.asarray(b.box))
    assert np.allclose(np.abs(box).max(), 1.0) and np.allclose(box.mean(0), 0.0, atol=1e-9)
    order = b.train + b.test
    assert len(bd.cameras) == len(order) and list(bd.train_indices) == list(range(len(b.train)))
    assert list(bd.test_indices) == list(range(len(b.train), len(order)))
    # the block's views see the block's points at the same pixels as the scene's views see the scene's
    M = block_similarity(b.box)
    inside = np.all((data.points >= np.asarray(b.box)[0]) & (data.points <= np.asarray(b.box)[1]), axis=1)
    assert len(bd.points) == inside.sum() > 0
    x = data.points[inside][:50].astype(np.float64)
    for k, i in enumerate(order[:5]):
        def project(cam, p):
            c = p @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
            uv = c @ cam.K.T
            return uv[:, :2] / uv[:, 2:]
        np.testing.assert_allclose(project(bd.cameras[k], apply_to_points(M, x)), project(data.cameras[i], x),
                                   atol=1e-6)
        assert float(bd.load_image(k)[0, 0, 0]) == pytest.approx(i / 100.0)  # the scene's photo of that view
    assert np.allclose(bd.normalization, M @ data.normalization)
    assert (bd.bounds[1] > bd.bounds[0]).all() and np.abs(bd.bounds).max() <= 1.0 + 1e-9


def test_store_in_a_folder_and_at_a_url(tmp_path):
    plain = Store(tmp_path / "shared")
    assert plain.local("block_00") == tmp_path / "shared" / "block_00"
    url = Store(f"file://{tmp_path / 'bucket'}")
    assert url.is_url and url.local("block_00") != tmp_path / "bucket" / "block_00"
    local = url.local("block_00")
    (local / "checkpoints").mkdir(parents=True, exist_ok=True)
    (local / "checkpoints" / "last.pt").write_bytes(b"12345")
    (local / "progress.json").write_text(json.dumps({"step": 7}))
    url.push("block_00")
    assert (tmp_path / "bucket" / "block_00" / "checkpoints" / "last.pt").read_bytes() == b"12345"
    assert url.read_json("block_00", "progress.json") == {"step": 7}
    assert url.read_json("block_01", "progress.json") is None
    # a retry on another machine starts from an empty scratch folder and gets the checkpoint back
    import shutil

    shutil.rmtree(local)
    url.pull("block_00")
    assert (local / "checkpoints" / "last.pt").read_bytes() == b"12345"
