"""`trisplat bench blocks`: partitioned training on local Ray against one run, on a synthetic street.

1. Quality at equal CPU: a street of `objects` objects along 40 m (trisplat.synth.street) trained as `blocks` blocks
   of `block_steps` steps each on local Ray, merged, against one ordinary run of blocks x block_steps steps. Both
   are separate processes, single-threaded (Ray's tasks get one CPU each); the CPU seconds of each (every process
   involved: the driver with its merge, and each block's Ray worker) are measured and reported beside the scores:
   test PSNR of the opaque mesh, Chamfer against the true geometry (gt_mesh.ply, both meshes in the capture's
   frame), the largest piece's share of the faces and the non-manifold edges.
2. Memory at a fixed block size: streets of 2, 4 and 8 objects (`memory_objects`), cut into objects / 2 blocks
   (about two objects, 11 m, per block), the same block_steps; the peak resident memory of every block's process
   (a fresh Ray worker per block), the merge's process, and the block's views and faces.

Each training process is a `trisplat train` command line (printed in the notes), so every number can be redone.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from trisplat.bench.common import BenchTable
from trisplat.commands.style import CLI_STYLE


@dataclass
class BlocksBenchArgs:
    """Partitioned training on local Ray vs one run on a synthetic street (quality at equal CPU, memory per block)."""

    out: Path = Path("bench_results")
    """folder for blocks.json and blocks.md (and the captures and runs, under blocks_work/)"""
    objects: int = 8
    blocks: int = 4
    block_steps: int = 300
    """training steps of each block; the single run gets blocks x block_steps"""
    views_per_object: int = 8
    width: int = 96
    height: int = 64
    memory_objects: list[int] = field(default_factory=lambda: [2, 4, 8])
    """street lengths (objects) of the memory part, each cut into objects / 2 blocks"""
    ray_cpus: int = 1
    """CPUs local Ray may use (1: the blocks run one after the other, single-threaded)"""
    preset: str = "fast"


def _start(capture: Path, out: Path, args: BlocksBenchArgs, steps: int, blocks: int | None) -> dict:
    """Start one `trisplat train` process (single-threaded; with `blocks`, partitioned on local Ray, one CPU)."""
    import os

    cmd = [sys.executable, "-m", "trisplat", "train", str(capture), "--out", str(out), "--preset", args.preset,
           "--steps", str(steps), "--texture-size", "0", "--num-renders", "1", "--quiet", "--force"]
    if blocks is not None:
        cmd += ["--blocks", str(blocks), "--ray-cpus", str(args.ray_cpus), "--cpus-per-block", "1"]
        if blocks == 1:  # one block through Ray and the merge, not the ordinary run
            cmd += ["--shared", str(out / "blocks")]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "OMP_WAIT_POLICY": "PASSIVE"}
    env.pop("RAY_ADDRESS", None)
    out.parent.mkdir(parents=True, exist_ok=True)
    log = open(out.parent / f"{out.name}.log", "w")
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=log)
    shown = " ".join(c if c != sys.executable else "python" for c in cmd)
    return {"proc": proc, "log": log, "t0": time.perf_counter(), "run": out,
            "command": shown.replace(" --quiet", "").replace(" --force", "")}


def _wait(job: dict) -> dict:
    """Wait for a process of _start: its metrics, wall seconds, CPU seconds and peak memory (its own, os.wait4)."""
    import os

    _, status, ru = os.wait4(job["proc"].pid, 0)
    job["proc"].returncode = os.waitstatus_to_exitcode(status)
    job["log"].close()
    wall = time.perf_counter() - job["t0"]
    if job["proc"].returncode != 0:
        log = (job["run"].parent / f"{job['run'].name}.log").read_text()
        raise RuntimeError(f"{job['command']} failed ({job['proc'].returncode}):\n{log[-3000:]}")
    m = json.loads((job["run"] / "metrics.json").read_text())
    return {"metrics": m, "wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime, "peak_mb": ru.ru_maxrss / 1024.0,
            "run": job["run"], "command": job["command"]}


def _chamfer(run: Path, capture: Path) -> float:
    from trisplat.eval.geometry import compare_surfaces, load_surface

    return compare_surfaces(load_surface(run / "mesh.ply"), load_surface(capture / "gt_mesh.ply")).chamfer


def main(argv: list[str]) -> int:
    args = tyro.cli(BlocksBenchArgs, args=argv, prog="trisplat bench blocks", description=__doc__, config=CLI_STYLE)
    from trisplat.synth.street import write_street_scene

    work = Path(args.out) / "blocks_work"
    work.mkdir(parents=True, exist_ok=True)

    def street(n: int) -> Path:
        cap = work / f"street{n}"
        if not (cap / "synth.json").exists():
            write_street_scene(cap, n_objects=n, views_per_object=args.views_per_object, width=args.width,
                               height=args.height)
        return cap

    table = BenchTable("blocks", ["run", "objects", "blocks", "steps", "CPU s", "wall s", "test PSNR dB",
                                  "Chamfer m", "largest piece", "non-manifold edges", "faces",
                                  "peak MiB per block (max)", "views per block", "merge s", "driver + merge peak MiB"])
    cap = street(args.objects)
    sizes = {n: street(n) for n in args.memory_objects}
    # every run at once, each single-threaded (Ray: one CPU per instance, so its blocks run one after the other):
    # CPU seconds and peak memory are per process and do not depend on what else runs; wall times do
    jobs = {"single": _start(cap, work / "single", args, args.blocks * args.block_steps, None),
            args.objects: _start(cap, work / f"blocks{args.objects}", args, args.block_steps, args.blocks)}
    for n in args.memory_objects:
        if n not in jobs:
            jobs[n] = _start(sizes[n], work / f"blocks{n}", args, args.block_steps, max(1, n // 2))
    done = {k: _wait(j) for k, j in jobs.items()}
    single, runs = done.pop("single"), done
    single_peak = single["peak_mb"]
    for res, name, nblocks in ((single, "single run", 1),
                               (runs[args.objects], f"{args.blocks} blocks, local Ray", args.blocks)):
        m = res["metrics"]
        b = m.get("blocks")
        block_cpu = sum(r["cpu_s"] for r in b["results"]) if b else 0.0
        views = (round(sum(r["train_views"] for r in b["results"]) / len(b["results"]), 1) if b
                 else len(list((cap / "images").iterdir())) - int(m["test_views"]))
        table.add(name, args.objects, nblocks, args.block_steps * nblocks, round(res["cpu_s"] + block_cpu, 1),
                  round(res["wall_s"], 1), round(m["psnr"], 2), round(_chamfer(res["run"], cap), 4),
                  round(m["mesh"]["largest_component_fraction"], 4), m["mesh"]["non_manifold_edges"], m["faces"],
                  round(max(r["peak_rss_mb"] for r in b["results"])) if b else round(single_peak), views,
                  round(b["merge_s"] + b["finish_s"], 1) if b else None, round(res["peak_mb"]) if b else None)
    for n in args.memory_objects:
        m = runs[n]["metrics"]
        b = m["blocks"]
        table.add(f"memory, {b['count']} blocks", n, b["count"], args.block_steps * b["count"],
                  round(runs[n]["cpu_s"] + sum(r["cpu_s"] for r in b["results"]), 1), round(runs[n]["wall_s"], 1),
                  round(m["psnr"], 2), round(_chamfer(work / f"blocks{n}", sizes[n]), 4),
                  round(m["mesh"]["largest_component_fraction"], 4), m["mesh"]["non_manifold_edges"], m["faces"],
                  round(max(r["peak_rss_mb"] for r in b["results"])),
                  round(sum(r["train_views"] for r in b["results"]) / len(b["results"]), 1),
                  round(b["merge_s"] + b["finish_s"], 1), round(runs[n]["peak_mb"]))
    per_block = runs[args.objects]["metrics"]["blocks"]["results"]
    table.notes.append("commands: " + "; ".join(sorted({single["command"]} | {r["command"] for r in runs.values()})))
    table.notes.append("per block (the comparison run): " + "; ".join(
        f"{r['name']}: {r['train_views']} train views, {r['steps']} steps, task {r['task_s']:.0f} s, CPU "
        f"{r['cpu_s']:.0f} s, training {r['wall_s']:.0f} s, peak {r['peak_rss_mb']:.0f} MiB, {r['faces']} faces"
        for r in per_block))
    table.notes.append(f"single run peak memory {single_peak:.0f} MiB (its process)")
    (work / "per_block.json").write_text(json.dumps({str(k): v["metrics"]["blocks"] for k, v in runs.items()},
                                                    indent=2))
    md = table.write(args.out, "trisplat bench blocks " + " ".join(argv))
    print(md.read_text())
    return 0
