"""The fused Adam step (trisplat.train.adam) against torch.optim.Adam: same parameters and moments over several
steps with per-group learning rates changing between steps, parameters without a gradient skipped, moments
remapped mid-run as trisplat.strategy.ops does, and NaN/Inf in a gradient or a new value reported."""
from __future__ import annotations

import numba
import pytest
import torch

from trisplat.train.adam import adam_step, torch_adam_step

SHAPES = {"positions": (37, 3), "sh_dc": (37, 1, 3), "sh_rest": (37, 15, 3), "opacity_logit": (37,)}


def _pair(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    values = {n: torch.randn(s, generator=g) for n, s in SHAPES.items()}
    out = []
    for fused in (False, True):
        params = {n: torch.nn.Parameter(v.clone()) for n, v in values.items()}
        groups = [{"params": [params[n]], "lr": 0.0, "name": n} for n in SHAPES]
        out.append((params, torch.optim.Adam(groups, eps=1e-15, fused=fused)))
    return out


def _grads(step: int, skip: str | None = None) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(100 + step)
    # gradients of very different sizes per parameter and element (Adam's normalisation is what is tested)
    return {n: torch.randn(s, generator=g) * 10.0 ** torch.randint(-6, 2, s, generator=g) for n, s in SHAPES.items()
            if n != skip}


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_matches_torch_adam_over_steps_with_per_group_learning_rates(threads):
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        (ref_p, ref_opt), (p, opt) = _pair()
        lrs = {"positions": 1e-3, "sh_dc": 2.5e-3, "sh_rest": 1.25e-4, "opacity_logit": 5e-2}
        for step in range(12):
            skip = "sh_rest" if step in (0, 5) else None  # no gradient: no step for it (its own bias correction)
            for params, o in ((ref_p, ref_opt), (p, opt)):
                for group in o.param_groups:
                    group["lr"] = lrs[group["name"]] * (0.9 ** step)
                for n, g in _grads(step, skip).items():
                    params[n].grad = g.clone()
            assert torch_adam_step(ref_opt)
            assert adam_step(opt)
            for o in (ref_opt, opt):
                o.zero_grad(set_to_none=True)
            for n in SHAPES:
                torch.testing.assert_close(p[n].detach(), ref_p[n].detach(), rtol=1e-6, atol=1e-7)
                s, rs = opt.state[p[n]], ref_opt.state[ref_p[n]]
                assert len(s) == len(rs)
                if not rs:  # never had a gradient yet
                    continue
                # (torch rounds each operation to float32, this pass rounds once: a few float32 roundings apart,
                # relative to the tensor's largest moment where the moment cancelled to near zero)
                for k in ("exp_avg", "exp_avg_sq"):
                    torch.testing.assert_close(s[k], rs[k], rtol=1e-6, atol=1e-6 * float(rs[k].abs().max()))
                assert float(s["step"]) == float(rs["step"]) and s["step"].dtype == torch.float32
        assert float(opt.state[p["sh_rest"]]["step"]) == 10.0
        # the parameters moved by many learning rates: a wrong bias correction or moment would show
        assert float((p["positions"].detach() - _pair()[0][0]["positions"].detach()).abs().max()) > 1e-3
    finally:
        numba.set_num_threads(before)


def test_moments_remapped_mid_run_and_state_dict_round_trip():
    """Rows removed and appended (the moments follow, new rows start at zero) and a state_dict saved and loaded into
    a fresh optimizer give the same steps as torch's Adam."""
    from trisplat.strategy import ops
    from trisplat.scene.model import TriangleScene

    g = torch.Generator().manual_seed(3)
    scene = TriangleScene(positions=torch.randn(20, 3, generator=g), sh=torch.randn(20, 4, 3, generator=g),
                          opacity_logit=torch.randn(20, generator=g), faces=torch.randint(0, 20, (10, 3), generator=g,
                                                                                           dtype=torch.int32))
    a, b = ops.make_trainable(scene, {n: 1e-2 for n in ops.VERTEX_PARAMS}), ops.make_trainable(
        scene, {n: 1e-2 for n in ops.VERTEX_PARAMS})
    for step in range(6):
        if step == 3:
            keep = torch.arange(0, 20, 2)
            for ts in (a, b):
                ts.faces = torch.zeros(0, 3, dtype=torch.int64)
                ops.index_vertices(ts, keep)
                ops.append_vertices(ts, {n: ts.params[n].detach()[:4] + 1.0 for n in ops.VERTEX_PARAMS})
        if step == 4:
            sd = b.optimizer.state_dict()
            b.optimizer = ops.make_adam([{"params": [b.params[n]], "lr": 1e-2, "name": n} for n in ops.VERTEX_PARAMS])
            b.optimizer.load_state_dict(sd)
        gg = torch.Generator().manual_seed(50 + step)
        grads = {n: torch.randn(a.params[n].shape, generator=gg) for n in ops.VERTEX_PARAMS}
        for ts in (a, b):
            for n in ops.VERTEX_PARAMS:
                ts.params[n].grad = grads[n].clone()
        assert torch_adam_step(a.optimizer)
        assert adam_step(b.optimizer)
        for ts in (a, b):
            ts.optimizer.zero_grad(set_to_none=True)
        for n in ops.VERTEX_PARAMS:
            torch.testing.assert_close(b.params[n].detach(), a.params[n].detach(), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("where", ["grad_nan", "grad_inf", "value_overflow"])
def test_reports_nan_and_inf(where):
    (_, ref_opt), (p, opt) = _pair()
    for group in opt.param_groups:
        group["lr"] = 1e-3
    for n, g in _grads(0).items():
        p[n].grad = g
    if where == "grad_nan":
        p["sh_rest"].grad[3, 2, 1] = float("nan")
    elif where == "grad_inf":
        p["positions"].grad[-1, 0] = float("inf")
    else:  # a finite gradient and a finite update whose result overflows float32
        opt.param_groups[3]["lr"] = 2e37
        p["opacity_logit"].data[0] = -3.3e38
        p["opacity_logit"].grad[0] = 1.0  # the update: -2e37 (Adam's first step moves by lr): -3.5e38
    assert not adam_step(opt)


def test_other_devices_dtypes_and_options_use_torch():
    """float64 parameters or a weight decay: torch's step (the same numbers as torch's own Adam)."""
    for kind in ("float64", "weight_decay"):
        x = torch.nn.Parameter(torch.randn(5, 3, dtype=torch.float64 if kind == "float64" else torch.float32))
        y = torch.nn.Parameter(x.detach().clone())
        wd = 0.1 if kind == "weight_decay" else 0.0
        ox, oy = torch.optim.Adam([x], lr=1e-2, weight_decay=wd), torch.optim.Adam([y], lr=1e-2, weight_decay=wd)
        for _ in range(3):
            x.grad, y.grad = torch.ones_like(x), torch.ones_like(y)
            assert adam_step(ox)
            oy.step()
        torch.testing.assert_close(x.detach(), y.detach(), rtol=0, atol=0)
