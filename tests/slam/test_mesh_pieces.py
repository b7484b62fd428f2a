"""SLAM's mesh keeps a room's separate pieces down to --slam.mesh-min-piece of the largest (chairs standing apart
from the floor in the fused surface), where the training switch drops pieces below 2% as floaters; its unseen space
is solid deeper (--slam.mesh-unseen-depth)."""
from __future__ import annotations

import numpy as np
import pytest

import trisplat.train.switch as switch
from trisplat.slam.system import SlamConfig


def _strip(n: int, x0: float) -> tuple[np.ndarray, np.ndarray]:
    """A strip of 2n triangles (one connected piece) starting at x = x0."""
    xs = x0 + np.arange(n + 1, dtype=np.float64)
    v = np.concatenate([np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], 1),
                        np.stack([xs, np.ones_like(xs), np.zeros_like(xs)], 1)])
    i = np.arange(n)
    f = np.concatenate([np.stack([i, i + 1, n + 1 + i], 1), np.stack([i + 1, n + 2 + i, n + 1 + i], 1)])
    return v, f


def _two_pieces():
    va, fa = _strip(500, 0.0)  # 1,000 faces
    vb, fb = _strip(7, 1000.0)  # 14 faces: 1.4% of the largest
    return np.concatenate([va, vb]), np.concatenate([fa, fb + len(va)])


@pytest.mark.parametrize("fraction, kept", [(0.01, 2), (0.02, 1)])
def test_pieces_below_the_fraction_are_dropped(fraction, kept):
    v, f = _two_pieces()
    v2, f2, pieces, dropped = switch._drop_small_pieces(v, f, fraction)
    assert pieces == 2 and dropped == 2 - kept
    assert len(f2) == (1014 if kept == 2 else 1000) and f2.max() == len(v2) - 1  # unused vertices gone


def test_slam_mesh_uses_its_own_piece_fraction(monkeypatch, rgbd_capture):
    import torch

    from trisplat.data.rgbd_stream import load_frame, open_stream
    from trisplat.slam.map import SlamMap
    from trisplat.slam.mapping import Keyframe
    from trisplat.slam.system import map_surface

    seen = {}

    def fake_soup_to_surface(scene, cams, render, bounds, config, progress=None, images=None):
        seen["config"] = config
        raise RuntimeError("stop here")

    monkeypatch.setattr(switch, "soup_to_surface", fake_soup_to_surface)
    stream = open_stream(rgbd_capture)
    rgb, depth = load_frame(stream, 0, 1)
    kf = Keyframe(0, torch.from_numpy(rgb), torch.from_numpy(depth), np.eye(4))
    for frac, depth in ((0.01, 0.08), (0.005, 0.2)):
        with pytest.raises(RuntimeError, match="stop here"):
            map_surface(SlamMap.empty(), [kf], stream, SlamConfig(downscale=1, mesh_min_piece=frac,
                                                                  mesh_unseen_depth=depth), lambda *a, **k: None)
        assert seen["config"].min_component_fraction == frac and seen["config"].unseen_faces == "drop_but_bridges"
        assert seen["config"].max_depth_fraction == depth  # (training's objects keep theirs)
    assert SlamConfig().mesh_unseen_depth > switch.SurfaceConfig().max_depth_fraction
    assert SlamConfig().mesh_min_piece == 0.01 < switch.SurfaceConfig().min_component_fraction



class _Mesh:
    """Triangles added one by one, each wound so that its normal points along `towards`."""

    def __init__(self):
        self.v, self.f, self.name = [], [], []

    def vert(self, p) -> int:
        p = tuple(float(x) for x in p)
        if p not in self.v:
            self.v.append(p)
        return self.v.index(p)

    def tri(self, a, b, c, towards, name):
        ia, ib, ic = self.vert(a), self.vert(b), self.vert(c)
        n = np.cross(np.subtract(b, a), np.subtract(c, a))
        self.f.append((ia, ib, ic) if n @ np.asarray(towards, float) > 0 else (ia, ic, ib))
        self.name.append(name)

    def quad(self, a, b, c, d, towards, name):
        self.tri(a, b, c, towards, name)
        self.tri(a, c, d, towards, name)

    def arrays(self):
        return np.array(self.v, np.float64), np.array(self.f, np.int64), np.array(self.name)


def _slab(m: _Mesh, x0, x1, y0, y1, z0, z1, name):
    """A box: top and sides seen (`name`), the bottom unseen (`name` + ' underside', 2x2 quads, facing down)."""
    xm, ym = (x0 + x1) / 2, (y0 + y1) / 2
    m.quad((x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1), (0, 0, 1), name)
    for a, b, t in [((x0, y0), (x1, y0), (0, -1, 0)), ((x1, y0), (x1, y1), (1, 0, 0)),
                    ((x1, y1), (x0, y1), (0, 1, 0)), ((x0, y1), (x0, y0), (-1, 0, 0))]:
        m.quad((*a, z0), (*b, z0), (*b, z1), (*a, z1), t, name)
    for xa, xb in [(x0, xm), (xm, x1)]:
        for ya, yb in [(y0, ym), (ym, y1)]:
            m.quad((xa, ya, z0), (xb, ya, z0), (xb, yb, z0), (xa, yb, z0), (0, 0, -1), name + " underside")


def _room():
    """A floor (seen); a table top (a 5 cm slab, its underside unseen) on a leg (seen) that touches the underside's
    centre vertex; a shelf slab hanging free above the floor (underside unseen, joined to nothing); the back of a
    wall (unseen, facing out into nothing)."""
    m = _Mesh()
    m.quad((-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0), (0, 0, 1), "floor")
    _slab(m, -0.5, 0.5, -0.5, 0.5, 0.75, 0.8, "table")
    m.tri((0, 0, 0.75), (0.05, 0, 0.02), (-0.05, 0, 0.02), (0, 1, 0), "leg")
    _slab(m, 1.0, 1.6, -0.3, 0.3, 1.2, 1.25, "shelf")
    m.quad((-2.5, -2, 0), (-2.5, -2, 2.5), (-2.5, 2, 2.5), (-2.5, 2, 0), (-1, 0, 0), "wall back")
    return m.arrays()


def test_only_hidden_sides_that_join_seen_pieces_are_kept():
    v, f, names = _room()
    unseen = np.isin(names, ["table underside", "shelf underside", "wall back"])
    assert set(names[switch.facing_seen(v, f, unseen, reach=2.0)]) == {"table underside", "shelf underside"}
    assert set(names[switch.facing_seen(v, f, unseen, reach=1.0)]) == {"table underside"}  # the shelf: 1.2 away
    # the table's underside joins the top (its rim) to the leg: kept; the shelf's joins nothing: dropped
    kept = switch.hidden_bridges(v, f, unseen, reach=2.0)
    assert set(names[kept]) == {"table underside"} and kept.sum() == 8
    assert not switch.hidden_bridges(v, f, np.zeros(len(f), bool), reach=2.0).any()
    # a piece below min_piece x the largest (here the leg: 1 face against the table's 10) is a floater: nothing to join
    assert not switch.hidden_bridges(v, f, unseen, reach=2.0, min_piece=0.2).any()


def test_without_embree_the_bridges_fall_back_to_dropping_with_a_note(monkeypatch):
    import trimesh

    rep = switch.SwitchReport()
    monkeypatch.setattr(trimesh.ray, "has_embree", False)
    assert not switch._fast_rays(rep) and "no Embree ray caster" in rep.notes[0]
    monkeypatch.setattr(trimesh.ray, "has_embree", True)
    assert switch._fast_rays(rep)
