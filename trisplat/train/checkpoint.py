"""Checkpoints: atomic save (temporary file, then rename) and exact resume of parameters, Adam state and RNG."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from trisplat.scene.model import TriangleScene
from trisplat.strategy import ops


def atomic_torch_save(obj, path: Path) -> None:
    """Write to path.tmp, fsync, then rename: a kill or full disk never corrupts the previous file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        torch.save(obj, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def checkpoint_state(ts: ops.TrainableScene, step: int, total_steps: int, generator: torch.Generator,
                     extra: dict) -> dict:
    """Everything needed to continue exactly: parameters with their Adam moments, faces, statistics, RNG."""
    opt_state = {}
    for group in ts.optimizer.param_groups:
        p = group["params"][0]
        opt_state[group["name"]] = {"lr": group["lr"], "state": {k: (v.clone() if torch.is_tensor(v) else v)
                                                                 for k, v in ts.optimizer.state.get(p, {}).items()}}
    return {
        "step": step,
        "total_steps": total_steps,
        "params": {k: v.detach().clone() for k, v in ts.params.items()},
        "optimizer": opt_state,
        "faces": ts.faces.clone(),
        "face_stats": {k: v.clone() for k, v in ts.face_stats.items()},
        "opacity_floor": ts.opacity_floor,
        "linear_light": ts.linear_light,
        "generator": generator.get_state(),
        "extra": extra,
    }


def restore_trainable(ckpt: dict, device: torch.device | str | None = None) -> ops.TrainableScene:
    """Rebuild the TrainableScene (parameters, Adam state, faces, statistics) saved by checkpoint_state, its tensors
    on `device` (None: where the checkpoint's are; a checkpoint read from disk is on the CPU)."""
    dev = ckpt["faces"].device if device is None else torch.device(device)
    params = {k: torch.nn.Parameter(v.to(dev, copy=True)) for k, v in ckpt["params"].items()}
    groups = [{"params": [params[n]], "lr": ckpt["optimizer"][n]["lr"], "name": n} for n in ops.VERTEX_PARAMS]
    opt = ops.make_adam(groups)
    for n in ops.VERTEX_PARAMS:
        st = ckpt["optimizer"][n]["state"]
        if st:
            opt.state[params[n]] = {k: (v.to(dev, copy=True) if torch.is_tensor(v) else v) for k, v in st.items()}
    F = int(ckpt["faces"].shape[0])
    stats = {k: ckpt["face_stats"][k].to(dev, copy=True) if k in ckpt["face_stats"] else torch.zeros(F, device=dev)
             for k in ops.FACE_STATS}  # checkpoints of older versions lack the newer statistics: they start at zero
    return ops.TrainableScene(params=params, optimizer=opt, faces=ckpt["faces"].to(dev, copy=True),
                              opacity_floor=float(ckpt["opacity_floor"]),
                              linear_light=bool(ckpt.get("linear_light", False)), face_stats=stats)


def load_checkpoint(path: Path) -> dict:
    """A checkpoint written by `checkpoint_state` + `atomic_torch_save`. Loaded with `weights_only=True`: a
    checkpoint holds only tensors, numbers, strings, lists and dicts, so a file that would run code when unpickled
    (or any other object) is refused instead of executed."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no checkpoint to resume from")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a corrupt or foreign file
        raise ValueError(f"{path}: unreadable checkpoint, or one holding more than plain tensors and numbers "
                         f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from exc


def load_scene_from_run(run) -> tuple[TriangleScene, np.ndarray]:
    """A run's model in the normalised frame and its normalisation [4,4]: model.ply when training finished,
    otherwise the last checkpoint (a model.ply of an unfinished run may be from an interrupted finish; an unreadable
    model.ply falls back to the checkpoint with a warning)."""
    import warnings

    from trisplat import run as run_layout
    from trisplat.io import load_model_ply

    model, ckpt_path = run.path / run_layout.MODEL, run.path / run_layout.CHECKPOINT
    if model.exists() and (run.state.get("finished") or not ckpt_path.exists()):
        try:
            return load_model_ply(model)
        except Exception as exc:  # noqa: BLE001 - any unreadable model file: the checkpoint is the fallback
            if not ckpt_path.exists():
                raise
            warnings.warn(f"{model}: unreadable ({exc}); using the checkpoint {ckpt_path}", stacklevel=2)
    ckpt = load_checkpoint(ckpt_path)
    ts = restore_trainable(ckpt)
    return ts.to_scene(), np.asarray(ckpt["extra"]["normalization"], dtype=np.float64)
