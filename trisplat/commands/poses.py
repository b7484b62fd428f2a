"""`trisplat poses PHOTOS_OR_VIDEO --out CAPTURE`: camera poses by structure from motion (pycolmap, CPU)."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

from trisplat.commands.style import CLI_STYLE, flowing_help, help_description


@flowing_help
@dataclass
class PosesArgs:
    """Estimate camera poses for a folder of photos or a video (SIFT, matching, global mapping, undistortion)
    and write an ordinary COLMAP capture (OUT/images, OUT/sparse/0) that `trisplat train OUT` reads."""

    source: tyro.conf.Positional[Path]
    """a folder of photos (its own files only, not subfolders) or a video file (.mp4, .mov, .mkv, ...)"""
    out: Path
    """capture folder to write (must be empty, or an earlier `trisplat poses` result with --force)"""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """auto: exhaustive up to --exhaustive-max photos; sequential (+ retrieval loop closure) for more and videos"""
    exhaustive_max: int = 100
    overlap: int = 10
    """sequential matching: successors each image is matched with"""
    loop_neighbours: int = 5
    """sequential matching: most similar images elsewhere in the sequence each image is matched with (0: none)"""
    camera_model: Literal["auto", "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = "auto"
    """COLMAP camera model fitted; auto: OPENCV, or SIMPLE_RADIAL (one focal, one radial term) when the OPENCV fit
    gives non-square pixels"""
    camera_mode: Literal["single", "per-image"] = "single"
    """single: one camera shared by all images (they must have one size); per-image: one camera each"""
    max_image_size: int = 3200
    """longest side (pixels) SIFT runs at"""
    max_features: int = 8192
    min_registered: float = 0.5
    """fail when fewer than this fraction of the images register"""
    rate: float = 2.0
    """video: frames kept per second (the sharpest of each interval)"""
    max_frames: int = 300
    """video: at most this many frames (the rate is lowered to fit)"""
    undistort: bool = True
    """write undistorted pinhole images (else the originals and the distorted model)"""
    seed: int = 0
    mapper: Literal["global", "incremental"] = "global"
    """COLMAP's global mapper (GLOMAP; the incremental one maps again when it registers too few), or its incremental
    mapper (slower, and on bonsai's photos its result changed between machines)"""
    force: bool = False
    """replace an earlier `trisplat poses` result in OUT"""
    quiet: bool = False
    """no progress bars"""
    verbose: bool = False
    """show COLMAP's own log"""


def main(argv: list[str]) -> int:
    args = tyro.cli(PosesArgs, args=argv, prog="trisplat poses", description=help_description(PosesArgs.__doc__), config=CLI_STYLE)
    from trisplat.sfm import PosesOptions, run_poses

    opts = PosesOptions(matcher=args.matcher, exhaustive_max=args.exhaustive_max, overlap=args.overlap,
                        loop_neighbours=args.loop_neighbours, camera_model=args.camera_model,
                        camera_mode=args.camera_mode, max_image_size=args.max_image_size,
                        max_features=args.max_features, min_registered=args.min_registered, video_rate=args.rate,
                        max_frames=args.max_frames, undistort=args.undistort, seed=args.seed, force=args.force,
                        verbose=args.verbose, mapper=args.mapper)
    try:
        report = run_poses(args.source, args.out, opts, progress=not args.quiet)
    except FileExistsError as exc:
        print(f"trisplat poses: error: {exc}", file=sys.stderr)
        return 1
    print(report.summary())
    return 0
