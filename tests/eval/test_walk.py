"""Walk check (trisplat.eval.walk): spheres dropped on a welded floor stand on it; on a floor of loose shards with
gaps between them many fall through; drop points lie on upward faces the cameras see; the up direction comes from
the cameras."""
import numpy as np
import pytest

from tests.mesh.test_fusion import look_at
from trisplat.eval.walk import WalkConfig, drop_targets, up_direction, walk_check

pytest.importorskip("pybullet", reason="pybullet is not installed (pip install pybullet, part of the test extra)")


def _floor(n=24, half=1.0, shrink=1.0):
    """A floor z = 0 over [-half, half]^2 as n x n squares of two triangles, counter-clockwise from +z (up). With
    shrink < 1 every triangle is shrunk about its centroid and gets private vertices: shards with gaps."""
    xs = np.linspace(-half, half, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    pos = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    if shrink < 1.0:
        tri = pos[faces]
        cen = tri.mean(1, keepdims=True)
        pos = (cen + shrink * (tri - cen)).reshape(-1, 3)
        faces = np.arange(len(pos)).reshape(-1, 3)
    return pos, faces


def _cameras():
    # four cameras above the floor looking down at it obliquely, upright (their up is +z)
    return [look_at([1.2 * np.cos(t), 1.2 * np.sin(t), 0.8], target=(0, 0, 0), size=64, focal=48.0)
            for t in np.linspace(0, 2 * np.pi, 4, endpoint=False)]


def test_up_is_the_cameras_mean_up():
    np.testing.assert_allclose(up_direction(_cameras()), [0, 0, 1], atol=1e-9)


def test_drop_targets_lie_on_upward_faces_seen_by_the_cameras():
    pos, faces = _floor()
    # a wall x = 0.5 facing -x: its points never qualify (not facing up)
    wall = np.array([[0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5]])
    pos2 = np.concatenate([pos, wall])
    n0 = len(pos)
    faces2 = np.concatenate([faces, [[n0, n0 + 2, n0 + 1], [n0, n0 + 3, n0 + 2]]])
    pts, candidates = drop_targets(pos2, faces2, _cameras(), np.array([0, 0, 1.0]), WalkConfig(drops=100))
    assert len(pts) == 100 and candidates > 100
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-4)  # on the floor, none on the wall
    assert np.abs(pts[:, :2]).max() <= 1.0 + 1e-6


def test_spheres_stand_on_a_welded_floor_and_fall_through_shards():
    cams = _cameras()
    cfg = WalkConfig(drops=40, radius=0.03, settle_s=1.5)
    welded = walk_check(*_floor(), cams, cfg)
    assert len(welded.drops) == 40
    standing = [d for d in welded.drops if d.on_surface]
    assert len(standing) >= 38
    # only a sphere dropped past the floor's edge can miss it
    assert all(np.abs(d.end[:2]).max() > 1.0 for d in welded.drops if not d.on_surface)
    assert all(d.at_rest and abs(d.end[2] - cfg.radius) < 0.2 * cfg.radius for d in standing)  # resting on z = 0
    # the same floor as loose shards, shrunk to 40%: gaps wider than the sphere between them
    shards = walk_check(*_floor(n=8, shrink=0.4), cams, cfg)
    assert len(shards.drops) == 40
    assert shards.fraction < 0.8
    fell = [d for d in shards.drops if not d.on_surface]
    assert all(d.end[2] < -0.5 for d in fell)  # they keep falling: nothing below the floor


def test_an_empty_mesh_is_refused():
    with pytest.raises(ValueError, match="mesh with faces"):
        walk_check(np.zeros((0, 3)), np.zeros((0, 3), int), _cameras())
