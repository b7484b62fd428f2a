"""Schedules as pure functions of progress p = step / total_steps, so a short run has the 30k run's shape."""
from __future__ import annotations

import math
from dataclasses import dataclass

from trisplat.train.config import PAPER_STEPS, TrainConfig


def progress(step: int, total: int) -> float:
    return min(max(step / max(total, 1), 0.0), 1.0)


def sigma(p: float, cfg: TrainConfig) -> float:
    """Window sharpness: linear from sigma_start to sigma_end over the whole run. After the switch to a connected
    surface (cfg.switch_at), at most cfg.surface_sigma, decaying geometrically to sigma_end at the end: the window is
    0 on every edge, so a soft window shows a connected mesh's edges as see-through cracks."""
    linear = linear_sigma(p, cfg)
    at = cfg.switch_at
    if at is None or p < at or cfg.surface_sigma is None:
        return linear
    start = min(cfg.surface_sigma, cfg.sigma_start + (cfg.sigma_end - cfg.sigma_start) * at)
    q = min((p - at) / max(1.0 - at, 1e-9), 1.0)
    return min(linear, start * (cfg.sigma_end / start) ** q) if start > cfg.sigma_end else linear


def linear_sigma(p: float, cfg: TrainConfig) -> float:
    """The soup's window sharpness: linear from sigma_start at p = 0 to sigma_end at p = 1."""
    return cfg.sigma_start + (cfg.sigma_end - cfg.sigma_start) * p


def _event_index(p: float, begin: float, interval: float) -> int:
    """How many events (every `interval`, starting at `begin`) have happened by progress p; -1 before the first."""
    if p < begin:
        return -1
    return int(math.floor((p - begin) / interval + 1e-9))


def opacity_floor(p: float, cfg: TrainConfig) -> float:
    """Opacity floor, raised in steps every floor_interval from floor_begin, reaching floor_end at floor_full."""
    k = _event_index(p, cfg.floor_begin, cfg.floor_interval)
    if k < 0:
        return 0.0  # TS+ starts with no floor; the first raise jumps to floor_start
    q = min(max((cfg.floor_begin + k * cfg.floor_interval - cfg.floor_begin)
                / (cfg.floor_full - cfg.floor_begin), 0.0), 1.0)
    if p >= 1.0 - 1e-9:
        q = 1.0
    return cfg.floor_start + (cfg.floor_end - cfg.floor_start) * q


def position_lr(p: float, cfg: TrainConfig, extent: float) -> float:
    """0 during the hold, then exponential decay from lr_position to lr_position * final_ratio (times extent)."""
    if p < cfg.position_hold:
        return 0.0
    q = (p - cfg.position_hold) / max(1.0 - cfg.position_hold, 1e-9)
    return cfg.lr_position * extent * math.exp(math.log(cfg.lr_position_final_ratio) * min(q, 1.0))


def surface_position_lr(p: float, at: float, cfg: TrainConfig, extent: float) -> float:
    """The position learning rate after a switch at progress `at` when cfg.surface_lr_position > 0: from
    surface_lr_position x lr_position at the switch, exponentially to lr_position x lr_position_final_ratio at the
    end (times extent); the soup's schedule (position_lr) otherwise."""
    if cfg.surface_lr_position <= 0 or p < at:
        return position_lr(p, cfg, extent)
    q = min((p - at) / max(1.0 - at, 1e-9), 1.0)
    start, end = cfg.surface_lr_position, cfg.lr_position_final_ratio
    return cfg.lr_position * extent * start * (end / start) ** q


def sh_degree(p: float, cfg: TrainConfig) -> int:
    """Active SH degree: one more band every 1k paper-iterations, up to cfg.sh_degree."""
    return min(cfg.sh_degree, int(p * PAPER_STEPS // 1000))


def supersample(p: float, cfg: TrainConfig) -> int:
    if p >= cfg.supersample_4x_from:
        return 4
    if p >= cfg.supersample_2x_from:
        return 2
    return 1


def coarse(p: float, cfg: TrainConfig, width: int, height: int) -> int:
    """Resolution divisor of a training step at progress p (1: the training resolution): cfg.coarse_factor before
    cfg.coarse_until when the coarse image keeps at least cfg.coarse_min_px on its short side."""
    f = int(cfg.coarse_factor)
    if p < cfg.coarse_until and min(width, height) // f >= cfg.coarse_min_px:
        return f
    return 1


def pixel_cost(p: float, cfg: TrainConfig, width: int, height: int) -> float:
    """Rendered pixels per training step at progress p relative to the training resolution (supersampling and the
    coarse steps): what --minutes planning prices the rest of the schedule with."""
    return (supersample(p, cfg) / coarse(p, cfg, width, height)) ** 2


def prune_threshold(p: float, cfg: TrainConfig) -> float:
    """Rises by prune_threshold_step at each paper pruning event after prune_from."""
    k = max(_event_index(p, cfg.prune_from, cfg.prune_interval), 0)
    return cfg.prune_threshold_start + cfg.prune_threshold_step * k


def crossed(p_prev: float, p: float, begin: float, end: float, interval: float) -> bool:
    """True when progress moving from p_prev to p crosses an event boundary begin + k * interval (< end)."""
    if p < begin or p >= end:
        return False
    return _event_index(p, begin, interval) != _event_index(p_prev, begin, interval)


@dataclass
class Clock:
    """Progress as a pure function of the step: linear from (anchor_step, anchor_p) to (total, 1).

    A fixed-step run has anchor (0, 0). `--minutes` runs re-plan `total` from the measured step rate; re-planning
    moves the anchor to the current step so progress never jumps or runs backwards.
    """

    total: int
    anchor_step: int = 0
    anchor_p: float = 0.0

    def p(self, step: int) -> float:
        if step >= self.total:
            return 1.0
        span = max(self.total - self.anchor_step, 1)
        return min(max(self.anchor_p + (step - self.anchor_step) / span * (1.0 - self.anchor_p), 0.0), 1.0)

    def replan(self, step: int, new_total: int) -> None:
        new_total = max(int(new_total), step + 1)
        self.anchor_p = self.p(step)
        self.anchor_step = step
        self.total = new_total
