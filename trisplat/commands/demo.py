"""`trisplat demo`: generate the built-in scene, train it with the fast preset, write an HTML page of the result."""
from __future__ import annotations

import dataclasses
import html
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT, flowing_help, help_description

from trisplat import run as layout


PROG = "trisplat demo"

@flowing_help
@dataclass
class DemoArgs:
    """Generate a procedural coloured scene (rendered by trimesh's ray caster, an independent renderer), train it
    with the fast preset and write DIR/index.html: ground truth vs the final opaque mesh, metrics, mesh files.
    Running it again resumes an interrupted demo and re-uses a finished one (use --force to start over)."""

    out: Path = Path("trisplat_demo")
    """Output folder: scene/ (generated photos), run/ (the trained run), index.html."""
    minutes: Annotated[float | None, NO_DEFAULT_HINT] = None
    """Fit training into this many minutes of wall time (default: the fast preset's step count)."""
    steps: Annotated[int | None, NO_DEFAULT_HINT] = None
    """Training steps (default: the fast preset's)."""
    views: int = 48
    """Training views to generate (plus 8 test views)."""
    size: int = 128
    """Image width and height in pixels."""
    force: bool = False
    """Start over: the previous output folder is moved aside (never deleted)."""
    quiet: bool = False
    """No progress bars or messages, only the final line."""


def generate_scene(out: Path, views: int, size: int, quiet: bool) -> Path:
    from trisplat.synth import demo_mesh, write_blender_scene

    scene_dir = out / "scene"
    if (scene_dir / "synth.json").exists() and (scene_dir / "transforms_test.json").exists():
        return scene_dir
    if not quiet:
        print(f"generating the demo scene ({views} + 8 views at {size}x{size}) in {scene_dir} ...", file=sys.stderr)
    return write_blender_scene(scene_dir, demo_mesh(), n_train=views, n_test=8, width=size, height=size,
                               progress=not quiet)


def write_page(out: Path, run_dir: Path) -> Path:
    """index.html: per test view ground truth | opaque mesh render, the metrics and links to the mesh files."""
    metrics = json.loads((run_dir / layout.METRICS).read_text())
    renders = sorted((run_dir / layout.RENDERS).glob("*.png"))
    scene_test = out / "scene" / "test"
    rows = []
    for r in renders:
        gt = scene_test / r.name
        rows.append(f"<tr><td>{html.escape(r.stem)}</td><td><img src='{gt.relative_to(out)}'></td>"
                    f"<td><img src='{r.relative_to(out)}'></td></tr>")
    ss = metrics.get("supersample", 1)
    fmt = lambda v, d: "-" if v is None else f"{v:.{d}f}"  # noqa: E731
    files = " ".join(f"<a href='run/mesh.{s}'>mesh.{s}</a>" for s in ("ply", "obj", "glb"))
    page = f"""<!doctype html><html><head><meta charset='utf-8'><title>trisplat demo</title>
<style>body{{font-family:sans-serif;margin:2em}} img{{width:256px;image-rendering:pixelated}}
td{{padding:4px;text-align:center}}</style></head><body>
<h1>trisplat demo</h1>
<p>A procedural scene rendered by trimesh's ray caster (ground truth), reconstructed as an opaque triangle mesh by
differentiable triangle splatting, shown here with an ordinary z-buffer render of the final mesh
({ss}x{ss} samples per pixel, as the ground truth).</p>
<p>Test views: PSNR {fmt(metrics.get('psnr'), 2)} dB, SSIM {fmt(metrics.get('ssim'), 3)},
LPIPS {fmt(metrics.get('lpips'), 3)} (soft render PSNR {fmt(metrics.get('soft_psnr'), 2)} dB; one sample per pixel:
PSNR {fmt(metrics.get('psnr_1spp', metrics.get('psnr')), 2)} dB);
{metrics['faces']} faces, {metrics['vertices']} vertices; trained {metrics['steps']} steps in
{metrics['wall_s'] / 60:.1f} min.</p>
<p>Mesh files: {files} &middot; full report: <a href='run/eval_test/report.html'>run/eval_test/report.html</a>
&middot; view it in 3D: <code>trisplat view {html.escape(str(run_dir))}</code></p>
<table><tr><th>view</th><th>ground truth</th><th>opaque mesh</th></tr>{''.join(rows)}</table>
</body></html>"""
    path = out / "index.html"
    path.write_text(page)
    return path


def main(argv: list[str]) -> int:
    args = tyro.cli(DemoArgs, args=argv, description=help_description(DemoArgs.__doc__), prog=PROG, config=CLI_STYLE)
    from trisplat.commands.train import check_cheap_options, make_train_args, run_training

    out = args.out
    run_dir = out / "run"
    # the training options are checked before the scene is generated (a minute of ray casting)
    train_args = make_train_args(out / "scene", run_dir, "fast", quiet=args.quiet, minutes=args.minutes,
                                 steps=args.steps)
    check_cheap_options(dataclasses.replace(train_args, force=True))
    if args.force and out.exists():
        from trisplat.commands.train import move_aside

        move_aside(out)
    scene_dir = generate_scene(out, args.views, args.size, args.quiet)
    state = layout.open_run(run_dir).state if (run_dir / layout.CONFIG).exists() else None
    if state is None or not state.get("finished"):
        resume = state is not None and (run_dir / layout.CHECKPOINT).exists()
        if resume and not args.quiet:
            print(f"resuming the interrupted demo run in {run_dir}", file=sys.stderr)
        run_training(dataclasses.replace(train_args, data=scene_dir, resume=resume,
                                         force=state is not None and not resume))
    page = write_page(out, run_dir)
    m = json.loads((run_dir / layout.METRICS).read_text())
    print(f"demo done: test PSNR {m['psnr']:.2f} dB with {m['faces']} opaque faces. Open {page.resolve()}")
    return 0
