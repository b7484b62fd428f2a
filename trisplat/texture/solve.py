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
def _sum_blocks(blocks, out):  # pragma: no cover (compiled)
    n = out.shape[0]
    for i in nb.prange(n):
        for c in range(3):
            s = np.float32(0.0)
            for t in range(blocks.shape[0]):
                s += blocks[t, i, c]
            out[i, c] = s


@nb.njit(cache=True)
def _laplacian_apply(edges, x, out):  # pragma: no cover (compiled)
    """out += L x for the graph of `edges` [E,2] (sum over neighbours of x_i - x_j)."""
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        for c in range(3):
            d = x[i, c] - x[j, c]
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

    def ata(self, x: np.ndarray) -> np.ndarray:
        """A^T A x for x [n,3]."""
        x = np.ascontiguousarray(x, np.float32)
        self._blocks[:] = 0.0
        _ata_apply(self._indptr, self._indices, self._data, x, self._chunks, self._blocks)
        if len(self._blocks) == 1:
            return self._blocks[0].copy()
        out = np.empty((self.n, 3), np.float32)
        _sum_blocks(self._blocks, out)
        return out

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, np.float32)
        out = self.ata(x)
        if self.smoothness:
            lx = np.zeros_like(out)
            _laplacian_apply(self._edges, x, lx)
            out += np.float32(self.smoothness) * lx
        if self.prior:
            out += np.float32(self.prior) * x
        return out

    def diagonal(self) -> np.ndarray:
        """diag(A^T A) + smoothness * degree + prior, float64 [n]."""
        d = column_square_sums(self._indices, self._data, self.n)
        deg = np.bincount(self._edges.ravel(), minlength=self.n).astype(np.float64)
        return d + self.smoothness * deg + self.prior


def pcg(apply, b: np.ndarray, minv: np.ndarray, x: np.ndarray, iterations: int, tol: float):
    """Preconditioned conjugate gradients on the columns of b [n,k] at once (each column its own step sizes);
    minv: the inverse of the diagonal. Stops when every column's residual is below tol times its right-hand side.
    Products in float32 (apply's), sums in float64. Returns (x, iterations, the largest relative residual)."""
    b = np.asarray(b, np.float64)
    x = np.array(x, np.float64)
    r = b - apply(x)
    z = r * minv[:, None]
    p = z.copy()
    rz = (r * z).sum(0)
    bnorm = np.maximum(np.linalg.norm(b, axis=0), 1e-30)
    rel = float((np.linalg.norm(r, axis=0) / bnorm).max())
    k = 0
    if rel < tol:
        return x, k, rel
    for k in range(1, iterations + 1):  # noqa: B007 (k is the count returned)
        Ap = apply(p)
        alpha = rz / np.maximum((p * Ap).sum(0), 1e-30)
        x += p * alpha
        r -= Ap * alpha
        rel = float((np.linalg.norm(r, axis=0) / bnorm).max())
        if rel < tol:
            break
        z = r * minv[:, None]
        rz_new = (r * z).sum(0)
        p = z + p * (rz_new / np.maximum(rz, 1e-30))
        rz = rz_new
    return x, k, rel
