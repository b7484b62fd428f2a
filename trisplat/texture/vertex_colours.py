"""The vertex colours that best fit the photos: the texture fit's least-squares problem (trisplat.texture.fit) with
the mesh's vertices as the unknowns.

What a glTF viewer shows of a mesh with vertex colours (COLOR_0, linear) is, at every sample, the perspective-correct
barycentric mix of its face's three vertex colours, in linear light; the pixel is the mean of its samples. So the
colours minimise the same objective as the texels do, with A's rows now holding each pixel's barycentric weights on
vertices, the smoothness term running over the mesh's edges and the prior pulling towards the model's own band-0
colours (what vertices no photo sees keep).

Why: the run's model colours a vertex with spherical harmonics, and the files can hold only band 0. The higher bands
were trained together with band 0, so band 0 alone is not the best view-independent colour: on Spot's surface the
model scored 36.7 dB and its band-0 file 34.2. Fitting the colours the file holds to the photos, as the file is
seen, recovers what an unlit vertex colour can.
"""
from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from trisplat.io.colour import linear_to_srgb, srgb_to_linear
from trisplat.mesh.orient import edge_table
from trisplat.texture.fit import SMOOTHNESS, NoViewSeesMesh, solve, view_rows
from trisplat.texture.raster import view_samples

# Pull towards the model's colours, relative to the mean photo weight a vertex gets. Fitted on 90% of the training
# views, scored on the other 10% and the test views (ad hoc, 2026-11-26), prior 0.01 / 0.1 / 1 / 3: Spot's surface
# test views 35.07 / 35.15 / 35.24 / 35.11 dB (band 0: 34.17); lego's 25.78 / - / 26.14 / 26.13 (band 0: 26.08).
PRIOR = 1.0
CG_ITERATIONS = 200
CG_TOLERANCE = 1e-4


@dataclass
class VertexProblem:
    """rows = W^1/2 A (csr float32, a row per covered pixel of every view, a column per vertex), b = W^1/2 b
    [rows,3], edges [E,2]: the mesh's edges, prior [V,3]: linear prior colours (the fit's `solve` reads these)."""

    rows: sp.csr_matrix
    b: np.ndarray
    edges: np.ndarray
    prior: np.ndarray
    views: int
    samples: int


@dataclass
class VertexFitStats:
    views: int
    samples: int
    pixels: int
    vertices: int
    seen: int  # vertices some pixel constrains
    iterations: int
    relative_residual: float
    seconds: float


class VertexRows:
    """The vertex problem's rows, a view at a time (add: one rasterisation of the view, which can feed the texture's
    rows too, trisplat.texture.fit.TexelRows), then the problem (finish)."""

    def __init__(self, n_vertices: int, faces: np.ndarray, background):
        self.n = int(n_vertices)
        self.faces = np.asarray(faces, np.int64)
        self.bg_lin = srgb_to_linear(np.asarray(background, np.float64))
        self.parts = ([], [], [], [])  # row lengths, vertex ids, values, rhs
        self.views = self.samples = 0

    def add(self, ss, photo) -> None:
        faces = self.faces
        blk = view_rows(ss, photo, self.bg_lin, lambda fid, bary: (faces[fid], bary), self.n)
        if blk is None:
            return
        for lst, part in zip(self.parts, blk):
            lst.append(part)
        self.views += 1
        self.samples += blk[4]

    def finish(self, prior_colors: np.ndarray) -> VertexProblem:
        """The problem; the rows added so far are handed over (this accumulator is empty afterwards)."""
        (lengths, cols, vals, rhs), self.parts = self.parts, ([], [], [], [])
        if not lengths:
            raise NoViewSeesMesh("no view sees the mesh: nothing to fit vertex colours to")
        indptr = np.r_[0, np.cumsum(np.concatenate(lengths))]
        A = sp.csr_matrix((np.concatenate(vals), np.concatenate(cols), indptr), shape=(len(indptr) - 1, self.n))
        prior = srgb_to_linear(np.clip(np.asarray(prior_colors, np.float64), 0.0, 1.0))
        return VertexProblem(rows=A, b=np.concatenate(rhs), edges=edge_table(self.faces).edges, prior=prior,
                             views=self.views, samples=self.samples)


def assemble_vertices(positions: np.ndarray, faces: np.ndarray, views: Iterable, background,
                      prior_colors: np.ndarray, supersample: int = 2, near: float = 0.01) -> VertexProblem:
    """The rows W^1/2 A and right-hand sides W^1/2 b of every view over the mesh's vertices (module docstring)."""
    rows = VertexRows(len(positions), faces, background)
    for ss, photo in view_samples(positions, rows.faces, views, supersample, near):
        rows.add(ss, photo)
    return rows.finish(prior_colors)


def fit_vertex_colors(positions: np.ndarray, faces: np.ndarray, views: Iterable, background,
                      prior_colors: np.ndarray, supersample: int = 2, near: float = 0.01,
                      smoothness: float = SMOOTHNESS, prior: float = PRIOR, iterations: int = CG_ITERATIONS,
                      tolerance: float = CG_TOLERANCE) -> tuple[np.ndarray, VertexFitStats]:
    """sRGB vertex colours [V,3] in [0,1] that best fit `views` ((camera, photo float [H,W,3] sRGB) pairs) as a
    glTF viewer shows the mesh with them (linear COLOR_0, samples averaged in linear light). positions [V,3],
    faces [F,3]: the opaque mesh in the cameras' frame; background: the sRGB colour behind it; prior_colors [V,3]
    sRGB: the model's colours, which vertices no photo sees keep."""
    t0 = time.perf_counter()
    problem = assemble_vertices(positions, faces, views, background, prior_colors, supersample, near)
    return solve_vertex_colors(problem, t0, smoothness, prior, iterations, tolerance)


def solve_vertex_colors(problem: VertexProblem, t0: float, smoothness: float = SMOOTHNESS, prior: float = PRIOR,
                        iterations: int = CG_ITERATIONS, tolerance: float = CG_TOLERANCE
                        ) -> tuple[np.ndarray, VertexFitStats]:
    """fit_vertex_colors's solve of an assembled problem; t0: the perf_counter time the fit started at."""
    x, its, rel = solve(problem, smoothness, prior, iterations, tolerance)
    n = problem.rows.shape[1]
    seen = np.bincount(problem.rows.indices, minlength=n) > 0
    colors = linear_to_srgb(np.clip(x, 0.0, 1.0)).astype(np.float32)
    stats = VertexFitStats(views=problem.views, samples=problem.samples, pixels=problem.rows.shape[0],
                           vertices=n, seen=int(seen.sum()), iterations=its, relative_residual=rel,
                           seconds=time.perf_counter() - t0)
    return colors, stats
