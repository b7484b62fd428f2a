"""Densification: midpoint subdivision of faces sampled by max blending weight plus the largest faces, up to a cap."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from trisplat.strategy import ops


@dataclass(frozen=True)
class DensifyResult:
    faces_selected: int
    vertices_added: int
    reason: str = ""


def face_areas(positions: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    p = positions[faces]
    return 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).norm(dim=1)


def densify(ts: ops.TrainableScene, growth: float, max_vertices: int, n_largest: int, min_face_px: float,
            generator: torch.Generator | None = None) -> DensifyResult:
    """Grow the vertex count towards min(max_vertices, growth * V) by subdividing faces.

    Candidates are sampled without replacement with probability proportional to their running max blending weight
    (zero for faces whose longest projected edge stayed below min_face_px), plus the n_largest faces by world area.
    Never fails for lack of candidates: with no positive weight it subdivides only the largest faces, and with no
    faces at all it does nothing and says so.
    """
    V, F = ts.num_vertices, ts.num_faces
    target = min(int(max_vertices), int(growth * V))
    if F == 0:
        return DensifyResult(0, 0, "no faces")
    if target <= V:
        return DensifyResult(0, 0, "vertex cap reached")
    # each subdivided face adds at most 3 vertices (fewer where midpoints are shared)
    n_want = max(1, min(F, (target - V) // 3))
    with torch.no_grad():
        weight = ts.face_stat("max_weight").clone()
        weight[ts.face_stat("max_screen_px") < min_face_px] = 0.0
        areas = face_areas(ts.params["positions"].detach(), ts.faces)
        largest = torch.topk(areas, min(n_largest, F)).indices
        n_sample = min(n_want, int((weight > 0).sum()))
        chosen = [largest]
        if n_sample > 0:  # drawn on the generator's device (the CPU's for a GPU run: the same draws as on the CPU)
            at = weight.device if generator is None else generator.device
            chosen.append(torch.multinomial(weight.to(at), n_sample, replacement=False,
                                            generator=generator).to(weight.device))
        selected = torch.unique(torch.cat(chosen))
    added = ops.subdivide_faces(ts, selected)
    return DensifyResult(int(selected.numel()), added, "" if n_sample > 0 else "no blended faces; largest only")
