"""Opacity floor: raise it and re-solve the logits so realised vertex opacities do not jump."""
from __future__ import annotations

import torch

from trisplat.strategy import ops

_EPS = 1e-6


def resolve_logits(logit: torch.Tensor, old_floor: float, new_floor: float) -> torch.Tensor:
    """Logits w' with new_floor + (1-new_floor) sigmoid(w') = old_floor + (1-old_floor) sigmoid(w), where possible
    (opacities below the new floor are lifted to just above it)."""
    o = old_floor + (1.0 - old_floor) * torch.sigmoid(logit)
    s = ((o - new_floor) / max(1.0 - new_floor, 1e-12)).clamp(_EPS, 1.0 - _EPS)
    return torch.log(s) - torch.log1p(-s)


def raise_floor(ts: ops.TrainableScene, new_floor: float) -> None:
    if new_floor == ts.opacity_floor:
        return
    with torch.no_grad():
        p = ts.params["opacity_logit"]
        p.copy_(resolve_logits(p, ts.opacity_floor, new_floor))
    ts.opacity_floor = float(new_floor)
