"""The normal-smoothness term of the fine-tuned surface: zero on a flat sheet, 2 on a fold, and its gradient
flattens a bump (checked against finite differences and by descent)."""
from __future__ import annotations

import numpy as np
import torch

from trisplat.train.losses import face_adjacency, normal_smoothness


def _grid(n: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    xs = np.linspace(0.0, 1.0, n)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    pos = np.column_stack([X.ravel(), Y.ravel(), np.zeros(n * n)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return torch.tensor(pos, dtype=torch.float64), torch.tensor(faces, dtype=torch.int32)


def test_flat_sheet_is_zero_and_a_fold_is_two():
    pos, faces = _grid()
    pairs = face_adjacency(faces)
    n = 5
    assert len(pairs) == 3 * (n - 1) ** 2 - 2 * (n - 1)  # interior edges of the triangulated grid
    assert float(normal_smoothness(pos, faces, pairs)) < 1e-12
    # two triangles sharing an edge, the second folded flat onto the first (opposite normals)
    p2 = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.25, 0.25, 0]], dtype=torch.float64)
    f2 = torch.tensor([[0, 1, 2], [2, 1, 3]], dtype=torch.int32)  # consistent winding, vertex 3 folded back over face 0
    assert float(normal_smoothness(p2, f2, face_adjacency(f2))) == 2.0
    # a hinge at 90 degrees: 1 - cos(90) = 1
    p3 = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    f3 = torch.tensor([[0, 1, 2], [0, 3, 1]], dtype=torch.int32)
    assert abs(float(normal_smoothness(p3, f3, face_adjacency(f3))) - 1.0) < 1e-12


def test_gradient_matches_finite_differences_and_flattens_a_bump():
    pos, faces = _grid()
    rng = np.random.default_rng(0)
    pos[:, 2] = torch.tensor(0.05 * rng.standard_normal(len(pos)))
    pairs = face_adjacency(faces)
    x = pos.clone().requires_grad_(True)
    normal_smoothness(x, faces, pairs).backward()
    eps = 1e-6
    for v in (6, 12, 18):
        for k in range(3):
            d = torch.zeros_like(pos)
            d[v, k] = eps
            fd = (normal_smoothness(pos + d, faces, pairs) - normal_smoothness(pos - d, faces, pairs)) / (2 * eps)
            assert abs(float(fd) - float(x.grad[v, k])) < 1e-6 * max(1.0, abs(float(fd)))
    # gradient descent on the term alone flattens the bumpy sheet (boundary fixed)
    inner = torch.zeros(len(pos), dtype=torch.bool)
    inner[[6, 7, 8, 11, 12, 13, 16, 17, 18]] = True
    y = pos.clone().requires_grad_(True)
    opt = torch.optim.Adam([y], lr=2e-3)
    start = float(normal_smoothness(pos, faces, pairs))
    for _ in range(300):
        opt.zero_grad()
        normal_smoothness(y, faces, pairs).backward()
        y.grad[~inner] = 0
        opt.step()
    assert float(normal_smoothness(y, faces, pairs).detach()) < 0.3 * start


def test_fused_kernels_match_the_torch_twin_in_value_and_gradient():
    import trimesh

    from trisplat.train.losses import normal_smoothness_torch

    m = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(1)
    verts = m.vertices + 0.03 * rng.standard_normal(m.vertices.shape)
    verts[m.faces[5, 1]] = verts[m.faces[5, 0]]  # one degenerate face (|c| = 0: the clamp's branch)
    faces = torch.tensor(m.faces, dtype=torch.int64)
    pairs = face_adjacency(faces)
    for dtype, tol in ((torch.float64, 1e-10), (torch.float32, 1e-4)):
        a = torch.tensor(verts, dtype=dtype, requires_grad=True)
        b = torch.tensor(verts, dtype=dtype, requires_grad=True)
        la, lb = normal_smoothness(a, faces, pairs), normal_smoothness_torch(b, faces, pairs)
        (3.0 * la).backward()
        (3.0 * lb).backward()
        assert la.dtype == dtype and abs(float(la) - float(lb)) < tol
        ok = torch.ones(len(verts), dtype=torch.bool)
        if dtype == torch.float32:  # the clamped face's two vertices get ~1e8 gradients (x 1/1e-12) in both: in
            ok[m.faces[5, :2]] = False  # float32 they agree to float32's precision only; in float64 exactly
        torch.testing.assert_close(a.grad[ok], b.grad[ok], atol=tol, rtol=tol)
    assert float(normal_smoothness(a, faces, pairs[:0])) == 0.0  # no pairs


def test_the_kernels_at_any_thread_count_with_unused_vertices_repeated_pairs_and_kept_tables():
    """Every thread count gives the torch twin's value and gradient (the passes split faces and vertices among the
    threads); vertices no face uses get 0, a pair listed twice counts twice, and the tables built once serve later
    calls with moved positions."""
    import numba
    import trimesh

    from trisplat.train.fused_smoothness import smoothness_topology
    from trisplat.train.losses import normal_smoothness_torch

    m = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(2)
    verts = np.concatenate([m.vertices + 0.05 * rng.standard_normal(m.vertices.shape), rng.standard_normal((7, 3))])
    faces = torch.tensor(m.faces, dtype=torch.int64)
    pairs = face_adjacency(faces)
    pairs = torch.cat([pairs, pairs[:5]])  # repeated pairs
    topo = smoothness_topology(faces, pairs, len(verts))
    before = numba.get_num_threads()
    try:
        for threads in sorted({1, 2, 3, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            for shift in (0.0, 0.02):
                v = verts + shift * rng.standard_normal(verts.shape)
                a = torch.tensor(v, dtype=torch.float64, requires_grad=True)
                b = torch.tensor(v, dtype=torch.float64, requires_grad=True)
                la = normal_smoothness(a, faces, pairs, topo)
                lb = normal_smoothness_torch(b, faces, pairs)
                (2.0 * la).backward()
                (2.0 * lb).backward()
                assert abs(float(la) - float(lb)) < 1e-12
                torch.testing.assert_close(a.grad, b.grad, atol=1e-12, rtol=1e-10)
                assert float(a.grad[len(m.vertices):].abs().max()) == 0.0
    finally:
        numba.set_num_threads(before)
