"""Schedules are pure functions of progress and hit their end points."""
import math

import pytest

from trisplat.train import schedules as S
from trisplat.train.config import PRESETS, TrainConfig, make_config


def test_sigma_and_floor_end_points():
    cfg = TrainConfig()
    assert S.sigma(0.0, cfg) == pytest.approx(1.0)
    assert S.sigma(1.0, cfg) == pytest.approx(1e-4)
    assert S.sigma(0.5, cfg) == pytest.approx((1.0 + 1e-4) / 2)
    assert S.opacity_floor(0.0, cfg) == 0.0
    assert S.opacity_floor(5000 / 30000, cfg) == pytest.approx(0.1)
    assert S.opacity_floor(24000 / 30000, cfg) == pytest.approx(0.9999)
    assert S.opacity_floor(1.0, cfg) == pytest.approx(0.9999)
    # the paper's formula at its event points: floor = 0.1 + 0.8999 * (it - 5000) / 19000 every 500 iterations
    for it in (5000, 5500, 12000, 23500):
        assert S.opacity_floor(it / 30000, cfg) == pytest.approx(0.1 + 0.8999 * (it - 5000) / 19000)
    # monotone
    vals = [S.opacity_floor(k / 1000, cfg) for k in range(1001)]
    assert all(b >= a for a, b in zip(vals, vals[1:]))


def test_position_lr_hold_and_decay():
    cfg = TrainConfig()
    assert S.position_lr(0.0, cfg, 2.0) == 0.0
    assert S.position_lr(cfg.position_hold, cfg, 2.0) == pytest.approx(1.5e-3 * 2.0)
    assert S.position_lr(1.0, cfg, 2.0) == pytest.approx(1.5e-5 * 2.0)


def test_surface_position_lr_restarts_at_the_switch():
    cfg = TrainConfig(surface_lr_position=0.1)
    assert S.surface_position_lr(0.5, 0.6, cfg, 2.0) == S.position_lr(0.5, cfg, 2.0)  # before the switch: the soup's
    assert S.surface_position_lr(0.6, 0.6, cfg, 2.0) == pytest.approx(1.5e-4 * 2.0)  # 0.1 x lr_position
    assert S.surface_position_lr(0.8, 0.6, cfg, 2.0) == pytest.approx(2.0 * 1.5e-3 * math.sqrt(0.1 * cfg.lr_position_final_ratio))
    assert S.surface_position_lr(1.0, 0.6, cfg, 2.0) == pytest.approx(S.position_lr(1.0, cfg, 2.0))
    off = TrainConfig()  # 0: the soup's decay goes on after the switch
    assert S.surface_position_lr(0.8, 0.6, off, 2.0) == S.position_lr(0.8, off, 2.0)


def test_sh_degree_and_prune_threshold():
    cfg = TrainConfig(sh_degree=3)
    assert S.sh_degree(0.0, cfg) == 0
    assert S.sh_degree(1000 / 30000, cfg) == 1
    assert S.sh_degree(1.0, cfg) == 3
    assert S.prune_threshold(4000 / 30000, cfg) == pytest.approx(0.235)
    assert S.prune_threshold(5000 / 30000, cfg) == pytest.approx(0.255)


def test_events_scale_with_run_length():
    cfg = TrainConfig()
    for total in (300, 3000, 30000):
        clock = S.Clock(total)
        n = sum(S.crossed(clock.p(s - 1) if s else -1, clock.p(s), cfg.densify_from, cfg.densify_until,
                          cfg.densify_interval) for s in range(total))
        assert n == 25  # 500, 1000, ..., 12500 of 30k: the same count whatever the run length


def test_clock_replan_is_continuous():
    c = S.Clock(1000)
    p_before = c.p(400)
    c.replan(400, 3000)
    assert c.p(400) == pytest.approx(p_before)
    assert c.p(3000) == 1.0
    ps = [c.p(s) for s in range(400, 3001)]
    assert all(b >= a for a, b in zip(ps, ps[1:]))


def test_presets_build_and_reject_unknown():
    for name in PRESETS:
        assert isinstance(make_config(name), TrainConfig)
    with pytest.raises(ValueError, match="unknown preset"):
        make_config("nope")
    with pytest.raises(ValueError, match="unknown config keys"):
        TrainConfig.from_dict({"stepz": 3})
    with pytest.raises(ValueError, match="eval_supersample must be one of"):
        make_config("default", eval_supersample=5)  # refused before training, not when scoring after it
    assert math.isclose(make_config("fast", steps=10).steps, 10)
