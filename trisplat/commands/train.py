"""`trisplat train DATA --out RUN`: optimise triangles on a capture, with checkpoints, resume and exports."""
from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from trisplat import run as layout
from trisplat.run import move_aside, prepare_run_dir  # noqa: F401  (the run rules of every command)
from trisplat.commands.style import flowing_help, help_description
from trisplat.train.config import PRESETS, TrainConfig, make_config


PROG = "trisplat train"


@flowing_help
@dataclass
class TrainArgs:
    """Train a scene: photos (or a generated scene) -> an opaque triangle mesh in OUT. Every field of the preset's
    configuration can be overridden (--steps, --minutes, --max-vertices, --sh-degree, --downscale, ...)."""

    data: tyro.conf.Positional[Path]
    """Capture folder (COLMAP, Blender/NeRF, instant-ngp transforms.json or RGB-D), or a folder of photos / a video
    without poses (posed first by `trisplat poses`, into a cache folder)."""
    out: Path
    """Run directory (created; an existing run is never overwritten without --force)."""
    preset: Literal[tuple(PRESETS)] = "default"  # type: ignore[valid-type]
    """fast (a few minutes on a laptop CPU), default, full (the paper's 30k steps), meshsplatting. Without --preset
    the defaults shown are the 'default' preset's; another preset changes them (`trisplat train --preset fast --help`
    shows its values)."""
    resume: bool = False
    """Continue a run from its last checkpoint with its saved configuration; --minutes, --checkpoint-every-s,
    --log-every, --eval-max-views, --num-renders and --eval-supersample may change, and so may --output and
    --connect-at until the run has switched to a surface (how it is finished: after a failed switch, `--resume
    --output soup` or `--resume --connect-at P`); other settings are refused."""
    force: bool = False
    """Start over in a directory that holds a run (the old run is moved aside, never deleted)."""
    quiet: bool = False
    """No progress bar or messages (errors are still printed)."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """cpu: the Numba kernels; cuda: the scene's tensors on the GPU and the numba-cuda renderer (gpu extra and a CUDA
    build of torch). With no usable GPU, --device cuda stops at once with the reason (no torch CUDA device, no
    numba-cuda), before the run folder is touched; nothing falls back to the CPU. auto: cuda when it can run here,
    else cpu. Not yet run end to end on a GPU: docs/benchmarks_gpu.md."""
    blocks: str = "1"
    """Partitioned training (issue 28): 'auto' or N cuts the scene's ground plane into blocks with overlapping
    margins, trains each block as a Ray task (needs the cluster extra: pip install -e ".[cluster]") and merges them
    into one connected surface in OUT. 1: one ordinary run."""
    cluster: str = "local"
    """Where --blocks runs: 'local' (Ray on this machine; RAY_ADDRESS, when set, names an existing cluster), or the
    address of an existing Ray cluster (ray://HOST:PORT, or a node's HOST:PORT)."""
    plan: bool = False
    """Dry run of --blocks: print the blocks, their views and their estimated memory and time, and stop."""
    shared: Annotated[str | None, tyro.conf.arg(metavar="PATH|URL")] = None
    """Folder (every Ray node must see it) or fsspec URL (s3://..., gs://...) for the blocks' run folders; default
    OUT/blocks. Given with --blocks 1, the scene is trained as one block through Ray and the merge."""
    block_margin: float = 0.2
    """Overlap margin of a block: its cell grown by this fraction of its size on every inner side."""
    block_visibility: float = 0.25
    """A view joins a block whose expanded cell holds at least this fraction of the sparse points it sees (or its
    camera)."""
    cpus_per_block: int = 1
    """CPUs (Ray num_cpus, and threads) of each block's task."""
    max_retries: int = 3
    """Ray retries of a block whose worker dies; each retry resumes from the block's checkpoint."""
    ray_cpus: Annotated[int | None, tyro.conf.arg(metavar="INT")] = None
    """--cluster local: the CPUs Ray may use on this machine; not given: all of them."""
    chunk_steps: int = 50
    """A block writes a checkpoint and its progress line every this many steps."""
    config: Annotated[TrainConfig, tyro.conf.arg(name="")] = field(default_factory=TrainConfig)


def make_train_args(data, out, preset: str = "default", resume: bool = False, force: bool = False,
                    quiet: bool = False, **overrides) -> TrainArgs:
    """TrainArgs for a preset with some configuration fields overridden (None values are ignored)."""
    return TrainArgs(data=Path(data), out=Path(out), preset=preset, resume=resume, force=force, quiet=quiet,
                     config=make_config(preset, **overrides))


def _preset_in(argv: list[str]) -> str:
    for i, a in enumerate(argv):
        if a == "--preset" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--preset="):
            return a.split("=", 1)[1]
    return "default"


# settings a resumed run takes from the command line: they change how it is run, not what is being optimised
RESUME_OVERRIDABLE = ("minutes", "checkpoint_every_s", "log_every", "eval_max_views", "num_renders",
                      "eval_supersample")
# how the run is finished: a resumed run may change them until it has switched to a connected surface (a switch that
# failed is tried again at a moved --connect-at; --output soup finishes as a soup)
RESUME_FINISHING = ("output", "connect_at")


def explicit_fields(argv: list[str]) -> set[str]:
    """Names of the TrainConfig fields given on a command line (`--lr-position 1e-3`, `--no-final-max-weight-pass`,
    `--minutes=5`)."""
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    found = set()
    for tok in argv:
        if not tok.startswith("--"):
            continue
        key = tok[2:].split("=", 1)[0].replace("-", "_")
        if key not in names and key.startswith("no_") and key[3:] in names:
            key = key[3:]
        if key in names:
            found.add(key)
    return found


def _option(name: str) -> str:
    return "--" + name.replace("_", "-")


def resume_config(out: Path, saved: dict, given: TrainConfig, explicit: set[str]) -> TrainConfig:
    """The saved configuration of a run with the explicitly given settings applied. Settings in RESUME_OVERRIDABLE
    are honoured (--minutes: the whole run, time already spent included, fits into that many minutes), and those in
    RESUME_FINISHING while the run's checkpoint has not switched to a connected surface; any other setting that
    differs from the saved one is refused: the checkpoint was optimised with the saved values."""
    fields = dataclasses.fields(TrainConfig)
    values = {**{f.name: f.default for f in fields if f.default is not dataclasses.MISSING},
              **{k: v for k, v in saved.items() if k not in ("data", "data_options")}}  # older runs lack newer keys
    if "background" in values:
        values["background"] = tuple(values["background"])
    unknown = set(values) - {f.name for f in fields}
    if unknown:
        raise ValueError(f"{out / layout.CONFIG}: unknown config keys {sorted(unknown)}")
    changed = {k for k in explicit if getattr(given, k) != values.get(k, getattr(given, k))}
    refused = sorted(changed - set(RESUME_OVERRIDABLE) - set(RESUME_FINISHING))
    if refused:
        what = ", ".join(f"{_option(k)} (saved {values[k]!r}, given {getattr(given, k)!r})" for k in refused)
        raise ValueError(f"{out}: --resume continues the saved configuration and cannot change {what}; drop these "
                         f"options, or start a new run with --force. A resumed run accepts "
                         f"{', '.join(map(_option, RESUME_OVERRIDABLE + RESUME_FINISHING))} (the last two until "
                         "the run has switched to a connected surface).")
    finishing = sorted(changed & set(RESUME_FINISHING))
    if finishing and (out / layout.CHECKPOINT).exists():
        from trisplat.train.checkpoint import load_checkpoint

        ckpt = load_checkpoint(out / layout.CHECKPOINT)
        if ckpt["extra"].get("connected"):
            raise ValueError(
                f"{out}: the run has already switched to a connected surface (its checkpoint is at step "
                f"{int(ckpt['step'])}), so {' and '.join(map(_option, finishing))} can no longer change; drop "
                f"{'them' if len(finishing) > 1 else 'it'}, or start a new run with --force")
    try:
        return TrainConfig.from_dict({**values, **{k: getattr(given, k) for k in changed}})
    except ValueError as exc:  # e.g. a saved surface run without a switch point (connect_at None, before issue 26)
        raise ValueError(f"{out / layout.CONFIG}: {exc}") from exc


def run_training(args: TrainArgs, explicit: set[str] | None = None):
    """Train (or resume) `args.out`. `explicit`: the configuration fields the user set (the command line's; by
    default those of args.config that differ from its preset)."""
    from trisplat.data import load_dataset
    from trisplat.io.atomic import atomic_write_text
    from trisplat.render.device import resolve_device
    from trisplat.train.trainer import Trainer

    out = args.out
    device = resolve_device(args.device)  # before anything in `out` changes
    prepare_run_dir(out, args.resume, args.force)
    resume = args.resume and (out / layout.CHECKPOINT).exists()
    if args.resume:
        run = layout.open_run(out)
        if explicit is None:
            preset = make_config(args.preset)
            explicit = {f.name for f in dataclasses.fields(TrainConfig)
                        if getattr(args.config, f.name) != getattr(preset, f.name)}
        cfg = resume_config(out, run.config, args.config, explicit)
        data_options = run.config.get("data_options", {})
        data_path = run.config["data"]
        if args.data.resolve() != Path(data_path).resolve():
            raise ValueError(f"{out} was trained on {data_path}, not {args.data}; --resume continues with the "
                             "run's own capture")
    else:
        cfg = args.config
        data_options = {"downscale": cfg.downscale, "background": list(cfg.background), "test_every": cfg.test_every,
                        "format": cfg.data_format}
        data_path = str(args.data.resolve())
    data = load_dataset(data_path, **data_options)  # inputs checked before anything in `out` changes
    if not resume and "background" not in (explicit or set()) and cfg.background == make_config(args.preset).background:
        bg = photo_background(data)
        if bg is not None:
            cfg = dataclasses.replace(cfg, background=bg)
            data_options["background"] = list(bg)
            if not args.quiet:
                print(f"background: the mean colour of the photos, ({', '.join(f'{c:.3f}' for c in bg)}): they have "
                      "no alpha (--background R G B to choose)", file=sys.stderr)
    if not args.quiet:
        for w in data.warnings:  # what the loader fixed, skipped or could not use, said before the long work
            print(f"warning: {w}", file=sys.stderr)
    if args.resume and not resume:
        print(f"{out}: no checkpoint yet (stopped during initialisation): starting it again with its saved "
              "configuration", file=sys.stderr)
    elif args.force and not args.resume:
        move_aside(out)
    if device.type == "cuda" and cfg.backend == "numba":  # the Numba kernels run on the CPU only
        cfg = dataclasses.replace(cfg, backend="cuda")
    trainer = Trainer(cfg, data, out, resume=resume, show_progress=not args.quiet,
                      data_options=data_options, data_path=data_path, device=device)
    updated = {**run.config, **json.loads(json.dumps(cfg.to_dict()))} if resume else None
    if resume and updated != run.config:
        atomic_write_text(out / layout.CONFIG, json.dumps(updated, indent=2))
    return trainer.train()


def check_cheap_options(args: TrainArgs) -> None:
    """What can be checked in a moment, before the long work (posing plain photos by structure from motion, loading
    the capture): --device, --out's overwrite and resume rules, the step count and time budget, and the options the
    capture is loaded with. run_training checks them again (it has other callers)."""
    from trisplat.data.options import LoadOptions
    from trisplat.render.device import resolve_device

    cfg = args.config
    resolve_device(args.device)
    if cfg.steps < 1:
        raise ValueError(f"--steps must be at least 1, got {cfg.steps}")
    if cfg.minutes is not None and not cfg.minutes > 0:
        raise ValueError(f"--minutes must be > 0, got {cfg.minutes}")
    if not args.resume:  # a resumed run loads its capture with its saved options
        LoadOptions(downscale=cfg.downscale, background=cfg.background, test_every=cfg.test_every,
                    format=cfg.data_format)
    prepare_run_dir(args.out, args.resume, args.force)


def pose_plain_photos(args: TrainArgs) -> TrainArgs:
    """A folder of photos without poses (or a video) is posed by `trisplat poses` first, into a cache folder
    outside it (trisplat.sfm.cache); the run then trains on that capture."""
    from trisplat.data.capture import is_plain_image_folder
    from trisplat.sfm import is_video

    if not (is_video(args.data) or is_plain_image_folder(args.data)):
        return args
    from dataclasses import replace as _replace

    from trisplat.sfm.cache import cache_folder, posed_capture

    if args.resume:  # the run continues on the capture it was started with
        return _replace(args, data=cache_folder(args.data))
    return _replace(args, data=posed_capture(args.data, progress=not args.quiet))


# --minutes without --downscale: the training resolution follows the budget. About this many pixels per training
# image per minute of budget keep a CPU run at several thousand steps (lego, 400x400 = 160k px, trains at full size
# for 14 minutes and more; bonsai's 800x533 photos get half size at 30 minutes, fox's 1080x1920 a quarter)
PIXELS_PER_BUDGET_MINUTE = 12_000


def budget_downscale(width: int, height: int, minutes: float) -> int:
    """The smallest downscale (1, 2, 4, 8) whose images have at most PIXELS_PER_BUDGET_MINUTE x minutes pixels."""
    for factor in (1, 2, 4):
        if (width / factor) * (height / factor) <= PIXELS_PER_BUDGET_MINUTE * minutes:
            return factor
    return 8


BACKGROUND_SAMPLE_PHOTOS = 16  # training photos averaged for the background colour of a capture without alpha


def photo_background(data) -> tuple[float, float, float] | None:
    """For a capture whose photos have no alpha (real photos of a scene): the mean colour of (up to
    BACKGROUND_SAMPLE_PHOTOS of) its training photos, as the colour behind the triangles. White is not the background
    of a real photo: through a soft, half-transparent soup it showed as a bright haze the triangles had to hide.
    None for captures with alpha (their ground truth is composited over the configured background)."""
    train = [int(i) for i in data.train_indices]
    if not train or data.load_alpha(train[0]) is not None:
        return None
    import numpy as np

    pick = train[:: max(1, len(train) // BACKGROUND_SAMPLE_PHOTOS)][:BACKGROUND_SAMPLE_PHOTOS]
    mean = np.mean([np.asarray(data.load_image(i), dtype=np.float64).reshape(-1, 3).mean(0) for i in pick], axis=0)
    return tuple(round(float(c), 4) for c in mean)


def choose_downscale(args: TrainArgs, explicit: set[str]) -> TrainArgs:
    """--minutes given, --downscale not (and not resuming): pick the training resolution from the time budget and
    say so."""
    cfg = args.config
    if args.resume or "downscale" in explicit or not cfg.minutes:
        return args
    from trisplat.data import load_dataset

    probe = load_dataset(args.data, prepare="lazy", test_every=0, format=cfg.data_format)
    cam = probe.cameras[0]
    factor = budget_downscale(cam.width, cam.height, cfg.minutes)
    if factor != cfg.downscale:
        print(f"--minutes {cfg.minutes:g}: training at 1/{factor} of the photos' size ({cam.width // factor}x"
              f"{cam.height // factor} of {cam.width}x{cam.height}) to fit the budget (--downscale N to choose)",
              file=sys.stderr, flush=True)
        args = dataclasses.replace(args, config=dataclasses.replace(cfg, downscale=factor))
    return args


def result_shape(m: dict) -> str:
    """What a finished run's mesh is, for its final line, from its metrics.json: one connected surface, or a soup
    and why (asked for with --output soup, the switch failed or was given up, or the run ended before its switch).
    A surface that came out in several pieces says how many, and the largest one's share of the faces."""
    if m.get("connected"):
        mesh = m.get("mesh") or {}
        pieces = int(mesh.get("connected_components", 1) or 1)
        shape = (f"a connected surface in {pieces} pieces (the largest holds "
                 f"{100 * float(mesh.get('largest_component_fraction', 0.0)):.0f}% of the faces)" if pieces > 1
                 else "one connected surface")
        layers = m.get("psnr_by_layer") or {}
        if layers:  # a real capture: how much of what the test views show is that one surface
            shape += f", showing {100 * layers.get('surface', {}).get('pixels', 0.0):.0f}% of the test pixels"
            far = layers.get("far_field", {}).get("pixels", 0.0)
            if far:
                shape += f" (a far-field soup of independent triangles {100 * far:.0f}%)"
        return shape
    failure = m.get("switch_failure") or {}
    error = str(failure.get("error", "")).splitlines()[0][:160] if failure else ""
    failed = (f"the switch to a surface failed at step {failure['step']} ({error})" if failure.get("step") is not None
              else "the switch to a surface failed or was given up")
    if m.get("output") == "soup":
        return ("a triangle soup, as --output soup asked" + (f" after {failed}" if m.get("switch_failed") else ""))
    if m.get("switch_failed"):
        return f"a triangle soup, NOT a connected surface: {failed}"
    return (f"a triangle soup, NOT a connected surface: the run ended before its switch point (--connect-at "
            f"{m.get('connect_at')})")


def main(argv: list[str]) -> int:
    preset = _preset_in(argv)
    default = TrainArgs(data=tyro.MISSING, out=tyro.MISSING, preset=preset,  # type: ignore[arg-type]
                        config=make_config(preset) if preset in PRESETS else TrainConfig())
    # no DisallowNone: `--connect-at None` is meaningful (TrainConfig gives its optional fields plain metavars); no
    # FlagCreatePairsOff: a preset may turn a flag either way (`--no-final-max-weight-pass`, `--final-max-weight-pass`)
    args = tyro.cli(TrainArgs, args=argv, default=default, description=help_description(TrainArgs.__doc__), prog=PROG,
                    config=(tyro.conf.OmitArgPrefixes, tyro.conf.HelptextFromCommentsOff))
    from trisplat.blocks.train import blocks_requested

    if blocks_requested(args.blocks, args.shared) or args.plan:  # partitioned training (trisplat.blocks); --blocks 1: one run
        return _train_blocks(args, argv)
    from trisplat.api import train_from_args

    try:  # the path of trisplat.api.train: cheap checks, photos posed, resolution chosen, run_training
        run = train_from_args(args, explicit_fields(argv))
    except FileExistsError as exc:
        print(f"trisplat train: {exc}", file=sys.stderr)
        return 1
    for line in final_lines(run.metrics, run.wall_s, run.path):
        print(line)
    return 0  # the run finished and wrote its files; whether to trust them is metrics.json's `health`


def _train_blocks(args: TrainArgs, argv: list[str]) -> int:
    """--blocks auto|N (or --plan): trisplat.blocks.train; without Ray installed it stops at once, naming the
    install command."""
    from trisplat.blocks.run_ray import MissingRay
    from trisplat.blocks.train import train_in_blocks

    try:
        result = train_in_blocks(args, explicit_fields(argv))
    except MissingRay as exc:
        print(f"trisplat train: {exc}", file=sys.stderr)
        return 2
    except FileExistsError as exc:
        print(f"trisplat train: {exc}", file=sys.stderr)
        return 1
    for line in final_lines(result.metrics, result.wall_s, result.run_dir):
        print(line)
    return 0


def final_lines(m: dict, wall_s: float, run_dir) -> list[str]:
    """What a finished run says last: its verdict, the scores of what the user gets, the shape of the result, and
    one line per problem or recovery (metrics.json's `health`)."""
    if not m:
        return []
    lp = f", LPIPS {m['lpips']:.3f}" if m.get("lpips") is not None else ""
    health = m.get("health") or {"ok": True, "problems": []}
    what = "done" if health["ok"] else "finished, but the result is NOT trustworthy"
    shape = result_shape(m)
    soup_far = int(m.get("far_field_faces") or 0) - int(m.get("background_faces") or 0)
    far = (f" + a far-field soup of {soup_far} independent faces beyond the inner box" if soup_far > 0 else "") + (
        f" + a background sphere of {m['background_faces']} faces" if m.get("background_faces") else "")
    cov = f", {100 * m['coverage']:.1f}% of test pixels covered" if m.get("coverage") is not None else ""
    # what a user gets is the file: its score comes first when there is one (an unlit file cannot hold the
    # model's view-dependent colour; lego at 30 min: model 27.4 dB, its SH band 0 alone 26.6, mesh.glb 26.0)
    score = (f"mesh.glb {m['file_psnr']:.2f} dB as a glTF viewer shows it (the model: {m['psnr']:.2f} dB)"
             if m.get("file_psnr") is not None else f"test PSNR {m['psnr']:.2f} dB (hard)")
    lines = [f"{what} in {wall_s / 60:.1f} min: {score}, SSIM {m['ssim']:.3f}{lp}, {m['faces']} faces, "
             f"{m['vertices']} vertices ({shape}{far}{cov}) -> {run_dir}"]
    if m.get("psnr_exposure_matched") is not None:
        lines.append(f"  with each test photo's exposure taken from its neighbours in the photo order (RUN/exposure.json)"
                     f": the model {m['psnr_exposure_matched']:.2f} dB")
    for g in (m.get("intrinsics") or {}).get("groups", []):
        dx, dy = g["principal_point_shift_px"]
        lines.append(f"  intrinsics refined ({g['cameras']} cameras): focal length {g['fx_before']:.1f} -> "
                     f"{g['fx_after']:.1f} px ({g['focal_change_percent']:+.2f}%), principal point moved by "
                     f"({dx:+.2f}, {dy:+.2f}) px (RUN/intrinsics.json)")
    lines += [f"  problem: {p}" for p in health["problems"]]
    lines += [f"  warning: {w}" for w in health.get("warnings", [])]
    lines += [f"  recovered: {note}" for note in health.get("recoveries", [])]
    return lines
