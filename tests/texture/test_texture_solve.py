"""The texel solve (trisplat.texture.solve / fit.solve) reaches the exact least-squares minimiser of the fit's
objective: compared with scipy's LSQR on the same problem written out as one stacked sparse system."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import lsqr

from trisplat.texture.fit import TexelProblem, solve
from trisplat.texture.solve import NormalOperator


def _problem(seed=0, rows=3000, n=900, side=30):
    """Rows of a few dozen random positive weights over a side x side texel grid (like bilinear footprints:
    neighbouring texels), right-hand sides, 4-neighbour edges in two 'charts' (left and right half)."""
    rng = np.random.default_rng(seed)
    r, c, v = [], [], []
    for k in range(rows):
        y, x = rng.integers(0, side - 3, 2)
        taps = [(y + dy) * side + x + dx for dy in range(3) for dx in range(3) if rng.random() < 0.7]
        r += [k] * len(taps)
        c += taps
        v += list(rng.random(len(taps)).astype(np.float32) * 0.2)
    A = sp.csr_matrix((np.asarray(v, np.float32), (r, c)), shape=(rows, n))
    A.sum_duplicates()
    # a texel band no row reads: only the prior and the neighbours decide it
    keep = (np.arange(n) % side) != 7
    A = A @ sp.diags(keep.astype(np.float32))
    A.eliminate_zeros()
    b = rng.random((rows, 3)).astype(np.float32) * 0.3
    ids = np.arange(n)
    half = (ids % side) < side // 2
    edges = [(i, i + 1) for i in ids if (i % side) < side - 1 and half[i] == half[i + 1]]
    edges += [(i, i + side) for i in ids if i + side < n]
    prior = rng.random((n, 3)) * 0.5
    return TexelProblem(size=side, rows=A.tocsr(), b=b, ids=ids, unknown=np.ones(n, bool),
                        edges=np.asarray(edges, np.int64), prior=prior, views=1, samples=rows)


def _lsqr_solution(p: TexelProblem, smoothness: float, prior: float) -> np.ndarray:
    """The minimiser of ||A x - b||^2 + ls sum_edges (x_i - x_j)^2 + lp ||x - prior||^2 by LSQR (ls, lp scaled by
    the mean non-zero diagonal of A^T A, as fit.solve defines the weights)."""
    A = p.rows.astype(np.float64)
    d = np.asarray(A.multiply(A).sum(0)).ravel()
    scale = d[d > 0].mean()
    ls, lp = smoothness * scale, prior * scale
    e = p.edges
    n = A.shape[1]
    D = sp.csr_matrix((np.r_[np.ones(len(e)), -np.ones(len(e))], (np.r_[np.arange(len(e)), np.arange(len(e))],
                                                                   np.r_[e[:, 0], e[:, 1]])), shape=(len(e), n))
    M = sp.vstack([A, np.sqrt(ls) * D, np.sqrt(lp) * sp.identity(n)]).tocsr()
    out = np.empty((n, 3))
    for c in range(3):
        rhs = np.r_[p.b[:, c].astype(np.float64), np.zeros(len(e)), np.sqrt(lp) * p.prior[:, c]]
        out[:, c] = lsqr(M, rhs, atol=1e-14, btol=1e-14, conlim=1e12, iter_lim=20000)[0]
    return out


def test_solve_reaches_the_least_squares_minimiser():
    p = _problem()
    for smoothness, prior in ((1e-2, 1e-3), (0.3, 0.05)):
        x, its, rel = solve(p, smoothness, prior, iterations=2000, tolerance=1e-7, threads=1)
        ref = _lsqr_solution(p, smoothness, prior)
        assert rel < 1e-7 and its < 2000
        assert np.abs(x - ref).max() < 1e-4 * np.abs(ref).max(), (smoothness, prior, np.abs(x - ref).max())


def test_normal_operator_matches_the_assembled_matrix_on_any_thread_count():
    p = _problem(seed=1)
    A = p.rows.astype(np.float64)
    e = p.edges
    n = A.shape[1]
    adj = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n))
    L = sp.diags(np.asarray(adj.sum(1)).ravel()) - adj
    N = (A.T @ A + 0.7 * L + 0.2 * sp.identity(n)).tocsr()
    x = np.random.default_rng(2).random((n, 3)).astype(np.float32)
    for threads in (1, 2, 3):
        op = NormalOperator(p.rows, e, 0.7, 0.2, threads)
        np.testing.assert_allclose(op(x), N @ x.astype(np.float64), rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(op.diagonal(), N.diagonal(), rtol=1e-5)


def test_solve_starts_at_the_per_texel_mean_of_what_the_photos_show():
    """When every pixel shows the same colour the per-texel normal equation is already the minimiser (no step)
    wherever a photo sees the texel; texels no row reads start at the prior (here the same colour; elsewhere the
    prior is random and has no weight, so a start at the prior would take steps)."""
    p = _problem(seed=3)
    colour = np.array([0.2, 0.5, 0.7], np.float32)
    row_sum = np.asarray(p.rows.sum(1)).ravel()
    p.b = (row_sum[:, None] * colour[None, :]).astype(np.float32)  # each pixel: its texels all at `colour`
    unseen = np.asarray(p.rows.sum(0)).ravel() == 0
    assert unseen.any()
    p.prior[unseen] = colour
    x, its, rel = solve(p, 1e-2, 0.0, iterations=50, tolerance=1e-5, threads=1)
    assert its == 0, (its, rel)
    np.testing.assert_allclose(x, np.tile(colour, (len(x), 1)), atol=1e-5)
