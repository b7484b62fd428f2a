"""The base-colour texture that best fits the photos: a sparse linear least-squares problem, solved by conjugate
gradients.

Once the surface is opaque, what a glTF viewer shows at a pixel is linear in the texels (in linear light): every
sample sees one surface point (trisplat.texture.raster), whose colour is a bilinear lookup of four texels decoded
to linear (trisplat.texture.sampling), and the pixel is the mean of its s x s samples (background samples add a
known constant). With A the [pixels x texels] matrix of those weights over all training views, x the linear texels
and b the photos decoded to linear (minus the background share), the texture minimises

    || W^1/2 (A x - b) ||^2 + smoothness * sum over neighbouring texels of one chart (x_i - x_j)^2
                            + prior * || x - x_prior ||^2

W weights each pixel by the square of the sRGB curve's slope at its colour, so the fit minimises (to first order)
the error of the ENCODED values PSNR is taken on. x_prior is the model's per-vertex colour on the surface; the
small prior and smoothness terms only decide texels no photo constrains. Normal equations, applied from the rows of
A without forming A^T A (trisplat.texture.solve), Jacobi-preconditioned conjugate gradients on the three channels at
once, started from each texel's own weighted mean; texels outside every chart are filled from the nearest fitted
texel (gutters), so bilinear taps and mip levels across chart borders read surface colours.
"""
from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp
from scipy import ndimage

from trisplat.io.colour import linear_to_srgb, linear_to_srgb_slope, srgb_to_linear
from trisplat.texture.atlas import Atlas
from trisplat.texture.raster import surface_samples, view_samples
from trisplat.texture.sampling import bilinear_taps
from trisplat.texture.solve import NormalOperator, column_square_sums, pcg

SMOOTHNESS = 1e-2  # weight of the neighbour term, relative to the mean photo weight a texel gets
PRIOR = 1e-3  # weight of the pull towards the vertex colours, relative to the same
CG_ITERATIONS = 200
CG_TOLERANCE = 3e-4  # relative residual of the normal equations: lego's 2048 texture at 3e-4 (69 iterations) is
#                      58.0 dB from the one at 1e-4 (89), the 8-bit texture's own rounding (58.9 dB); 1e-3: 49.7 dB


@dataclass
class TexelProblem:
    """The fit's least-squares problem over the unknown texels: rows = W^1/2 A (csr float32, a row per covered
    pixel of every view, columns = unknowns), b = W^1/2 b [rows,3], ids: the unknowns' flat texel indices,
    unknown: [S*S] mask, edges [E,2]: neighbouring unknowns of one chart, prior [n,3]: linear prior colours."""

    size: int
    rows: sp.csr_matrix
    b: np.ndarray
    ids: np.ndarray
    unknown: np.ndarray
    edges: np.ndarray
    prior: np.ndarray
    views: int
    samples: int


@dataclass
class FitStats:
    views: int
    samples: int  # surface samples that saw the mesh
    pixels: int  # rows of A
    unknowns: int  # texels solved for
    iterations: int
    relative_residual: float
    seconds_raster: float
    seconds_solve: float


def _return_freed_memory() -> None:
    """Hand the heap's free pages back to the system (glibc's malloc_trim; elsewhere nothing). The views' many
    arrays of a few MB each are allocated on the heap once glibc's mmap threshold has grown, and what they leave free
    stays in the process's resident memory; the next allocations (the rows, twice while they are sorted) then add to
    it instead of reusing it."""
    import ctypes

    try:
        ctypes.CDLL(None).malloc_trim(0)  # the process's own symbols, libc's among them
    except (OSError, AttributeError, TypeError):  # not glibc (macOS, Windows, musl without it)
        pass


def texel_coverage(atlas: Atlas):
    """Rasterise the atlas itself: for every texel centre, the face whose uv triangle holds it (-1: none) and its
    barycentrics (the uv layout seen by an orthographic camera: positions (u S, v S, 1), identity pose)."""
    S = atlas.size
    pos = np.column_stack([atlas.uv * S, np.ones(len(atlas.uv))])
    K = np.eye(3)
    return surface_samples(pos, atlas.uv_faces, np.eye(4), K, S, S, 1, near=0.5)


def view_rows(ss, photo, bg_lin: np.ndarray, taps, columns: int):
    """One view's rows of W^1/2 A and W^1/2 b (module docstring): a row per pixel some sample of `ss`
    (trisplat.texture.raster.SurfaceSamples) sees the mesh in. taps(face_id [n], bary [n,3]) -> (column indices
    [n,k], weights [n,k]): the unknowns each sample's colour is the weighted sum of (texels, or vertices). Returns
    (row lengths, column ids int32, values float32, rhs float32 [rows,3], samples) or None when no sample hits."""
    s = ss.supersample
    W = ss.face_id.shape[1] // s
    ys, xs = np.nonzero(ss.face_id >= 0)
    if len(ys) == 0:
        return None
    idx, w = taps(ss.face_id[ys, xs], ss.bary[ys, xs])
    pix = (ys // s) * W + xs // s
    covered, row = np.unique(pix, return_inverse=True)
    frac = np.bincount(row, minlength=len(covered)) / float(s * s)  # surface share of each covered pixel
    target = srgb_to_linear(np.asarray(photo, np.float64).reshape(-1, 3)[covered])
    sq = linear_to_srgb_slope(target.mean(1))  # W^1/2
    b = (target - (1.0 - frac)[:, None] * bg_lin[None, :]) * sq[:, None]
    vals = (np.asarray(w, np.float32) / float(s * s)) * sq[row][:, None].astype(np.float32)
    A = sp.csr_matrix((vals.ravel(), (np.repeat(row, idx.shape[1]), np.asarray(idx).ravel())),
                      shape=(len(covered), columns), dtype=np.float32)
    A.sum_duplicates()
    return np.diff(A.indptr), A.indices.astype(np.int32), A.data, b.astype(np.float32), len(ys)


class NoViewSeesMesh(ValueError):
    """No fitting view sees the mesh: there is nothing to fit its colours or texture to."""


class TexelRows:
    """The texel problem's rows, a view at a time (add), then the problem over the texels some sample reads or a
    chart covers (finish). One rasterisation of a view (trisplat.texture.raster.SurfaceSamples) can feed this and the
    vertex colours' rows (trisplat.texture.vertex_colours.VertexRows) alike."""

    def __init__(self, faces: np.ndarray, atlas: Atlas, background):
        self.atlas = atlas
        self.faces = np.asarray(faces, np.int64)
        self.uv_corner = atlas.uv[atlas.uv_faces]  # [F,3,2]
        self.bg_lin = srgb_to_linear(np.asarray(background, np.float64))
        self.blocks = []  # per view: (row lengths, flat texel ids int32, values float32, rhs float32)
        self.views = self.samples = 0
        self.col_used = np.zeros(atlas.size * atlas.size, bool)

    def add(self, ss, photo) -> None:
        S, uv_corner = self.atlas.size, self.uv_corner

        def taps(fid, bary):
            return bilinear_taps(np.einsum("nk,nkc->nc", bary.astype(np.float64), uv_corner[fid]), S, S)

        blk = view_rows(ss, photo, self.bg_lin, taps, S * S)
        if blk is None:
            return
        self.col_used[blk[1]] = True
        self.blocks.append(blk[:4])
        self.views += 1
        self.samples += blk[4]

    def finish(self, prior_colors: np.ndarray) -> TexelProblem:
        """The problem (prior_colors [V,3] sRGB: what texels no photo sees are pulled towards); the rows added so
        far are handed over (this accumulator is empty afterwards)."""
        if not self.blocks:
            raise NoViewSeesMesh("no view sees the mesh: nothing to fit a texture to")
        blocks, self.blocks = self.blocks, []
        return _texel_problem(self.atlas, self.faces, blocks, self.col_used, prior_colors, self.views, self.samples)


def assemble(positions: np.ndarray, faces: np.ndarray, atlas: Atlas, views: Iterable, background,
             prior_colors: np.ndarray, supersample: int = 2, near: float = 0.01) -> TexelProblem:
    """The rows W^1/2 A and right-hand sides W^1/2 b of every view (see the module docstring) over the texels some
    sample reads or a chart covers, with what the regularisers need (prior colours, neighbour pairs)."""
    rows = TexelRows(faces, atlas, background)
    for ss, photo in view_samples(positions, rows.faces, views, supersample, near):
        rows.add(ss, photo)
    return rows.finish(prior_colors)


def _texel_problem(atlas: Atlas, faces: np.ndarray, blocks: list, col_used: np.ndarray, prior_colors: np.ndarray,
                   n_views: int, n_samples: int) -> TexelProblem:
    """The views' row blocks (TexelRows) as one problem over the unknown texels, sorted and regularised."""
    S = atlas.size
    _return_freed_memory()  # the views' temporaries (lego: 2,695 -> 2,066 MiB at the peak below, 2048 texture)

    # unknowns: texels some sample reads, and texels inside a chart (for the prior)
    cov = texel_coverage(atlas)
    inside = cov.face_id.ravel() >= 0
    unknown = col_used | inside
    remap = np.full(S * S, -1, np.int32)
    ids = np.nonzero(unknown)[0]
    remap[ids] = np.arange(len(ids), dtype=np.int32)
    # the views' rows into one csr over the unknowns, a view at a time (peak: the rows plus one view's)
    n_rows = sum(len(blk[0]) for blk in blocks)
    nnz = sum(len(blk[1]) for blk in blocks)
    indptr = np.zeros(n_rows + 1, np.int64)
    indices = np.empty(nnz, np.int32)
    data = np.empty(nnz, np.float32)
    b = np.empty((n_rows, 3), np.float32)
    r0 = k0 = 0
    for v in range(len(blocks)):
        lengths, cols, vals, rhs = blocks[v]
        blocks[v] = None
        r1, k1 = r0 + len(lengths), k0 + len(cols)
        indptr[r0 + 1:r1 + 1] = k0 + np.cumsum(lengths)
        indices[k0:k1] = remap[cols]
        data[k0:k1] = vals
        b[r0:r1] = rhs
        r0, k0 = r1, k1
    del blocks
    _return_freed_memory()
    # rows in the order of their first texel, over all views: a pass of the solve over the rows then sweeps the
    # texture once (lego, 2048 texture, 100 views: one product 0.27 s, against 1.22 s with each view's rows sorted
    # on their own (100 sweeps) and about 12x that in the pixels' order, where neighbouring rows read far-apart charts)
    order = np.argsort(indices[indptr[:-1]], kind="stable")  # (every row has a tap)
    A = sp.csr_matrix((data, indices, indptr), shape=(n_rows, len(ids)))[order]
    b = b[order]
    del data, indices, indptr

    # prior colour and chart label of every texel: inside a chart from the atlas raster, elsewhere the nearest one's
    fidx = cov.face_id.ravel()
    prior_lin = np.zeros((S * S, 3))
    pc = srgb_to_linear(np.asarray(prior_colors, np.float64))
    tin = np.nonzero(inside)[0]
    prior_lin[tin] = np.einsum("nk,nkc->nc", cov.bary.reshape(-1, 3)[tin].astype(np.float64), pc[faces[fidx[tin]]])
    label = np.full(S * S, -1, np.int64)
    label[tin] = atlas.charts[fidx[tin]]
    if len(tin):
        _, nearest = ndimage.distance_transform_edt(~inside.reshape(S, S), return_indices=True)
        near_flat = (nearest[0] * S + nearest[1]).ravel()
        prior_lin = prior_lin[near_flat]
        label = label[near_flat]

    # 4-neighbours of one chart, both unknown
    edges = []
    for step, ok in ((1, (np.arange(S * S) % S) < S - 1), (S, np.arange(S * S) < S * (S - 1))):
        a = np.nonzero(unknown & ok)[0]
        a = a[unknown[a + step] & (label[a] == label[a + step])]
        edges.append(np.stack([remap[a], remap[a + step]], 1))
    return TexelProblem(size=S, rows=A, b=b, ids=ids, unknown=unknown, edges=np.concatenate(edges),
                        prior=prior_lin[ids], views=n_views, samples=n_samples)


def solve(problem: TexelProblem, smoothness: float = SMOOTHNESS, prior: float = PRIOR,
          iterations: int = CG_ITERATIONS, tolerance: float = CG_TOLERANCE, threads: int | None = None):
    """The linear texels [n,3] minimising the problem's objective (module docstring; the weights relative to the
    mean photo weight a texel gets). Jacobi-preconditioned conjugate gradients from each texel's own weighted
    mean of what the photos show of it (the per-texel normal equation; the prior colour where none does).
    Returns (x, iterations, relative residual)."""
    import numba

    A = problem.rows
    d_data = column_square_sums(A.indices, A.data, A.shape[1])
    scale = float(d_data[d_data > 0].mean()) if (d_data > 0).any() else 1.0
    op = NormalOperator(A, problem.edges, smoothness * scale, prior * scale,
                        numba.get_num_threads() if threads is None else int(threads))
    rhs = _atb(A, problem.b).astype(np.float64) + op.prior * problem.prior
    row_sum = op.ata(np.ones((A.shape[1], 3), np.float32)).astype(np.float64) + op.prior  # (A^T A + prior I) 1
    seen = row_sum[:, 0] > 1e-12
    x0 = problem.prior.copy()
    x0[seen] = rhs[seen] / row_sum[seen]
    return pcg(op, rhs, 1.0 / op.diagonal(), x0, iterations, tolerance)


def texture_image(problem: TexelProblem, x: np.ndarray) -> np.ndarray:
    """sRGB uint8 [S,S,3] of the linear texels x [n,3]: clipped to [0,1]; every other texel takes the nearest
    solved texel's colour (gutters), so bilinear taps and mip levels across chart borders read surface colours."""
    S = problem.size
    lin = np.zeros((S * S, 3))
    lin[problem.ids] = np.clip(x, 0.0, 1.0)
    _, nearest = ndimage.distance_transform_edt(~problem.unknown.reshape(S, S), return_indices=True)
    lin = lin[(nearest[0] * S + nearest[1]).ravel()]
    return np.round(linear_to_srgb(lin) * 255.0).astype(np.uint8).reshape(S, S, 3)


def fit_texture(positions: np.ndarray, faces: np.ndarray, atlas: Atlas, views: Iterable, background,
                prior_colors: np.ndarray, supersample: int = 2, near: float = 0.01, smoothness: float = SMOOTHNESS,
                prior: float = PRIOR, iterations: int = CG_ITERATIONS,
                tolerance: float = CG_TOLERANCE) -> tuple[np.ndarray, FitStats]:
    """The sRGB uint8 texture [S,S,3] over `atlas` that best fits `views` (see the module docstring).

    positions [V,3], faces [F,3]: the opaque mesh in the cameras' frame; views: (camera, photo float [H,W,3] sRGB
    in [0,1]) pairs (cameras: world_to_camera, K, width, height); background: the sRGB colour behind the mesh;
    prior_colors [V,3]: sRGB vertex colours, what texels no photo sees get."""
    t0 = time.perf_counter()
    problem = assemble(positions, faces, atlas, views, background, prior_colors, supersample, near)
    return solve_texture(problem, time.perf_counter() - t0, smoothness, prior, iterations, tolerance)


def solve_texture(problem: TexelProblem, t_raster: float, smoothness: float = SMOOTHNESS, prior: float = PRIOR,
                  iterations: int = CG_ITERATIONS, tolerance: float = CG_TOLERANCE) -> tuple[np.ndarray, FitStats]:
    """fit_texture's solve of an assembled problem; t_raster: the seconds its rows took (for the report)."""
    t1 = time.perf_counter()
    x, its, rel = solve(problem, smoothness, prior, iterations, tolerance)
    t_solve = time.perf_counter() - t1
    image = texture_image(problem, x)
    stats = FitStats(views=problem.views, samples=problem.samples, pixels=problem.rows.shape[0],
                     unknowns=problem.rows.shape[1], iterations=its, relative_residual=rel,
                     seconds_raster=t_raster, seconds_solve=t_solve)
    return image, stats


@nb.njit(cache=True)
def _atb_rows(indptr, indices, data, b, out):  # pragma: no cover (compiled)
    for r in range(len(indptr) - 1):
        for k in range(indptr[r], indptr[r + 1]):
            j = indices[k]
            v = np.float64(data[k])
            for c in range(3):
                out[j, c] += v * b[r, c]


def _atb(A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
    """A^T b [n,3] float64 without transposing A."""
    out = np.zeros((A.shape[1], 3), np.float64)
    _atb_rows(A.indptr, A.indices, A.data, np.asarray(b, np.float32), out)
    return out
