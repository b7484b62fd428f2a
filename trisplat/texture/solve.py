"""The texel least-squares problem's normal equations, applied without forming them, and the conjugate-gradient
solve (trisplat.texture.fit).

The normal matrix of a 2048 texture over lego's 100 photos has 112M non-zeros (0.9 GB in float32, 3+ GB while
scipy multiplies A^T A out, 15 s); the rows of A (one per covered pixel, a few dozen texels each) are fewer
numbers, and one pass over them computes A^T (A x) for a vector: per row, t = a . x, then x's gradient gets a t.
Numba runs the rows in parallel, each thread into its own output block (no atomics), summed at the end.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp


@nb.njit(parallel=True, cache=True, fastmath=True)
def _ata_apply(indptr, indices, data, x, chunks, out):  # pragma: no cover (compiled)
    """out[t] = sum over the rows of chunk t of a_r^T (a_r . x); x [n,3] float32, out [T,n,3] zeroed."""
    for t in nb.prange(len(chunks) - 1):
        o = out[t]
        for r in range(chunks[t], chunks[t + 1]):
            a0 = np.float32(0.0)
            a1 = np.float32(0.0)
            a2 = np.float32(0.0)
            for k in range(indptr[r], indptr[r + 1]):
                j = indices[k]
                v = data[k]
                a0 += v * x[j, 0]
                a1 += v * x[j, 1]
                a2 += v * x[j, 2]
            for k in range(indptr[r], indptr[r + 1]):
                j = indices[k]
                v = data[k]
                o[j, 0] += v * a0
                o[j, 1] += v * a1
                o[j, 2] += v * a2


@nb.njit(parallel=True, cache=True, fastmath=True)
def _sum_blocks(blocks, x, prior, out):  # pragma: no cover (compiled)
    """out = the sum of the threads' blocks + prior x; the blocks are left zeroed for the next product."""
    n = out.shape[0]
    for i in nb.prange(n):
        for c in range(3):
            s = prior * x[i, c]
            for t in range(blocks.shape[0]):
                s += blocks[t, i, c]
                blocks[t, i, c] = 0.0
            out[i, c] = s


@nb.njit(cache=True)
def _laplacian_apply(edges, x, weight, out):  # pragma: no cover (compiled)
    """out += weight L x for the graph of `edges` [E,2] (sum over neighbours of x_i - x_j)."""
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        for c in range(3):
            d = weight * (x[i, c] - x[j, c])
            out[i, c] += d
            out[j, c] -= d


@nb.njit(cache=True)
def column_square_sums(indices, data, n):  # pragma: no cover (compiled)
    """diag(A^T A) [n] float64 of a csr's (indices, data), without a float64 copy of the data."""
    out = np.zeros(n, np.float64)
    for k in range(len(indices)):
        v = np.float64(data[k])
        out[indices[k]] += v * v
    return out


@dataclass
class NormalOperator:
    """x -> (A^T A + smoothness L + prior I) x for the rows A (csr, float32) over n unknowns, L the graph
    Laplacian of `edges` [E,2]; float32 throughout (the texture ends as 8-bit sRGB)."""

    rows: sp.csr_matrix
    edges: np.ndarray
    smoothness: float
    prior: float
    threads: int

    def __post_init__(self):
        A = self.rows
        self._indptr = A.indptr.astype(np.int64)
        self._indices = A.indices.astype(np.int32, copy=False)
        self._data = A.data.astype(np.float32, copy=False)
        nnz = self._indptr[1:]
        # one chunk of rows of about equal work per thread (each its own output block)
        parts = max(1, self.threads)
        cuts = np.searchsorted(nnz, np.linspace(0, nnz[-1] if len(nnz) else 0, parts + 1)[1:-1])
        self._chunks = np.unique(np.r_[0, cuts, A.shape[0]]).astype(np.int64)
        self.n = A.shape[1]
        self._blocks = np.zeros((len(self._chunks) - 1, self.n, 3), np.float32)
        self._edges = np.ascontiguousarray(self.edges, np.int64)

    def _apply(self, x: np.ndarray, prior: float) -> np.ndarray:
        """A^T A x + prior x (the threads' blocks are zero before and after)."""
        x = np.ascontiguousarray(x, np.float32)
        _ata_apply(self._indptr, self._indices, self._data, x, self._chunks, self._blocks)
        out = np.empty((self.n, 3), np.float32)
        _sum_blocks(self._blocks, x, np.float32(prior), out)
        return out

    def ata(self, x: np.ndarray) -> np.ndarray:
        """A^T A x for x [n,3]."""
        return self._apply(x, 0.0)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, np.float32)
        out = self._apply(x, self.prior)
        if self.smoothness:
            _laplacian_apply(self._edges, x, np.float32(self.smoothness), out)
        return out

    def diagonal(self) -> np.ndarray:
        """diag(A^T A) + smoothness * degree + prior, float64 [n]."""
        d = column_square_sums(self._indices, self._data, self.n)
        deg = np.bincount(self._edges.ravel(), minlength=self.n).astype(np.float64)
        return d + self.smoothness * deg + self.prior


@nb.njit(parallel=True, cache=True)
def _column_dots(a, b):  # pragma: no cover (compiled)
    """[3] float64: the dot product of each column of a and b ([n,3], any float type)."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    for i in nb.prange(a.shape[0]):
        s0 += np.float64(a[i, 0]) * np.float64(b[i, 0])
        s1 += np.float64(a[i, 1]) * np.float64(b[i, 1])
        s2 += np.float64(a[i, 2]) * np.float64(b[i, 2])
    return np.array([s0, s1, s2])


@nb.njit(parallel=True, cache=True)
def _cg_step(x, r, p, ap, alpha, minv, z):  # pragma: no cover (compiled)
    """x += alpha p; r -= alpha Ap; z = minv r (per column alpha [3]), in one pass. Returns (r . r, r . z) [3]."""
    a0, a1, a2 = alpha[0], alpha[1], alpha[2]
    rr0 = 0.0
    rr1 = 0.0
    rr2 = 0.0
    rz0 = 0.0
    rz1 = 0.0
    rz2 = 0.0
    for i in nb.prange(x.shape[0]):
        m = minv[i]
        x[i, 0] += a0 * p[i, 0]
        x[i, 1] += a1 * p[i, 1]
        x[i, 2] += a2 * p[i, 2]
        v0 = r[i, 0] - a0 * ap[i, 0]
        v1 = r[i, 1] - a1 * ap[i, 1]
        v2 = r[i, 2] - a2 * ap[i, 2]
        r[i, 0] = v0
        r[i, 1] = v1
        r[i, 2] = v2
        z[i, 0] = m * v0
        z[i, 1] = m * v1
        z[i, 2] = m * v2
        rr0 += v0 * v0
        rr1 += v1 * v1
        rr2 += v2 * v2
        rz0 += m * v0 * v0
        rz1 += m * v1 * v1
        rz2 += m * v2 * v2
    return np.array([rr0, rr1, rr2]), np.array([rz0, rz1, rz2])


@nb.njit(parallel=True, cache=True)
def _cg_direction(p, z, beta, p32):  # pragma: no cover (compiled)
    """p = z + beta p (per column beta [3]) and its float32 copy p32, in one pass."""
    for i in nb.prange(p.shape[0]):
        for c in range(3):
            v = z[i, c] + beta[c] * p[i, c]
            p[i, c] = v
            p32[i, c] = np.float32(v)


def pcg(apply, b: np.ndarray, minv: np.ndarray, x: np.ndarray, iterations: int, tol: float):
    """Preconditioned conjugate gradients on the three columns of b [n,3] at once (each column its own step sizes);
    minv: the inverse of the diagonal [n]. Stops when every column's residual is below tol times its right-hand side.
    Products in float32 (apply's, given a float32 [n,3] direction), the iterates and sums in float64; the vector
    updates are fused Numba passes (done with numpy, their temporaries cost lego's 1.7M-texel solve twice the
    products). Returns (x, iterations, the largest relative residual)."""
    b = np.asarray(b, np.float64)
    if b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"pcg solves [n,3] right-hand sides, got {b.shape}")
    x = np.array(x, np.float64)
    minv = np.ascontiguousarray(minv, np.float64)
    r = b - apply(x.astype(np.float32))
    z = r * minv[:, None]
    p = z.copy()
    p32 = p.astype(np.float32)
    rz = _column_dots(r, z)
    bnorm = np.maximum(np.linalg.norm(b, axis=0), 1e-30)
    rel = float((np.linalg.norm(r, axis=0) / bnorm).max())
    k = 0
    if rel < tol:
        return x, k, rel
    for k in range(1, iterations + 1):  # noqa: B007 (k is the count returned)
        ap = np.ascontiguousarray(apply(p32))
        alpha = rz / np.maximum(_column_dots(p, ap), 1e-30)
        rr, rz_new = _cg_step(x, r, p, ap, alpha, minv, z)
        rel = float((np.sqrt(rr) / bnorm).max())
        if rel < tol:
            break
        _cg_direction(p, z, rz_new / np.maximum(rz, 1e-30), p32)
        rz = rz_new
    return x, k, rel
