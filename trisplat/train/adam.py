"""torch.optim.Adam's step as one parallel Numba pass per parameter, and one check of the new values that stands for the
checks of the gradients and of the parameters (issue 50).

The optimizer stays a torch.optim.Adam: its param_groups (the learning rates the trainer sets), its state (step,
exp_avg, exp_avg_sq: what checkpoints save and trisplat.strategy.ops remaps when rows change) and its state_dict are
torch's own. `adam_step(optimizer)` does the update torch's Adam does (amsgrad, weight decay and maximize off, as
trisplat.strategy.ops.make_adam makes it), for every parameter with a gradient:

  step += 1
  m = beta1 m + (1 - beta1) g
  v = beta2 v + (1 - beta2) g^2
  p = p - lr / (1 - beta1^step) * m / (sqrt(v) / sqrt(1 - beta2^step) + eps)

in one vectorised parallel pass per parameter, then checks the new values in a second one (a NaN/Inf gradient leaves
a NaN there). Why: torch's fused CPU Adam (~13 ms of CPU time per step on bonsai's 221k-vertex surface, SH degree 3)
was followed by a check of every gradient (~2.4 ms) and preceded by one of every parameter at the next step
(~2.4 ms); the update here costs what torch's does, and its one check of the new values stands for both.

`torch_adam_step(optimizer)` is the reference: torch's own step, with the checks as separate passes. Tensors off
the CPU, other dtypes and other Adam options go there.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange


# no "nnan"/"ninf" among the fast-math flags: NaN and Inf must go through as they are (they are what is checked)
_FAST = {"contract", "arcp", "afn"}


@njit(parallel=True, cache=True, fastmath=_FAST)
def _adam(p, g, m, v, beta1, one_minus_beta1, beta2, one_minus_beta2, step_size, inv_bc2_sqrt, eps):
    """In place over the flat float32 arrays p, g, m, v (float32 scalars: the loop vectorises)."""
    for i in prange(p.shape[0]):
        gi = g[i]
        mi = beta1 * m[i] + one_minus_beta1 * gi
        vi = beta2 * v[i] + one_minus_beta2 * gi * gi
        m[i] = mi
        v[i] = vi
        p[i] = p[i] - step_size * mi / (np.sqrt(vi) * inv_bc2_sqrt + eps)


@njit(parallel=True, cache=True, fastmath={"reassoc"})
def _nonfinite(p):
    """0 when every value of p is finite, NaN otherwise (x - x is 0 for a finite x, NaN for NaN and +-Inf)."""
    s = np.float32(0.0)
    for i in prange(p.shape[0]):
        s += p[i] - p[i]
    return s


def _fused_ok(optimizer: torch.optim.Optimizer) -> bool:
    """Whether every group and parameter with a gradient is one `_adam` does exactly."""
    if type(optimizer) is not torch.optim.Adam:
        return False
    for group in optimizer.param_groups:
        if group.get("amsgrad") or group.get("weight_decay", 0) != 0 or group.get("maximize") or \
                group.get("capturable") or group.get("differentiable") or isinstance(group["lr"], torch.Tensor):
            return False
        for p in group["params"]:
            if p.grad is None:
                continue
            if p.device.type != "cpu" or p.dtype != torch.float32 or p.grad.dtype != torch.float32 or p.grad.is_sparse \
                    or not (p.is_contiguous() and p.grad.is_contiguous()):
                return False
            st = optimizer.state.get(p)
            if st and not (st["exp_avg"].is_contiguous() and st["exp_avg_sq"].is_contiguous()
                           and st["exp_avg"].dtype == torch.float32 and st["exp_avg_sq"].dtype == torch.float32):
                return False
    return True


def adam_step(optimizer: torch.optim.Adam) -> bool:
    """One Adam step of every parameter with a gradient (module docstring), checking the gradients and the new values;
    False when one is NaN/Inf (the parameters are then partly updated: the caller rolls back). Falls back to
    torch_adam_step where the fused pass does not apply."""
    if not _fused_ok(optimizer):
        return torch_adam_step(optimizer)
    ok = True
    f32 = np.float32
    for group in optimizer.param_groups:
        beta1, beta2 = (float(b) for b in group["betas"])
        lr, eps = float(group["lr"]), float(group["eps"])
        for p in group["params"]:
            if p.grad is None:
                continue
            st = optimizer.state[p]
            if len(st) == 0:  # as torch initialises it (a float32 step tensor: what its fused Adam keeps)
                st["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            st["step"] += 1
            step = float(st["step"])
            step_size = lr / (1.0 - beta1 ** step)
            inv_bc2_sqrt = 1.0 / math.sqrt(1.0 - beta2 ** step)
            values = p.detach().view(-1).numpy()
            _adam(values, p.grad.detach().view(-1).numpy(), st["exp_avg"].view(-1).numpy(),
                  st["exp_avg_sq"].view(-1).numpy(), f32(beta1), f32(1.0 - beta1), f32(beta2), f32(1.0 - beta2),
                  f32(step_size), f32(inv_bc2_sqrt), f32(eps))
            # a NaN/Inf gradient makes the new value NaN (m or m / sqrt(v) is NaN), so checking the new values
            # checks the gradients too
            ok = ok and _nonfinite(values) == 0
    return ok


def all_finite(t: torch.Tensor) -> bool:
    """No NaN/Inf in t. A finite sum proves it (one fast pass, ~7x cheaper than isfinite().all() on CPU); only a
    non-finite sum (a NaN/Inf, or an overflow of the sum itself) needs the exact element-wise test."""
    return bool(torch.isfinite(t.sum())) or bool(torch.isfinite(t).all())


def torch_adam_step(optimizer: torch.optim.Optimizer) -> bool:
    """The reference: check every gradient, torch's own step (nothing is updated when a gradient is NaN/Inf), then
    check the new values: adam_step's contract as separate passes."""
    params = [p for g in optimizer.param_groups for p in g["params"] if p.grad is not None]
    if not all(all_finite(p.grad) for p in params):
        return False
    optimizer.step()
    return all(all_finite(p.detach()) for p in params)
