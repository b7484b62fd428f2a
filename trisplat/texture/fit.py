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
small prior and smoothness terms only decide texels no photo constrains. Normal equations, Jacobi-preconditioned
conjugate gradients on the three channels at once; texels outside every chart are filled from the nearest fitted
texel (gutters), so bilinear taps and mip levels across chart borders read surface colours.
"""
from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy import ndimage

from trisplat.io.colour import linear_to_srgb, linear_to_srgb_slope, srgb_to_linear
from trisplat.texture.atlas import Atlas
from trisplat.texture.raster import surface_samples
from trisplat.texture.sampling import bilinear_taps

SMOOTHNESS = 1e-2  # weight of the neighbour term, relative to the mean photo weight a texel gets
PRIOR = 1e-3  # weight of the pull towards the vertex colours, relative to the same
CG_ITERATIONS = 200
CG_TOLERANCE = 1e-4  # relative residual of the normal equations


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


def texel_coverage(atlas: Atlas):
    """Rasterise the atlas itself: for every texel centre, the face whose uv triangle holds it (-1: none) and its
    barycentrics (the uv layout seen by an orthographic camera: positions (u S, v S, 1), identity pose)."""
    S = atlas.size
    pos = np.column_stack([atlas.uv * S, np.ones(len(atlas.uv))])
    K = np.eye(3)
    return surface_samples(pos, atlas.uv_faces, np.eye(4), K, S, S, 1, near=0.5)


def fit_texture(positions: np.ndarray, faces: np.ndarray, atlas: Atlas, views: Iterable, background,
                prior_colors: np.ndarray, supersample: int = 2, near: float = 0.01, smoothness: float = SMOOTHNESS,
                prior: float = PRIOR, iterations: int = CG_ITERATIONS) -> tuple[np.ndarray, FitStats]:
    """The sRGB uint8 texture [S,S,3] over `atlas` that best fits `views` (see the module docstring).

    positions [V,3], faces [F,3]: the opaque mesh in the cameras' frame; views: (camera, photo float [H,W,3] sRGB
    in [0,1]) pairs (cameras: world_to_camera, K, width, height); background: the sRGB colour behind the mesh;
    prior_colors [V,3]: sRGB vertex colours, what texels no photo sees get."""
    S = atlas.size
    faces = np.asarray(faces, np.int64)
    uv_corner = atlas.uv[atlas.uv_faces]  # [F,3,2]
    bg_lin = srgb_to_linear(np.asarray(background, np.float64))
    blocks, rhs = [], []
    n_views = n_samples = 0
    t0 = time.perf_counter()
    for cam, photo in views:
        W, H = cam.width, cam.height
        ss = surface_samples(positions, faces, np.asarray(cam.world_to_camera, np.float64), np.asarray(cam.K),
                             W, H, supersample, near)
        s = ss.supersample
        hit = ss.face_id >= 0
        ys, xs = np.nonzero(hit)
        if len(ys) == 0:
            continue
        fid = ss.face_id[ys, xs]
        uv = np.einsum("nk,nkc->nc", ss.bary[ys, xs].astype(np.float64), uv_corner[fid])
        idx, w = bilinear_taps(uv, S, S)
        pix = (ys // s) * W + xs // s
        covered, row = np.unique(pix, return_inverse=True)
        frac = np.bincount(row, minlength=len(covered)) / float(s * s)  # surface share of each covered pixel
        target = srgb_to_linear(np.asarray(photo, np.float64).reshape(-1, 3)[covered])
        omega = linear_to_srgb_slope(target.mean(1)) ** 2
        sq = np.sqrt(omega)
        b = (target - (1.0 - frac)[:, None] * bg_lin[None, :]) * sq[:, None]
        vals = (w / float(s * s)) * sq[row][:, None].astype(np.float32)
        A = sp.csr_matrix((vals.ravel(), (np.repeat(row, 4), idx.ravel())), shape=(len(covered), S * S),
                          dtype=np.float32)
        A.sum_duplicates()
        blocks.append(A)
        rhs.append(b.astype(np.float32))
        n_views += 1
        n_samples += len(ys)
    if not blocks:
        raise ValueError("no view sees the mesh: nothing to fit a texture to")
    A = sp.vstack(blocks, format="csr")
    b = np.concatenate(rhs)
    del blocks, rhs
    t_raster = time.perf_counter() - t0

    # unknowns: texels some sample reads, and texels inside a chart (for the prior)
    cov = texel_coverage(atlas)
    inside = cov.face_id.ravel() >= 0
    col_used = np.zeros(S * S, bool)
    col_used[A.indices] = True
    unknown = col_used | inside
    remap = np.full(S * S, -1, np.int64)
    ids = np.nonzero(unknown)[0]
    remap[ids] = np.arange(len(ids))
    A = sp.csr_matrix((A.data, remap[A.indices].astype(np.int32), A.indptr), shape=(A.shape[0], len(ids)))

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

    # smoothness between 4-neighbours of one chart, both unknown
    edges = []
    for step, ok in ((1, (np.arange(S * S) % S) < S - 1), (S, np.arange(S * S) < S * (S - 1))):
        a = np.nonzero(unknown & ok)[0]
        a = a[unknown[a + step] & (label[a] == label[a + step])]
        edges.append(np.stack([remap[a], remap[a + step]], 1))
    e = np.concatenate(edges)
    n = len(ids)
    adj = sp.coo_matrix((np.ones(2 * len(e), np.float32), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                        shape=(n, n)).tocsr()
    lap = sp.diags(np.asarray(adj.sum(1)).ravel().astype(np.float32)) - adj

    AtA_diag = np.asarray(A.multiply(A).sum(0)).ravel()
    scale = float(AtA_diag[AtA_diag > 0].mean()) if (AtA_diag > 0).any() else 1.0
    lam_s, lam_p = smoothness * scale, prior * scale
    x_prior = prior_lin[ids]
    At = A.T.tocsr()
    rhs = At @ b + lam_p * x_prior
    # the normal matrix once (rows of A hold a few dozen texels: cheap), then each iteration is one sparse product
    N = (At @ A + lam_s * lap + sp.identity(n, dtype=np.float32, format="csr") * lam_p).tocsr()
    del At, A
    diag = N.diagonal().astype(np.float64)

    def apply(x):
        return N @ x

    t1 = time.perf_counter()
    x, its, rel = _pcg(apply, rhs, 1.0 / diag, x_prior.copy(), iterations, CG_TOLERANCE)
    t_solve = time.perf_counter() - t1

    lin = np.zeros((S * S, 3))
    lin[ids] = np.clip(x, 0.0, 1.0)
    # gutters: every other texel takes the nearest solved texel's colour
    _, nearest = ndimage.distance_transform_edt(~unknown.reshape(S, S), return_indices=True)
    lin = lin[(nearest[0] * S + nearest[1]).ravel()]
    image = np.round(linear_to_srgb(lin) * 255.0).astype(np.uint8).reshape(S, S, 3)
    stats = FitStats(views=n_views, samples=n_samples, pixels=len(b), unknowns=n, iterations=its,
                     relative_residual=rel, seconds_raster=t_raster, seconds_solve=t_solve)
    return image, stats


def _pcg(apply, b: np.ndarray, minv: np.ndarray, x: np.ndarray, iterations: int, tol: float):
    """Preconditioned conjugate gradients on the columns of b [n,k] at once (each column its own step sizes);
    minv: the inverse of the diagonal. Returns (x, iterations, the largest relative residual)."""
    r = b - apply(x)
    z = r * minv[:, None]
    p = z.copy()
    rz = (r * z).sum(0)
    bnorm = np.maximum(np.linalg.norm(b, axis=0), 1e-30)
    rel = float((np.linalg.norm(r, axis=0) / bnorm).max())
    k = 0
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
