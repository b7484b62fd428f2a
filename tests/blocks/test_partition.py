"""Blocks of a scene (trisplat.blocks.partition): every camera and point in exactly one cell, margins of the asked
size on the inner sides only, views assigned by what they see, the dry run's table, and --blocks without Ray."""
import math
import sys

import numpy as np
import pytest

from trisplat.blocks.partition import grid_for, in_rect, partition, plan_lines, resolve_count
from trisplat.cameras import Camera
from trisplat.data.types import SceneData
from trisplat.synth.orbit import look_at
from trisplat.train.config import make_config


def _street_data(n_cams: int = 24, length: float = 2.0) -> SceneData:
    """A scene along x in the normalised frame: points on a strip (z = 0) and on posts, cameras on both sides
    looking at the axis right in front of them."""
    rng = np.random.default_rng(0)
    ground = np.column_stack([rng.uniform(-length / 2, length / 2, 2000), rng.uniform(-0.1, 0.1, 2000),
                              np.zeros(2000)])
    posts = np.column_stack([rng.uniform(-length / 2, length / 2, 500), rng.uniform(-0.02, 0.02, 500),
                             rng.uniform(0, 0.1, 500)])
    pts = np.concatenate([ground, posts]).astype(np.float32)
    W, H = 64, 48
    K = np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])
    cams = []
    for i, x in enumerate(np.linspace(-length / 2, length / 2, n_cams)):
        side = 1 if i % 2 == 0 else -1
        cams.append(Camera(look_at((x, side * 0.3, 0.15), (x, 0.0, 0.0)), K, W, H, name=f"c{i}"))
    test = np.arange(0, n_cams, 8)
    train = np.setdiff1d(np.arange(n_cams), test)
    return SceneData(cameras=cams, train_indices=train, test_indices=test, points=pts,
                     point_colors=np.full_like(pts, 0.5), bounds=np.array([[-1.0, -0.2, 0.0], [1.0, 0.2, 0.1]]),
                     format="colmap")


def test_every_camera_and_point_lies_in_exactly_one_cell():
    data = _street_data()
    plan = partition(data, 4, up=np.array([0.0, 0.0, 1.0]))
    assert plan.grid == (4, 1)  # a long scene is cut across its length
    centres = np.stack([c.center for c in data.cameras])
    for x in (data.points, centres, np.array([[50.0, -40.0, 3.0], [-50.0, 40.0, -3.0]])):  # far outside too
        uv = plan.ground(x)
        hits = np.stack([in_rect(uv, b.cell) for b in plan.blocks])
        assert (hits.sum(0) == 1).all()
    # cells split the content evenly (quantiles of the points)
    counts = np.bincount(plan.cell_of(data.points), minlength=4)
    assert counts.min() >= 0.2 * len(data.points)
    # along +x: block 0 holds the lowest x
    xs = [float(np.mean(data.points[plan.cell_of(data.points) == b.index][:, 0])) for b in plan.blocks]
    assert xs == sorted(xs)


def test_margins_grow_inner_sides_only_by_the_asked_fraction():
    data = _street_data()
    plan = partition(data, 4, margin=0.25, up=np.array([0.0, 0.0, 1.0]))
    b0, b1 = plan.blocks[0], plan.blocks[1]
    assert b0.cell[0][0] == -math.inf and b0.expanded[0][0] == -math.inf  # outer side: not grown, unbounded
    w1 = b1.cell[1][0] - b1.cell[0][0]
    assert b1.expanded[0][0] == pytest.approx(b1.cell[0][0] - 0.25 * w1)
    assert b1.expanded[1][0] == pytest.approx(b1.cell[1][0] + 0.25 * w1)
    # the box of a block covers its expanded cell within the content and every point of it
    for b in plan.blocks:
        box = np.asarray(b.box)
        inside = in_rect(plan.ground(data.points), b.expanded)
        assert inside.sum() == b.points > 0
        assert (data.points[inside] >= box[0] - 1e-6).all() and (data.points[inside] <= box[1] + 1e-6).all()
    no_margin = partition(data, 4, margin=0.0, up=np.array([0.0, 0.0, 1.0]))
    assert sum(b.points for b in no_margin.blocks) == len(data.points)  # no overlap without a margin
    assert sum(b.points for b in plan.blocks) > len(data.points)


def test_views_go_to_the_blocks_they_see():
    data = _street_data()
    plan = partition(data, 4, margin=0.1, up=np.array([0.0, 0.0, 1.0]))
    centres_uv = plan.ground(np.stack([c.center for c in data.cameras]))
    for i in data.train_indices:
        owners = [b.index for b in plan.blocks if i in b.train]
        assert owners, f"view {i} in no block"
        # a camera whose centre lies in a block's expanded cell belongs to it
        for b in plan.blocks:
            if in_rect(centres_uv[i][None], b.expanded)[0]:
                assert i in b.train
    # a view added by visibility alone: a camera far outside a cell looking into it
    look = Camera(look_at((-3.0, 0.0, 0.3), (0.6, 0.0, 0.0)), data.cameras[0].K, 64, 48, name="far")
    data.cameras.append(look)
    data.train_indices = np.append(data.train_indices, len(data.cameras) - 1)
    plan = partition(data, 4, margin=0.1, up=np.array([0.0, 0.0, 1.0]))
    k = len(data.cameras) - 1
    assert k in plan.blocks[0].train  # its centre lies in block 0's (unbounded) cell
    seen_by = {b.index for b in plan.blocks if k in b.train}
    assert len(seen_by) >= 2  # and it sees the blocks down the street too
    # test views are assigned too, every one to some block
    assert set(data.test_indices) <= {i for b in plan.blocks for i in b.test}


def test_grid_and_counts():
    assert grid_for(4, 40.0, 8.0) == (4, 1)
    assert grid_for(4, 10.0, 10.0) == (2, 2)
    assert grid_for(6, 10.0, 30.0) == (2, 3)
    assert resolve_count("auto", 150) == 1 and resolve_count("auto", 1000) == 5 and resolve_count("3", 10) == 3
    for bad in ("0", "-2", "many"):
        with pytest.raises(ValueError, match="--blocks"):
            resolve_count(bad, 10)


def test_plan_lines_list_every_block_with_its_views_and_estimates():
    data = _street_data()
    plan = partition(data, 3, up=np.array([0.0, 0.0, 1.0]))
    lines = plan_lines(plan, data, make_config("fast"))
    assert lines[0].startswith("3 blocks (3 x 1 cells")
    rows = [line for line in lines if line.startswith("block_")]
    assert len(rows) == 3
    for b, row in zip(plan.blocks, rows):
        cols = row.split()
        assert int(cols[-6]) == len(b.train) and int(cols[-5]) == len(b.test) and int(cols[-4]) == b.points
        assert int(cols[-2]) == b.estimates["memory_mb"] > 0
    assert "over all blocks" in lines[-1]


def test_plan_dry_run_from_the_command_line(tmp_path, capsys):
    from trisplat.cli import main
    from trisplat.synth.street import write_street_scene

    cap = write_street_scene(tmp_path / "street", n_objects=3, views_per_object=4, width=32, height=24,
                             samples_per_pixel=1)
    # --blocks 1 --plan needs no Ray; it prints one block holding every training view and trains nothing
    assert main(["train", str(cap), "--out", str(tmp_path / "run"), "--preset", "fast", "--blocks", "1",
                 "--plan"]) == 0
    out = capsys.readouterr().out
    assert "1 blocks (1 x 1 cells" in out and out.count("\nblock_00") == 1
    assert not (tmp_path / "run").exists()
    pytest.importorskip("ray")
    assert main(["train", str(cap), "--out", str(tmp_path / "run"), "--preset", "fast", "--blocks", "3",
                 "--plan"]) == 0
    out = capsys.readouterr().out
    assert "3 blocks (3 x 1 cells" in out and [ln[:8] for ln in out.splitlines() if ln.startswith("block_")] == \
        ["block_00", "block_01", "block_02"]
    assert not (tmp_path / "run").exists()


def test_blocks_without_ray_fail_at_once_with_the_install_command(tmp_path, monkeypatch, capsys):
    from trisplat.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ModuleNotFoundError
    # the capture does not even exist: the missing extra is reported first, before any work
    rc = main(["train", str(tmp_path / "no_capture"), "--out", str(tmp_path / "run"), "--blocks", "4"])
    err = capsys.readouterr().err
    assert rc == 2
    assert 'pip install -e ".[cluster]"' in err and "ray[client]==2.60.0" in err
    assert not (tmp_path / "run").exists()
