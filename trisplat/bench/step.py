"""`trisplat bench step RUN`: one training step of a run, stage by stage, at 1, 2, ... N threads (issue 50).

Each phase starts from the run's own checkpoint in a copy (the run is not touched): `soup` from
checkpoints/soup.pt (the soup just before the switch), `surface` from checkpoints/last.pt (the connected surface
at the end). After `warmup` untimed steps, `steps` steps are timed at each thread count (numba's and torch's set
together), each step split into its stages (trisplat.timing): the soft render's kernels forward and backward, the SH
colours forward and backward, the photometric loss, the geometric terms (the fused normal term apart), the rest of
the backward pass (torch's autograd engine and the small ops' gradients), the optimizer, the finiteness checks, the
per-face statistics, loading the photo, and what is left (Python between them). Medians over the steps. The
speed-up is the 1-thread step time over the N-thread one; the serial fraction is Amdahl's, s = (N / speed-up - 1) /
(N - 1): the share of the 1-thread step that more threads do not shorten. The pruning and densification events of
the soup (every few hundred steps) are not part of a step. Writes step.json and step.md.

Beside the wall time, each row gives the CPU time of all the process's threads per step and that of the thread
running the step, and the load average is printed and kept: other jobs on a shared machine stretch the wall times
(a 2-thread row among them says little). The "CPU speed-up bound" is the 1-thread step's CPU time over the N-thread
step's main-thread CPU time: the speed-up if the other threads never kept the main one waiting. Parallel loops
split their work by count, so it holds on a busy machine too; it is optimistic (waits at the end of unevenly
finishing loops and a shared memory bus are not in it: on bonsai_c4 with e5e7d3e, 1.72 where 1.57 was measured
quiet with the same step code).
`--clock cpu` times the step and its stages in CPU time of the thread that runs it (time.thread_time): at 1 thread
(numba's and torch's work then run in that thread) that is the stage's work, which compares two versions of the
code on a busy machine better than wall time does.
"""
from __future__ import annotations

import os
import shutil
import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from trisplat.bench.common import BenchTable
from trisplat.commands.style import CLI_STYLE

# stages reported, in order: (column, the stage names of trisplat.timing summed into it)
STAGES = (
    ("render fwd", ("render_forward",)),
    ("render bwd", ("render_backward",)),
    ("SH fwd+bwd", ("sh_forward", "sh_backward")),
    ("photometric loss", ("loss",)),
    ("terms", ("terms",)),
    ("normal term", ("normal_term",)),
    ("optimizer", ("optimizer",)),
    ("checks", ("checks",)),
    ("statistics", ("statistics",)),
    ("photo", ("photo",)),
)


@dataclass
class StepArgs:
    """A training step of a run, stage by stage, at 1..N threads: speed-up and serial fraction."""

    run: Annotated[Path, tyro.conf.Positional]
    """run folder written by `trisplat train` (with checkpoints/soup.pt and/or checkpoints/last.pt)"""
    threads: list[int] = field(default_factory=list)
    """thread counts to time (default: 1 .. the machine's CPUs)"""
    steps: int = 20
    """timed steps per phase and thread count"""
    warmup: int = 3
    """untimed steps before them"""
    phases: list[str] = field(default_factory=lambda: ["soup", "surface"])
    """'soup' (checkpoints/soup.pt) and/or 'surface' (checkpoints/last.pt)"""
    out: Path = Path("bench_results")
    """folder for step.json and step.md"""
    clock: str = "wall"
    """'wall', or 'cpu': the step and its stages in CPU time of the thread that runs the step (time.thread_time), for
    comparing 1-thread runs on a shared machine (at more threads it leaves out the other threads' work: no speed-up
    or serial fraction then)"""


def _trainer(run_dir: Path, checkpoint: Path, tmp: Path):
    """A Trainer resumed from `checkpoint` in a copy of the run's configuration under `tmp` (quiet)."""
    import dataclasses

    from trisplat.run import open_run
    from trisplat.train.config import TrainConfig
    from trisplat.train.trainer import Trainer

    (tmp / "checkpoints").mkdir(parents=True)
    shutil.copy(run_dir / "config.json", tmp / "config.json")
    shutil.copy(checkpoint, tmp / "checkpoints" / "last.pt")
    run = open_run(tmp)
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    cfg = TrainConfig(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in run.config.items() if k in names})
    data = open_run(run_dir).load_scene_data()
    return Trainer(cfg, data, tmp, resume=True, show_progress=False, data_options=run.config.get("data_options"),
                   data_path=run.config["data"])


def time_steps(trainer, steps: int, warmup: int, clock=time.perf_counter) -> tuple[float, dict[str, float]]:
    """Median seconds of a whole step and of each stage (seconds; a stage a step did not run counts 0), and under
    "cpu" the median CPU seconds of the process's threads per step (at 1 thread the step's work, which other jobs on
    a shared machine stretch less than its wall time)."""
    from trisplat.timing import recording

    totals, cpus, mains, per = [], [], [], []
    for k in range(warmup + steps):
        with recording(clock) as rec:
            t0, c0, m0 = clock(), time.process_time(), time.thread_time()
            res = trainer.train_step()
            dt, dc, dm = clock() - t0, time.process_time() - c0, time.thread_time() - m0
        if not res["ok"]:
            raise RuntimeError(f"step {trainer.step} of the benchmark failed (NaN/Inf)")
        trainer.step += 1
        if k >= warmup:
            totals.append(dt)
            cpus.append(dc)
            mains.append(dm)
            per.append(dict(rec))
    names = {n for d in per for n in d}
    return statistics.median(totals), {n: statistics.median(d.get(n, 0.0) for d in per) for n in names} | {
        "cpu": statistics.median(cpus), "cpu_main": statistics.median(mains)}


def serial_fraction(speedup: float, threads: int) -> float | None:
    """Amdahl's serial fraction from the speed-up on `threads` threads (None for one thread)."""
    if threads <= 1:
        return None
    return (threads / speedup - 1.0) / (threads - 1.0)


def main(argv: list[str]) -> int:
    args = tyro.cli(StepArgs, args=argv, prog="trisplat bench step", description=__doc__, config=CLI_STYLE)
    import numba
    import torch

    threads = args.threads or list(range(1, (os.cpu_count() or 1) + 1))
    if args.clock not in ("wall", "cpu"):
        raise SystemExit(f"trisplat bench step: --clock {args.clock!r}: 'wall' or 'cpu'")
    clock = time.thread_time if args.clock == "cpu" else time.perf_counter
    files = {"soup": args.run / "checkpoints" / "soup.pt", "surface": args.run / "checkpoints" / "last.pt"}
    for ph in args.phases:
        if ph not in files:
            raise SystemExit(f"trisplat bench step: unknown phase {ph!r} (known: soup, surface)")
        if not files[ph].is_file():
            raise SystemExit(f"trisplat bench step: {files[ph]} not found (the {ph} phase needs it)")
    cols = ["phase", "faces", "pixels", "threads", "step ms", "step CPU ms", "main thread CPU ms", "speed-up",
            "serial fraction", "CPU speed-up bound"]
    cols += [f"{c} ms" for c, _ in STAGES] + ["autograd rest ms", "Python rest ms"]
    table = BenchTable("step", cols)
    for ph in args.phases:
        with tempfile.TemporaryDirectory(prefix="trisplat-bench-step-") as tmp:
            trainer = _trainer(args.run, files[ph], Path(tmp))
            trainer.warm_up_kernels()
            start = trainer.step
            cam = trainer.data.cameras[int(trainer.data.train_indices[0])]
            base = base_cpu = None
            for t in threads:
                numba.set_num_threads(min(t, numba.config.NUMBA_NUM_THREADS))
                torch.set_num_threads(t)
                trainer.step = start  # the same views at every thread count
                total, st = time_steps(trainer, args.steps, args.warmup, clock)
                base = total if base is None else base
                base_cpu = st["cpu"] if base_cpu is None else base_cpu
                speed = base / total
                bound = base_cpu / st["cpu_main"] if threads[0] == 1 else None
                staged = [1e3 * sum(st.get(n, 0.0) for n in names) for _, names in STAGES]
                inner = sum(st.get(n, 0.0) for n in ("render_backward", "sh_backward", "normal_term"))
                autograd_rest = 1e3 * max(st.get("backward", 0.0) - inner, 0.0)
                python_rest = 1e3 * total - sum(staged) - autograd_rest
                sf = serial_fraction(speed, t) if t == threads[-1] and threads[0] == 1 else None
                if args.clock == "cpu" and t > 1:
                    speed, sf = float("nan"), None  # (the other threads' work is not in this thread's clock)
                table.add(ph, trainer.ts.num_faces, cam.width * cam.height, t, round(1e3 * total, 1),
                          round(1e3 * st["cpu"], 1), round(1e3 * st["cpu_main"], 1), round(speed, 3),
                          None if sf is None else round(sf, 3), None if bound is None else round(bound, 3),
                          *[round(x, 1) for x in staged],
                          round(autograd_rest, 1), round(python_rest, 1))
                print(f"{ph}: {t} thread(s): {1e3 * total:.0f} ms/step (x{speed:.2f}; CPU {1e3 * st['cpu']:.0f} ms; "
                      f"load average {os.getloadavg()[0]:.2f})", flush=True)
    layer = numba.threading_layer()
    if args.clock == "cpu":
        table.notes.append("--clock cpu: times are CPU time of the thread running the step (time.thread_time)")
    table.notes.append(f"numba threading layer: {layer}; OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')};"
                       f" {args.steps} timed steps after {args.warmup} untimed, medians; serial fraction (Amdahl) "
                       f"from the first and last thread counts when the first is 1")
    table.started["numba_threading_layer"] = layer
    table.started["load_average_end"] = list(os.getloadavg())  # other jobs on the machine stretch the wall times
    md = table.write(args.out, "trisplat bench step " + " ".join(argv))
    print(md.read_text())
    return 0
