"""`trisplat train CAPTURE --out RUN --blocks auto|N [--cluster local|ray://HOST:PORT] [--plan]`: the scene cut into
blocks (partition), one Ray task per block (run_ray), the blocks merged into RUN (merge)."""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path



@dataclass
class BlocksResult:
    """What `trisplat train --blocks` ends with (the fields final_lines reads, as TrainResult's)."""

    run_dir: Path
    wall_s: float
    metrics: dict
    plan: object = None
    blocks: list | None = None


def blocks_requested(blocks: str, shared: str | None = None) -> bool:
    """Whether the command line asks for partitioned training: --blocks other than 1, or --shared (with --blocks 1:
    the whole scene as one block, through Ray and the merge, as `trisplat bench blocks` measures it)."""
    return str(blocks).strip() != "1" or bool(shared)


def default_store(out: Path) -> Path:
    """Where the blocks' run folders go when --shared is not given: RUN/blocks."""
    return Path(out) / "blocks"


def train_in_blocks(args, explicit: set[str] | None = None) -> BlocksResult:
    """Plan (and with args.plan only print) the blocks of args.data, train them on Ray and merge them into args.out.
    args: trisplat.commands.train.TrainArgs."""
    from trisplat.blocks.partition import partition, plan_lines, resolve_count
    from trisplat.commands.train import photo_background
    from trisplat.data import load_dataset
    from trisplat.run import move_aside, prepare_run_dir

    t0 = time.perf_counter()
    if blocks_requested(args.blocks, args.shared):
        from trisplat.blocks.run_ray import require_ray

        require_ray()
    if args.resume and not args.plan:
        raise ValueError("--blocks with --resume: run the same command again without --resume (finished blocks are "
                         "kept, unfinished ones continue from their checkpoints) after moving the merged files away, "
                         "or with --force to start the merge over")
    cfg = args.config
    data_options = {"downscale": cfg.downscale, "background": list(cfg.background), "test_every": cfg.test_every,
                    "format": cfg.data_format}
    data_path = str(Path(args.data).resolve())
    data = load_dataset(data_path, **data_options)
    if "background" not in (explicit or set()):
        bg = photo_background(data)
        if bg is not None:
            cfg = dataclasses.replace(cfg, background=bg)
            data_options["background"] = list(bg)
            data = load_dataset(data_path, **data_options)
    plan = partition(data, resolve_count(args.blocks, len(data.train_indices)), args.block_margin,
                     args.block_visibility)
    lines = plan_lines(plan, data, cfg)
    if args.plan or not args.quiet:
        print("\n".join(lines), file=sys.stdout if args.plan else sys.stderr, flush=True)
    if args.plan:
        return BlocksResult(Path(args.out), time.perf_counter() - t0, {}, plan)
    store = str(args.shared) if args.shared else str(default_store(args.out))
    if args.force:
        move_aside(Path(args.out))
    elif Path(args.out).exists() and any(p.name != "blocks" for p in Path(args.out).iterdir()):
        prepare_run_dir(Path(args.out), False, False)  # says what is there
    from trisplat.blocks.merge import merge_blocks
    from trisplat.blocks.run_ray import Store, run_blocks

    results = run_blocks(plan, data_path, data_options, json.loads(json.dumps(cfg.to_dict())), store,
                         cluster=args.cluster, cpus_per_block=args.cpus_per_block, max_retries=args.max_retries,
                         chunk_steps=args.chunk_steps, num_cpus=args.ray_cpus, show_progress=not args.quiet)
    st = Store(store)
    for b in plan.blocks:
        st.pull(b.name)
    metrics = merge_blocks(plan, data, [st.local(b.name) for b in plan.blocks], Path(args.out), cfg, data_path,
                           data_options, results, show_progress=not args.quiet)
    return BlocksResult(Path(args.out), time.perf_counter() - t0, metrics, plan, results)

