"""Pruning: drop faces that are too transparent, never blended, or oversized; then drop orphaned vertices."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from trisplat.strategy import ops


@dataclass(frozen=True)
class PruneResult:
    faces_before: int
    faces_removed: int
    vertices_removed: int


def prune(ts: ops.TrainableScene, threshold: float, max_screen_px: float | None = None,
          min_faces: int = 1) -> PruneResult:
    """Drop faces whose min vertex opacity or running max blending weight is <= threshold, and faces whose running
    maximum projected edge length exceeds max_screen_px (pixels). Never removes all faces: at least `min_faces`
    (the most important ones) are kept, so training can always continue."""
    F = ts.num_faces
    with torch.no_grad():
        o = ts.opacities()
        face_opacity = o[ts.faces].min(dim=1).values
        weight = ts.face_stat("max_weight")
        remove = (face_opacity <= threshold) | (weight <= threshold)
        if max_screen_px is not None:
            remove |= ts.face_stat("max_screen_px") > max_screen_px
        if int((~remove).sum()) < min(min_faces, F):
            keep_idx = torch.topk(weight, min(min_faces, F)).indices
            remove[keep_idx] = False
    n_removed = int(remove.sum())
    ops.keep_faces(ts, ~remove)
    v_removed = ops.remove_orphan_vertices(ts)
    return PruneResult(F, n_removed, v_removed)


def final_max_weight_prune(ts: ops.TrainableScene, max_weight: torch.Tensor, threshold: float) -> PruneResult:
    """The final pass: `max_weight` [F] measured over all training views; drop faces at or below threshold."""
    F = ts.num_faces
    keep = max_weight > threshold
    ops.keep_faces(ts, keep)
    v_removed = ops.remove_orphan_vertices(ts)
    return PruneResult(F, int((~keep).sum()), v_removed)
