"""One Ray task per block: each an ordinary trisplat run (the same Trainer, checkpoints and outputs) on the views of
its block, bounded to its cell and margin, writing its run folder to a shared location.

The block's run is trained in the block's own frame: a similarity that maps the box of its expanded cell onto the
cube [-1, 1]^3 (so the trainer's fusion grid, position learning rates and far field are sized for the block, not
the scene), with only the sparse points inside that box to start from and that box as its content box. Its
model.ply records that frame (the block's normalisation), which is how the merge brings it back.

Storage: a plain path is used in place (a folder every Ray node sees: a shared filesystem; tests use a local folder);
any URL (`s3://...`, `gs://...`, `file:///...`) goes through fsspec: the block trains in a local scratch folder that is
pulled from the URL before it starts (a retried task continues from the checkpoint there) and pushed after every
chunk of steps.

Faults: a task whose worker dies (killed, out of memory, its node lost) is retried by Ray (`max_retries`); the retry
resumes from the block's last checkpoint (written after every chunk of `chunk_steps` steps and by the trainer's own
timer), and the trainer's resume drops the history records of the steps it replays, so no step is counted twice.
Each attempt is recorded in the block's attempts.jsonl.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from trisplat import run as layout

INSTALL = 'pip install -e ".[cluster]"  (in a clone of trisplat; or: pip install "ray[client]==2.60.0")'
PROGRESS = "progress.json"
ATTEMPTS = "attempts.jsonl"
BLOCK_INFO = "block.json"
LOCAL_START_ATTEMPTS = 3  # tries to start local Ray (its node's start-up wait is fixed at 30 s)


class MissingRay(RuntimeError):
    """Ray (the optional `cluster` extra) is not installed."""


def require_ray():
    """The ray module, or MissingRay naming the install command."""
    try:
        import ray
    except ModuleNotFoundError as exc:
        if exc.name != "ray":
            raise
        raise MissingRay("partitioned training (--blocks other than 1, --plan) runs its blocks on Ray, an optional "
                         f"extra that is not installed here: {INSTALL}") from None
    return ray


# ------------------------------------------------------------------------------------------------- block frame
def block_similarity(box) -> np.ndarray:
    """[4,4] similarity from the scene's normalised frame to the block's: the box's centre to the origin, its
    longest side onto [-1, 1]."""
    from trisplat.data.normalize import similarity

    box = np.asarray(box, dtype=np.float64)
    return similarity(0.5 * (box[0] + box[1]), 0.5 * float((box[1] - box[0]).max()))


def block_scene_data(data, block, mask_outside: bool = True):
    """The SceneData one block trains on: its training and test views (re-indexed 0..), in the block's frame
    (block_similarity), its points (those inside its box) and its box as the content box. Images, alpha and depth
    are read from the scene's loaders, on demand.

    mask_outside (photos with alpha, whose content box confines the block's surface): the pixels whose content lies
    outside the block's content box (trisplat.blocks.mask.outside_content, from the scene's sparse points) are made
    background, with alpha 0, so the block is not asked to explain what it cannot hold (see trisplat.blocks.mask).
    Photos without alpha are left whole (their blocks keep a far field for what lies beyond the box)."""
    from trisplat.data.normalize import apply_to_points, apply_to_world_to_camera
    from trisplat.data.types import SceneData

    M = block_similarity(block.box)
    s = float(np.cbrt(np.linalg.det(M[:3, :3])))
    order = [int(i) for i in block.train] + [int(i) for i in block.test]
    cams = [dataclasses.replace(data.cameras[i], world_to_camera=apply_to_world_to_camera(M, data.cameras[i].world_to_camera))
            for i in order]
    box = np.asarray(block.box, dtype=np.float64)
    pts = cols = None
    if data.points is not None and len(data.points):
        inside = np.all((data.points >= box[0]) & (data.points <= box[1]), axis=1)
        pts = apply_to_points(M, np.asarray(data.points[inside], dtype=np.float64)).astype(np.float32)
        cols = None if data.point_colors is None else np.asarray(data.point_colors[inside], dtype=np.float32)
    content = box
    if data.bounds is not None:  # the scene's content box cuts the block's (a synthetic object box, robust points)
        full = np.asarray(data.bounds, dtype=np.float64)
        lo, hi = np.maximum(box[0], full[0]), np.minimum(box[1], full[1])
        if (hi > lo).all():
            content = np.stack([lo, hi])
    bounds = apply_to_points(M, content)
    image_loader = (lambda k: data.load_image(order[k]))
    alpha_loader = None if data.alpha_loader is None else (lambda k: data.load_alpha(order[k]))
    masked = (mask_outside and alpha_loader is not None and data.points is not None and len(data.points) > 0
              and data.load_alpha(order[0]) is not None)
    if masked:
        image_loader, alpha_loader = _outside_masked(data, order, content, image_loader, alpha_loader)
    depth_loader = None if data.depth_loader is None else (lambda k: data.load_depth(order[k]) * np.float32(s))
    return SceneData(cameras=cams, train_indices=np.arange(len(block.train), dtype=np.int64),
                     test_indices=np.arange(len(block.train), len(order), dtype=np.int64), points=pts,
                     point_colors=cols, normalization=M @ np.asarray(data.normalization, dtype=np.float64),
                     background=data.background, format=data.format, root=data.root,
                     warnings=[], image_loader=image_loader, bounds=bounds, options=dict(data.options),
                     depth_loader=depth_loader, alpha_loader=alpha_loader)


def _outside_masked(data, order: list[int], content: np.ndarray, image_loader, alpha_loader):
    """(image_loader, alpha_loader) of a block's views with the pixels outside_content finds made background (the
    capture's background colour, alpha 0); the masks are computed once per view, on first use."""
    from trisplat.blocks.mask import outside_content

    points = np.asarray(data.points, dtype=np.float64)
    background = np.asarray(data.background, dtype=np.float32).reshape(3)
    masks: dict[int, np.ndarray] = {}

    def outside(k: int) -> np.ndarray:
        if k not in masks:
            masks[k] = outside_content(data.cameras[order[k]], points, content)
        return masks[k]

    def load_image(k: int) -> np.ndarray:
        img = np.array(image_loader(k), dtype=np.float32, copy=True)
        img[outside(k)] = background
        return img

    def load_alpha(k: int) -> np.ndarray | None:
        a = alpha_loader(k)
        if a is None:
            return None
        a = np.array(a, dtype=np.float32, copy=True)
        a[outside(k)] = 0.0
        return a

    return load_image, load_alpha


# ----------------------------------------------------------------------------------------------------- storage
class Store:
    """Where block outputs go: a folder (used in place) or an fsspec URL (a local scratch copy, pulled and pushed)."""

    def __init__(self, location: str | Path):
        self.location = str(location)
        self.is_url = "://" in self.location
        if self.is_url:
            import fsspec

            self.fs, self.root = fsspec.core.url_to_fs(self.location)
            key = hashlib.sha1(self.location.encode()).hexdigest()[:12]
            self.scratch = Path(tempfile.gettempdir()) / f"trisplat-blocks-{key}"
        else:
            self.fs, self.root, self.scratch = None, self.location, Path(self.location)

    def local(self, name: str) -> Path:
        return self.scratch / name

    def _remote(self, name: str, rel: str = "") -> str:
        return "/".join(p for p in (self.root.rstrip("/"), name, rel) if p)

    def pull(self, name: str) -> None:
        """Copy the block's folder from the URL into its scratch folder (nothing for a plain folder)."""
        if not self.is_url:
            return
        local = self.local(name)
        local.mkdir(parents=True, exist_ok=True)
        remote = self._remote(name)
        if not self.fs.exists(remote):
            return
        for f in self.fs.find(remote):
            rel = f[len(remote.rstrip("/")) + 1:] if f.startswith(remote.rstrip("/")) else Path(f).name
            dest = local / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            self.fs.get_file(f, str(dest))

    def push(self, name: str) -> None:
        """Copy the block's scratch folder to the URL (nothing for a plain folder)."""
        if not self.is_url:
            return
        local = self.local(name)
        for f in sorted(p for p in local.rglob("*") if p.is_file() and not p.name.endswith(".tmp")):
            remote = self._remote(name, f.relative_to(local).as_posix())
            self.fs.makedirs(remote.rsplit("/", 1)[0], exist_ok=True)
            self.fs.put_file(str(f), remote)

    def read_json(self, name: str, file: str) -> dict | None:
        """A small JSON file of a block (its progress), or None when it is not there (yet) or half written."""
        try:
            if self.is_url:
                with self.fs.open(self._remote(name, file), "r") as fh:
                    return json.loads(fh.read())
            return json.loads((self.local(name) / file).read_text())
        except (OSError, ValueError):
            return None


# -------------------------------------------------------------------------------------------------------- task
def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _write_json(path: Path, obj: dict) -> None:
    from trisplat.io.atomic import atomic_write_text

    atomic_write_text(path, json.dumps(obj, indent=2))


def train_block(job: dict) -> dict:
    """Train one block to the end (or continue it from its checkpoint). job: capture, data_options, config
    (TrainConfig dict), plan (Plan dict), block (index), store (location), chunk_steps, threads. Returns the block's
    summary (steps, wall time, faces, peak memory, node, attempts)."""
    import torch

    from trisplat.blocks.partition import Plan
    from trisplat.data import load_dataset
    from trisplat.train.config import TrainConfig
    from trisplat.train.trainer import Trainer

    t_start = time.perf_counter()
    threads = int(job.get("threads", 1))
    torch.set_num_threads(threads)
    try:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    except (ImportError, ValueError):
        pass
    node = ""
    try:
        import ray

        if ray.is_initialized():
            node = ray.get_runtime_context().get_node_id()
    except ImportError:
        pass
    plan = Plan.from_dict(job["plan"])
    block = plan.blocks[int(job["block"])]
    store = Store(job["store"])
    store.pull(block.name)
    run_dir = store.local(block.name)
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt = run_dir / layout.CHECKPOINT
    resume = ckpt.exists()
    start_step = 0
    if resume:
        from trisplat.train.checkpoint import load_checkpoint

        start_step = int(load_checkpoint(ckpt)["step"])
    attempts_path = run_dir / ATTEMPTS
    attempt = 1 + (len(attempts_path.read_text().splitlines()) if attempts_path.exists() else 0)
    with open(attempts_path, "a") as f:
        f.write(json.dumps({"attempt": attempt, "pid": os.getpid(), "node": node, "start_step": start_step,
                            "resumed": resume, "time": time.time()}) + "\n")
    cfg = TrainConfig.from_dict(job["config"])
    data = load_dataset(job["capture"], **job["data_options"])
    bdata = block_scene_data(data, block)
    _write_json(run_dir / BLOCK_INFO, {"block": dataclasses.asdict(block),
                                       "block_normalization": np.asarray(bdata.normalization).tolist(),
                                       "scene_normalization": np.asarray(data.normalization).tolist()})

    def progress(trainer, finished: bool) -> None:
        _write_json(run_dir / PROGRESS, {"block": block.index, "step": int(trainer.step),
                                         "total": int(trainer.clock.total), "attempt": attempt, "pid": os.getpid(),
                                         "node": node, "faces": int(trainer.ts.num_faces), "finished": finished,
                                         "peak_rss_mb": round(_peak_rss_mb(), 1)})
        store.push(block.name)

    state = json.loads((run_dir / layout.STATE).read_text()) if (run_dir / layout.STATE).exists() else {}
    if state.get("finished") and (run_dir / layout.METRICS).exists():  # done by an earlier attempt
        metrics = json.loads((run_dir / layout.METRICS).read_text())
        steps, wall_s = int(state["step"]), float(metrics.get("wall_s", 0.0))
    else:
        trainer = Trainer(cfg, bdata, run_dir, resume=resume, show_progress=False, data_options=dict(data.options),
                          data_path=str(job["capture"]))
        progress(trainer, False)
        chunk = max(1, int(job.get("chunk_steps", 50)))
        while True:
            result = trainer.train(stop_after=trainer.step + chunk)
            done = trainer.step >= trainer.clock.total
            progress(trainer, done)
            if done:
                break
        metrics, steps, wall_s = result.metrics, int(trainer.step), float(trainer.wall_s)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    out = {"block": block.index, "name": block.name, "steps": steps, "wall_s": wall_s,
           "cpu_s": round(ru.ru_utime + ru.ru_stime, 2),
           "task_s": round(time.perf_counter() - t_start, 2), "peak_rss_mb": round(_peak_rss_mb(), 1),
           "node": node, "attempt": attempt, "start_step": start_step, "faces": metrics.get("faces"),
           "psnr": metrics.get("psnr"), "train_views": len(block.train), "test_views": len(block.test)}
    _write_json(run_dir / "block_result.json", out)
    store.push(block.name)
    return out


# ------------------------------------------------------------------------------------------------------ driver
def connect(cluster: str = "local", num_cpus: int | None = None):
    """Ray for `cluster`: 'local' starts Ray on this machine (`ray.init()`; RAY_ADDRESS, when set, names an existing
    cluster instead, as Ray's own rule), anything else is the address of an existing cluster (`ray://HOST:PORT`
    through the Ray client, or the GCS address HOST:PORT of a node of it)."""
    ray = require_ray()
    if ray.is_initialized():
        return ray
    kwargs = dict(include_dashboard=False, logging_level="WARNING", log_to_driver=False)
    if cluster == "local":
        address = os.environ.get("RAY_ADDRESS") or None
        if address is None and num_cpus is not None:
            kwargs["num_cpus"] = int(num_cpus)
    else:
        address = cluster
        kwargs.pop("include_dashboard")
    for attempt in range(LOCAL_START_ATTEMPTS):
        try:
            ray.init(address=address, **kwargs)
            return ray
        except Exception as exc:  # noqa: BLE001 - Ray raises a bare Exception for this one
            # a new local node gives its raylet a fixed 30 s to register (ray/_private/node.py): on a loaded machine
            # that is not always enough, and a second try usually is
            if address is not None or "timed out during startup" not in str(exc) or attempt + 1 == LOCAL_START_ATTEMPTS:
                raise
            ray.shutdown()
            print(f"Ray did not start in time on this machine ({exc}); trying again", file=sys.stderr, flush=True)
    return ray


def _line(name: str, p: dict | None) -> str:
    if p is None:
        return f"{name}: waiting"
    pct = 100.0 * p["step"] / max(p["total"], 1)
    where = f", node {p['node'][:8]}" if p.get("node") else ""
    again = f", attempt {p['attempt']}" if p.get("attempt", 1) > 1 else ""
    state = "done" if p.get("finished") else "training"
    return (f"{name}: {state} step {p['step']}/{p['total']} ({pct:.0f}%), {p.get('faces', 0)} faces, "
            f"{p.get('peak_rss_mb', 0):.0f} MiB{where}{again}")


def run_blocks(plan, capture: str | Path, data_options: dict, config: dict, store: str | Path,
               cluster: str = "local", cpus_per_block: int = 1, max_retries: int = 3, chunk_steps: int = 50,
               num_cpus: int | None = None, show_progress: bool = True, poll_s: float = 1.0) -> list[dict]:
    """Train every block of `plan` as a Ray task (one per block, `cpus_per_block` CPUs each, retried up to
    `max_retries` times when its worker dies) and wait for all; returns their summaries in block order. With
    show_progress, one line per block on stderr (redrawn in place on a terminal, printed when it changes
    otherwise)."""
    ray = connect(cluster, num_cpus)
    remote = ray.remote(num_cpus=cpus_per_block, max_retries=max_retries, max_calls=1)(train_block)
    st = Store(store)
    jobs = [{"capture": str(capture), "data_options": data_options, "config": config, "plan": plan.to_dict(),
             "block": b.index, "store": str(store), "chunk_steps": chunk_steps, "threads": cpus_per_block}
            for b in plan.blocks]
    refs = [remote.remote(j) for j in jobs]
    names = [b.name for b in plan.blocks]
    tty = show_progress and sys.stderr.isatty()
    shown: list[str] = []
    pending = list(refs)
    while True:
        ready, pending = ray.wait(pending, num_returns=len(pending), timeout=poll_s)
        if show_progress:
            lines = [_line(n, st.read_json(n, PROGRESS)) for n in names]
            if tty:
                if shown:
                    sys.stderr.write(f"\x1b[{len(shown)}F")
                sys.stderr.write("".join(f"\x1b[2K{line}\n" for line in lines))
                sys.stderr.flush()
            else:
                for k, line in enumerate(lines):
                    if not shown or shown[k] != line:
                        print(line, file=sys.stderr, flush=True)
            shown = lines
        if not pending:
            break
    return [ray.get(r) for r in refs]
