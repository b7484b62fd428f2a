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
    # faces condemned by each rule (a face can meet several; the cap on one event's removals may spare some)
    by_opacity: int = 0
    by_weight: int = 0
    by_size: int = 0

    def to_dict(self) -> dict:
        return {"faces_before": self.faces_before, "faces_removed": self.faces_removed,
                "vertices_removed": self.vertices_removed, "by_opacity": self.by_opacity,
                "by_weight": self.by_weight, "by_size": self.by_size}


def prune(ts: ops.TrainableScene, threshold: float, max_screen_px: float | None = None,
          max_fraction: float = 1.0, min_faces: int = 1) -> PruneResult:
    """Drop faces whose min vertex opacity or running max blending weight is <= threshold, and faces whose running
    maximum projected edge length exceeds max_screen_px (pixels).

    At most `max_fraction` of the faces go in one call (those with the lowest max blending weight first) and at
    least `min_faces` stay, so a run whose opacities have not risen yet (a very short schedule) thins out over
    several events instead of collapsing to nothing."""
    F = ts.num_faces
    with torch.no_grad():
        o = ts.opacities()
        face_opacity = o[ts.faces].min(dim=1).values
        weight = ts.face_stat("max_weight")
        low_opacity, low_weight = face_opacity <= threshold, weight <= threshold
        remove = low_opacity | low_weight
        oversized = torch.zeros_like(remove)
        if max_screen_px is not None:
            oversized = ts.face_stat("max_screen_px") > max_screen_px
            remove |= oversized
        keep_at_least = min(F, max(min_faces, F - int(max_fraction * F)))
        if int((~remove).sum()) < keep_at_least:
            # keep the most important of the condemned faces (oversized ones are not spared)
            priority = torch.where(remove, weight, torch.full_like(weight, float("inf")))
            keep_idx = torch.topk(priority, keep_at_least).indices
            remove[keep_idx] = False
    n_removed = int(remove.sum())
    ops.keep_faces(ts, ~remove)
    v_removed = ops.remove_orphan_vertices(ts)
    return PruneResult(F, n_removed, v_removed, int(low_opacity.sum()), int(low_weight.sum()), int(oversized.sum()))


def final_max_weight_prune(ts: ops.TrainableScene, max_weight: torch.Tensor, threshold: float) -> PruneResult:
    """The final pass: `max_weight` [F] measured over all training views; drop faces at or below threshold.
    A pass that would remove every face is skipped (nothing removed): an empty mesh helps nobody."""
    F = ts.num_faces
    keep = max_weight > threshold
    if not keep.any():
        return PruneResult(F, 0, 0)
    ops.keep_faces(ts, keep)
    v_removed = ops.remove_orphan_vertices(ts)
    return PruneResult(F, int((~keep).sum()), v_removed)
