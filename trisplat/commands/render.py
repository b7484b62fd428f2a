"""`trisplat render RUN --split test --out DIR`: one PNG per image of the split, named after the source image."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT, flowing_help
from trisplat.progress import progress_bar


PROG = "trisplat render"

@flowing_help
@dataclass
class RenderArgs:
    """Render a trained run's cameras (hard, opaque mesh by default) so anyone can score them with their tools."""

    run: tyro.conf.Positional[Path]
    out: Path
    """Output folder for the PNGs (existing files are not overwritten without --force)."""
    split: Literal["train", "test", "all"] = "test"
    mode: Literal["hard", "soft"] = "hard"
    """hard: z-buffer render of the final mesh; soft: the splatting renderer at the final sigma."""
    supersample: Annotated[int | None, NO_DEFAULT_HINT] = None
    """samples per pixel side (anti-aliasing, 1-4; default: the run's eval_supersample, what its metrics used)"""
    force: bool = False
    """replace PNGs that exist in the output folder"""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """cpu: the Numba kernels; cuda: the numba-cuda kernels on an NVIDIA GPU (gpu extra and a CUDA build of torch;
    without them: an error naming what is missing); auto: cuda when it can run here, else cpu"""


def render_split(args: RenderArgs) -> list[Path]:
    from trisplat.eval.views import eval_supersample, render_view, scene_on, soft_sigma
    from trisplat.run import open_run
    from trisplat.eval.report import write_png
    from trisplat.train.outputs import output_stems

    from trisplat.render.device import resolve_device

    run = open_run(args.run)
    dev = resolve_device(args.device)  # cheap checks before the model and the capture are loaded
    scene = scene_on(run.load_model()[0], dev)
    data = run.load_scene_data()
    sigma = soft_sigma(run) if args.mode == "soft" else None
    ss = eval_supersample(run) if args.supersample is None else args.supersample
    idx = {"train": data.train_indices, "test": data.test_indices, "all": range(len(data.cameras))}[args.split]
    targets = {i: args.out / f"{stem}.png" for i, stem in output_stems(data.cameras, idx).items()}
    existing = [p for p in targets.values() if p.exists()]
    if existing and not args.force:  # checked before anything is written
        raise FileExistsError(f"{existing[0]} exists{f' (and {len(existing) - 1} more)' if len(existing) > 1 else ''}"
                              "; pass --force to overwrite")
    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    for i, path in progress_bar(list(targets.items()), desc=f"render {args.split}"):
        cam = data.cameras[i]
        write_png(render_view(scene, cam, args.mode, data.background, sigma, supersample=ss), path)
        written.append(path)
    return written


def main(argv: list[str]) -> int:
    args = tyro.cli(RenderArgs, args=argv, description=RenderArgs.__doc__, prog=PROG, config=CLI_STYLE)
    try:
        paths = render_split(args)
    except FileExistsError as exc:
        print(f"trisplat render: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {len(paths)} images to {args.out}")
    return 0
