"""trisplat.mesh.hidden_join: a piece standing apart is joined to the main one through the hidden surface nearest
to it, down to the floor when the floor is known; hidden surface farther away stays dropped."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from trisplat.mesh.cleanup import face_components
from trisplat.mesh.hidden_join import join_through_hidden

VOXEL = 0.05


def _box_sdf(p, lo, hi):
    """Signed distance (approximate inside) to the axis-aligned box [lo, hi]: negative inside."""
    c, h = (np.asarray(lo) + hi) / 2, (np.asarray(hi) - lo) / 2
    q = np.abs(p - c) - h
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)


def _scene(plate: bool):
    """The surface of a floor slab (top at z = 0) and a table column (|x|, |y| < 0.3, up to z = 1) standing on it,
    marching cubes of their union; with `plate`, a low wall (|y| < 0.05, x 0.3..1.5, up to z = 0.35) leaning on the
    column's side. Returns vertices, faces, face centroids, and which faces the views saw: the table above z = 0.5,
    the floor's top beyond 0.45 of the column, the plate; hidden: the column below 0.5, the floor at its foot, the
    slab's rim and underside (the back of the scan)."""
    from skimage.measure import marching_cubes

    xs = np.arange(-2.0, 2.0 + 1e-9, VOXEL)
    zs = np.arange(-0.4, 1.2 + 1e-9, VOXEL)
    p = np.stack(np.meshgrid(xs, xs, zs, indexing="ij"), -1)
    sdf = np.minimum(_box_sdf(p, (-1.9, -1.9, -0.2), (1.9, 1.9, 0.0)), _box_sdf(p, (-0.3, -0.3, -0.1), (0.3, 0.3, 1.0)))
    if plate:
        sdf = np.minimum(sdf, _box_sdf(p, (0.2, -0.05, -0.1), (1.5, 0.05, 0.35)))
    v, f, _, _ = marching_cubes(sdf, 0.0, spacing=(VOXEL,) * 3)
    v = v + np.array([xs[0], xs[0], zs[0]])
    c = v[f].mean(1)
    r = np.abs(c[:, :2]).max(1)
    table = (c[:, 2] > 0.5) & (r < 0.35)
    floor = (np.abs(c[:, 2]) < 0.02) & (r > 0.45) & (r < 1.85)
    wall = plate & (np.abs(c[:, 1]) < 0.1) & (c[:, 0] > 0.35) & (c[:, 2] > -0.01)
    return v, f.astype(np.int64), c, table | floor | wall


def _pieces(f, nv, mask):
    n, lab = face_components(f[mask], nv)
    full = np.full(len(f), -1)
    full[mask] = lab
    return n, full


def test_a_table_apart_is_joined_through_its_hidden_skirt_and_nothing_else():
    v, f, c, seen = _scene(plate=False)
    n, lab = _pieces(f, len(v), seen)
    table = seen & (c[:, 2] > 0.5)
    assert n == 2 and len(np.unique(lab[table])) == 1  # the table stands apart from the floor
    keep, joined = join_through_hidden(v, f, ~seen)
    assert not (keep & seen).any() and len(joined) == 1 and joined[0]["faces"] == int(table.sum())
    n, lab = _pieces(f, len(v), seen | keep)
    assert n == 1  # one piece
    # the skirt all round, down to the floor: every hidden face of the column's sides is kept
    side = ~seen & (np.abs(c[:, :2]).max(1) > 0.27) & (np.abs(c[:, :2]).max(1) < 0.33) & (c[:, 2] > 0.03) \
        & (c[:, 2] < 0.5)
    assert side.sum() > 100 and keep[side].all()
    # the back of the scan (the slab's underside and rim) and the floor far from the foot stay dropped
    assert not keep[c[:, 2] < -0.1].any()
    assert not keep[np.abs(c[:, :2]).max(1) > 1.0].any()
    # the distance is the geodesic one: from the lowest seen rim (z ~ 0.5) down the side and out to 0.45 on the floor
    assert 0.55 < joined[0]["distance"] < 0.75


def test_a_piece_farther_than_its_own_size_stays_apart():
    v, f, c, seen = _scene(plate=False)
    keep, joined = join_through_hidden(v, f, ~seen, size_factor=0.5)  # the table's diagonal ~1.0, the join ~0.65
    assert not keep.any() and joined == []
    # pieces below min_piece x the main one are left to the floater rule
    keep, joined = join_through_hidden(v, f, ~seen, min_piece=0.9)
    assert not keep.any() and joined == []


@pytest.mark.parametrize("with_ground", [False, True])
def test_with_the_floor_known_the_piece_is_joined_where_it_meets_the_floor(with_ground):
    v, f, c, seen = _scene(plate=True)
    # the plate leans on the column at z 0.35: the nearest hidden way to the main piece; the floor is farther
    ground = SimpleNamespace(up=np.array([0.0, 0.0, 1.0]), height=0.0) if with_ground else None
    keep, joined = join_through_hidden(v, f, ~seen, ground=ground)
    assert len(joined) == 1 and joined[0]["floor"] == with_ground
    n, _ = _pieces(f, len(v), seen | keep)
    assert n == 1
    lowest = c[keep, 2].min()
    if with_ground:
        assert lowest < 0.05  # the skirt reaches the floor
    else:
        assert 0.25 < lowest < 0.45 and joined[0]["distance"] < 0.3  # it stops at the plate's top


def test_nothing_to_join():
    v, f, c, seen = _scene(plate=False)
    keep, joined = join_through_hidden(v, f, np.zeros(len(f), bool))
    assert not keep.any() and joined == []
    keep, joined = join_through_hidden(v, f, np.ones(len(f), bool))
    assert not keep.any() and joined == []
