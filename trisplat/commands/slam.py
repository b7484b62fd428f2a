"""`trisplat slam CAPTURE --out RUN`: RGB-D SLAM with triangles: poses, map, mesh from a raw RGB-D stream."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT, flowing_help
from trisplat.slam.system import SlamConfig


@flowing_help
@dataclass
class SlamArgs:
    """Track an RGB-D stream's camera poses and map it with triangles (Triangle Splatting SLAM), online, frames in
    order; poses in the capture, if any, only score the result (ATE). Writes RUN/trajectory.txt (TUM format),
    RUN/model.ply, RUN/mesh.ply (connected), RUN/metrics.json and a checkpoint for --resume."""

    capture: tyro.conf.Positional[Path]
    """RGB-D capture folder: TUM (rgb.txt + depth.txt), 7-Scenes/3DMatch (frame-NNNNNN.color/.depth), Redwood"""
    out: Path
    """run directory (created; an existing run is never overwritten without --force)"""
    depth_scale: Annotated[float | None, NO_DEFAULT_HINT] = None
    """metres per raw depth unit (default per format: TUM 1/5000, 7-Scenes and Redwood 1/1000)"""
    resume: bool = False
    """continue from RUN/checkpoint.pt; --slam.stride, --slam.downscale, --depth-scale and the capture are refused if
    they differ from the saved run's (they number its frames); --slam.max-frames may grow"""
    force: bool = False
    """start over in a directory that holds a run (the old run is moved aside, never deleted)"""
    colour_registration: str = "auto"
    """how colour maps onto the depth camera: 'auto' measures it from the frames (colour edges against depth
    outlines; 7-Scenes' Kinect v1 colour is a 0.9x zoom of its depth) and resamples colour only where that clearly
    helps; 'off' reads colour as it is; 'SCALE,DX,DY' gives it (colour focal / depth focal, shift in pixels)"""
    slam: SlamConfig = field(default_factory=SlamConfig)


def main(argv: list[str]) -> int:
    args = tyro.cli(SlamArgs, args=argv, prog="trisplat slam", description=__doc__, config=CLI_STYLE)
    from trisplat.api import slam_from_args

    slam_from_args(args)  # the path of trisplat.api.slam
    return 0
