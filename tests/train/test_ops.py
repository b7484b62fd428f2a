"""Topology edits keep vertex rows, face rows, Adam moments and statistics aligned."""
import torch

from trisplat.scene.model import TriangleScene
from trisplat.strategy import ops
from trisplat.strategy.densify import densify
from trisplat.strategy.opacity import raise_floor, resolve_logits
from trisplat.strategy.prune import prune


def _grid_scene(n=4, sh_degree=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    xs, ys = torch.meshgrid(torch.arange(n + 1.0), torch.arange(n + 1.0), indexing="ij")
    pos = torch.stack([xs.flatten(), ys.flatten(), torch.zeros((n + 1) ** 2)], 1)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            faces += [[a, b, c], [a, c, d]]
    scene = TriangleScene.from_rgb(pos, torch.tensor(faces), torch.rand(pos.shape[0], 3, generator=g), 0.5, sh_degree)
    scene.sh[:, 1:] = torch.randn(scene.sh[:, 1:].shape, generator=g)
    return scene


def _trainable_with_moments(scene):
    ts = ops.make_trainable(scene, {n: 0.0 for n in ops.VERTEX_PARAMS})  # lr 0: moments move, values do not
    # one Adam step with a gradient equal to a per-row signature, so each row's moments identify the row
    for name, p in ts.params.items():
        p.grad = torch.ones_like(p) * (p.detach() if name == "positions" else 1.0)
    sig = ts.params["positions"].detach()[:, 0] * 100 + ts.params["positions"].detach()[:, 1]
    ts.params["opacity_logit"].grad = sig.clone()
    ts.optimizer.step()
    return ts


def _moment(ts, name, key="exp_avg"):
    return ts.optimizer.state[ts.params[name]][key]


def _assert_aligned(ts):
    """exp_avg of opacity_logit was set from the row's position signature: it must still match its row."""
    pos = ts.params["positions"].detach()
    sig = pos[:, 0] * 100 + pos[:, 1]
    m = _moment(ts, "opacity_logit")
    old_rows = m != 0  # new (appended) rows start with zero moments
    torch.testing.assert_close(m[old_rows], 0.1 * sig[old_rows])  # Adam: exp_avg = (1 - beta1) * grad
    for name in ops.VERTEX_PARAMS:
        assert _moment(ts, name).shape == ts.params[name].shape
        assert ts.optimizer.param_groups[ops.VERTEX_PARAMS.index(name)]["params"][0] is ts.params[name]
    for v in ts.face_stats.values():
        assert v.shape == (ts.num_faces,)
    assert int(ts.faces.max()) < ts.num_vertices


def test_index_vertices_keeps_moments_with_rows():
    ts = _trainable_with_moments(_grid_scene())
    ops.keep_faces(ts, torch.arange(ts.num_faces) % 3 != 0)
    removed = ops.remove_orphan_vertices(ts)
    _assert_aligned(ts)
    assert removed >= 0
    # a permutation too
    perm = torch.randperm(ts.num_vertices, generator=torch.Generator().manual_seed(1))
    before = ts.params["positions"].detach()[ts.faces].clone()
    ops.index_vertices(ts, perm)
    _assert_aligned(ts)
    torch.testing.assert_close(ts.params["positions"].detach()[ts.faces], before)


def test_subdivide_shares_midpoints_and_averages():
    ts = _trainable_with_moments(_grid_scene(n=1))  # two triangles sharing the diagonal
    ts.face_stats["max_weight"][:] = torch.tensor([0.3, 0.7])
    V0 = ts.num_vertices
    added = ops.subdivide_faces(ts, torch.tensor([0, 1]))
    assert added == 5  # 3 + 3 edges, the shared diagonal counted once
    assert ts.num_faces == 8 and ts.num_vertices == V0 + 5
    _assert_aligned(ts)
    pos = ts.params["positions"].detach()
    # total area is preserved and every new vertex is the midpoint of two original ones
    p = pos[ts.faces]
    area = 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).norm(dim=1).sum()
    torch.testing.assert_close(area, torch.tensor(1.0))
    orig = pos[:V0]
    mids = (orig[:, None] + orig[None]) / 2
    for v in pos[V0:]:
        assert ((mids - v).norm(dim=-1) < 1e-6).any()
    # children keep their parent's statistics; winding (normal direction) preserved
    torch.testing.assert_close(ts.face_stats["max_weight"].sort().values, torch.tensor([0.3] * 4 + [0.7] * 4))
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (n[:, 2] * n[0, 2] > 0).all()


def test_prune_then_densify_stay_aligned_and_never_crash():
    ts = _trainable_with_moments(_grid_scene(n=6))
    ts.face_stats["max_weight"][:] = torch.linspace(0, 1, ts.num_faces)
    r = prune(ts, threshold=0.3)
    assert r.faces_removed == int((torch.linspace(0, 1, r.faces_before) <= 0.3).sum())
    _assert_aligned(ts)
    g = torch.Generator().manual_seed(0)
    d = densify(ts, growth=1.5, max_vertices=10_000, n_largest=2, min_face_px=0.0, generator=g)
    assert d.vertices_added > 0
    _assert_aligned(ts)
    # no blended faces at all: the reference crashes here ("cannot sample n_sample <= 0"); we subdivide the largest
    ts.reset_face_stats()
    d = densify(ts, growth=1.5, max_vertices=10_000, n_largest=3, min_face_px=0.0, generator=g)
    assert d.faces_selected == 3 and "largest" in d.reason
    # vertex cap reached: nothing happens
    d = densify(ts, growth=1.5, max_vertices=ts.num_vertices, n_largest=3, min_face_px=0.0, generator=g)
    assert d.faces_selected == 0 and d.vertices_added == 0
    # pruning everything keeps at least one face
    prune(ts, threshold=2.0)
    assert ts.num_faces >= 1
    _assert_aligned(ts)


def test_floor_raise_keeps_opacities():
    logit = torch.linspace(-4, 4, 50)
    new = resolve_logits(logit, 0.1, 0.3)
    o_old = 0.1 + 0.9 * torch.sigmoid(logit)
    o_new = 0.3 + 0.7 * torch.sigmoid(new)
    above = o_old > 0.3 + 1e-4
    torch.testing.assert_close(o_new[above], o_old[above], atol=1e-5, rtol=0)
    assert (o_new[~above] >= 0.3).all()
    ts = _trainable_with_moments(_grid_scene())
    before = ts.opacities().detach().clone()
    raise_floor(ts, 0.2)
    torch.testing.assert_close(ts.opacities().detach()[before > 0.21], before[before > 0.21], atol=1e-5, rtol=0)


def _edge_face_counts(faces):
    from trisplat.mesh.orient import edge_table

    t = edge_table(faces.numpy())
    return {tuple(e): int(c) for e, c in zip(t.edges.tolist(), t.edge_face_count.tolist())}


def test_subdivision_and_pruning_keep_shared_edges_shared():
    """A connected grid stays connected: subdividing both faces of an edge gives the two halves of that edge two
    faces each (one shared midpoint, no crack); removing faces elsewhere leaves other shared edges shared; the
    replacement by a connected surface keeps rows and faces aligned."""
    scene = _grid_scene(n=2)
    ts = _trainable_with_moments(scene)
    interior_before = sum(c == 2 for c in _edge_face_counts(ts.faces).values())
    # faces 0 and 1 share the diagonal (a, c) of the first cell
    a, c = int(ts.faces[0, 0]), int(ts.faces[0, 2])
    assert {a, c} <= set(ts.faces[1].tolist())
    added = ops.subdivide_faces(ts, torch.tensor([0, 1]))
    assert added == 5  # 6 edges of two faces, the shared one counted once
    counts = _edge_face_counts(ts.faces)
    p = ts.params["positions"].detach()
    mid = [v for v in range(ts.num_vertices) if torch.allclose(p[v], 0.5 * (p[a] + p[c]))]
    assert len(mid) == 1  # one midpoint for the shared edge
    m = mid[0]
    assert counts[tuple(sorted((a, m)))] == 2 and counts[tuple(sorted((m, c)))] == 2
    assert tuple(sorted((a, c))) not in counts  # the parent edge is gone, not left as a crack
    # pruning the faces of the last cell (and then orphaned vertices) keeps every edge the kept faces shared shared
    def shared_edges_by_position(faces, pos):
        key = {e: c for e, c in _edge_face_counts(faces).items()}
        return sorted((tuple(pos[e[0]].tolist()), tuple(pos[e[1]].tolist())) for e, c in key.items() if c == 2)

    keep = torch.arange(ts.num_faces) < ts.num_faces - 2
    expected = shared_edges_by_position(ts.faces[keep], ts.params["positions"].detach())
    ops.keep_faces(ts, keep)
    assert ops.remove_orphan_vertices(ts) >= 0
    assert shared_edges_by_position(ts.faces, ts.params["positions"].detach()) == expected
    assert len(expected) >= interior_before - 1  # only the removed cell's own diagonal went
    # replace_scene: a new vertex table and faces, fresh moments, aligned rows
    new = _grid_scene(n=3, seed=1)
    ops.replace_scene(ts, new)
    assert ts.num_vertices == new.num_vertices and torch.equal(ts.faces, new.faces.to(torch.int64))
    assert all(ts.params[n] not in ts.optimizer.state for n in ops.VERTEX_PARAMS)
    assert [g["params"][0] for g in ts.optimizer.param_groups] == [ts.params[n] for n in ops.VERTEX_PARAMS]
    assert ts.face_stats["max_weight"].shape == (new.num_faces,)


def _closed_sphere_scene():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2)
    pos = torch.tensor(m.vertices, dtype=torch.float32)
    g = torch.Generator().manual_seed(0)
    return TriangleScene.from_rgb(pos, torch.tensor(m.faces), torch.rand(len(pos), 3, generator=g), 0.5, 1), m


def test_conforming_refinement_keeps_a_closed_surface_closed():
    """refine_faces on a closed sphere: still closed (every edge has exactly two faces), consistently wound, the same
    area and volume (midpoints lie on the parents' edges), no T-junction (subdivide_faces would leave boundary edges
    around the selection); the selected faces are split in 4, their neighbours bisected; rows stay aligned."""
    import trimesh

    scene, mesh = _closed_sphere_scene()
    ts = _trainable_with_moments(scene)
    ts.face_stats["max_weight"] = torch.arange(ts.num_faces, dtype=torch.float32)
    centre = ts.params["positions"].detach()[ts.faces].mean(1)
    sel = torch.stack([centre[:, 0].argmax(), centre[:, 0].argmin(), centre[:, 2].argmax()])  # far apart
    parents_weight = ts.face_stats["max_weight"][sel].clone()
    F0, V0 = ts.num_faces, ts.num_vertices
    added = ops.refine_faces(ts, sel)
    assert ts.num_vertices == V0 + added
    counts = _edge_face_counts(ts.faces)
    assert set(counts.values()) == {2}  # closed: no boundary (T-junction) and no non-manifold edge
    out = trimesh.Trimesh(ts.params["positions"].detach().numpy(), ts.faces.numpy(), process=False)
    assert out.is_winding_consistent and out.is_watertight
    assert abs(out.area - mesh.area) < 1e-4 and abs(out.volume - mesh.volume) < 1e-4
    # three isolated faces: 3 x 3 edges split; each selected face -> 4, each of its 3 neighbours -> 2
    assert added == 9 and ts.num_faces == F0 + 3 * 3 + 3 * 3
    # children keep their parent's statistics: the selected faces' weights appear 4 times each
    for w in parents_weight.tolist():
        assert int((ts.face_stats["max_weight"] == w).sum()) == 4
    _assert_aligned(ts)
    # the naive 1-to-4 split of the same faces leaves T-junctions: boundary edges appear
    ts2 = _trainable_with_moments(_closed_sphere_scene()[0])
    ops.subdivide_faces(ts2, sel)
    assert 1 in set(_edge_face_counts(ts2.faces).values())


def test_conforming_refinement_closure_splits_faces_with_two_split_edges():
    """Two selected faces that both touch a third, unselected face: that face would get two split edges, so the
    closure splits it in 4 as well (a face is only ever bisected through ONE split edge); the surface stays closed."""
    scene, _ = _closed_sphere_scene()
    ts = ops.make_trainable(scene, {})
    edges = {}
    for fi, f in enumerate(ts.faces.tolist()):
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            edges.setdefault(tuple(sorted((a, b))), []).append(fi)
    nb = {}
    for f0, f1 in edges.values():
        nb.setdefault(f0, set()).add(f1)
        nb.setdefault(f1, set()).add(f0)
    f = 0
    g, h = sorted(nb[f])[:2]
    f_edges = [tuple(sorted(e)) for e in ((ts.faces[f, 0], ts.faces[f, 1]), (ts.faces[f, 1], ts.faces[f, 2]),
                                          (ts.faces[f, 2], ts.faces[f, 0]))]
    f_edges = [(int(a), int(b)) for a, b in f_edges]
    ops.refine_faces(ts, torch.tensor([g, h]))
    counts = _edge_face_counts(ts.faces)
    assert set(counts.values()) == {2}
    assert not any(e in counts for e in f_edges)  # all three edges of f were split: f went 1-to-4
