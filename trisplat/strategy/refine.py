"""Refinement of a connected surface: more vertices where the photos show detail the surface cannot yet colour.

After the switch the surface's vertex colours are interpolated across each face, so colour detail needs vertices.
Marching cubes and quadric decimation place vertices by geometry (many on curved parts, few on flat textured
parts); refinement adds them by appearance: faces whose vertices keep receiving large colour gradients (residual
photometric error around them) are split in 4 by conforming (red-green) refinement (`ops.refine_faces`), which keeps
the surface welded: no T-junctions, every edge still shared by the faces on both sides.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from trisplat.strategy import ops

FACES_PER_SPLIT = 6  # a face split in 4 adds 3 faces, and its (typically 3) bisected neighbours 1 each


@dataclass(frozen=True)
class RefineResult:
    faces_selected: int
    vertices_added: int
    faces_added: int
    reason: str = ""


@torch.no_grad()
def accumulate_colour_gradient(ts: ops.TrainableScene) -> None:
    """After a backward pass: add each face's mean colour-gradient norm over its vertices (base colour, SH DC) to
    face_stats["colour_grad"], and count the faces that got one (seen in this view) in colour_grad_n."""
    g = ts.params["sh_dc"].grad
    if g is None:
        return
    vn = g.reshape(g.shape[0], -1).norm(dim=1)
    score = vn[ts.faces].mean(1)
    ts.face_stats["colour_grad"] += score
    ts.face_stats["colour_grad_n"] += (score > 0).to(score.dtype)


def reset_colour_gradient(ts: ops.TrainableScene) -> None:
    ts.face_stats["colour_grad"] = torch.zeros_like(ts.face_stats["colour_grad"])
    ts.face_stats["colour_grad_n"] = torch.zeros_like(ts.face_stats["colour_grad_n"])


def refine_surface(ts: ops.TrainableScene, growth: float, max_faces: int, min_face_px: float) -> RefineResult:
    """Grow the face count towards min(max_faces, growth x F): split the faces with the largest mean colour gradient
    (among faces whose longest projected edge reached 2 x min_face_px: smaller ones are already finer than the
    pixels) by conforming refinement, then restart the gradient statistics."""
    F = ts.num_faces
    target = min(int(max_faces), int(growth * F))
    if F == 0:
        return RefineResult(0, 0, 0, "no faces")
    if target <= F:
        return RefineResult(0, 0, 0, "face cap reached")
    n_want = max(1, (target - F) // FACES_PER_SPLIT)
    score = ts.face_stats["colour_grad"] / ts.face_stats["colour_grad_n"].clamp_min(1.0)
    score[ts.face_stat("max_screen_px") < 2.0 * min_face_px] = 0.0
    n = min(n_want, int((score > 0).sum()))
    if n == 0:
        reset_colour_gradient(ts)
        return RefineResult(0, 0, 0, "no face large enough with a colour gradient")
    chosen = torch.topk(score, n).indices
    added = ops.refine_faces(ts, chosen)
    reset_colour_gradient(ts)
    return RefineResult(n, added, ts.num_faces - F)
