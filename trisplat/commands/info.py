"""`trisplat info PATH`: a readable summary of a capture (format, cameras, splits, points, bounds, warnings)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from trisplat.commands.style import CLI_STYLE, flowing_help


@flowing_help
@dataclass
class InfoConfig:
    """Summarise a capture folder as trisplat reads it (no images are processed)."""

    path: tyro.conf.Positional[Path]
    """capture folder (COLMAP, Blender/NeRF, instant-ngp, RGB-D), a transforms.json, or a COLMAP sparse/0"""
    downscale: int = 1
    """1, 2, 4 or 8: report resolutions and intrinsics at this downscale"""
    test_every: int = 8
    """hold out every n-th image for test when the capture has no split (0: none)"""
    data_format: Annotated[Literal["auto", "colmap", "blender", "ngp", "rgbd"],
                           tyro.conf.arg(aliases=("--format",))] = "auto"
    """capture format, as `trisplat train --data-format` (auto: a COLMAP model with points before a
    transforms.json; the summary names the other formats found)"""


def _fmt_vec(v) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in np.asarray(v).ravel()) + ")"


def describe(data) -> str:
    """The summary text for a loaded SceneData."""
    cams = data.cameras
    lines = [f"capture     {data.root}", f"format      {data.format}"]
    models = Counter(c.extras.get("source_model", "PINHOLE") for c in cams)
    undist = sum(bool(c.extras.get("undistorted")) for c in cams)
    model_txt = ", ".join(f"{m} x{n}" for m, n in models.most_common())
    lines.append(f"cameras     {len(cams)} ({model_txt}; {undist} undistorted to pinhole)")
    sizes = Counter((c.width, c.height) for c in cams)
    lines.append("resolution  " + ", ".join(f"{w}x{h} x{n}" for (w, h), n in sizes.most_common()))
    src = Counter(tuple(c.extras.get("source_size", (c.width, c.height))) for c in cams)
    lines.append("source      " + ", ".join(f"{w}x{h} x{n}" for (w, h), n in src.most_common()))
    f = np.array([[c.K[0, 0], c.K[1, 1]] for c in cams])
    lines.append(
        f"focal       fx {f[:, 0].min():.1f}..{f[:, 0].max():.1f}  fy {f[:, 1].min():.1f}..{f[:, 1].max():.1f} px"
    )
    lines.append(f"split       {len(data.train_indices)} train, {len(data.test_indices)} test")
    if data.points is not None:
        lines.append(f"points      {len(data.points)}")
    else:
        lines.append("points      none (random initialisation in the bounds)")
    if data.format == "rgbd":
        lines.append(f"depth       scale {cams[0].depth_scale:g} capture units per raw value")
    s = data.scale
    centre = -data.normalization[:3, 3] / s
    lines.append(
        f"normalise   rule {data.options.get('normalize')}: scale {s:.6g} per capture unit, "
        f"capture centre {_fmt_vec(centre)}"
    )
    if data.bounds is not None:
        lines.append(f"bounds      {_fmt_vec(data.bounds[0])} .. {_fmt_vec(data.bounds[1])} (normalised)")
    lines.append(f"radius      cameras {data.scene_radius:.4g}, content {data.bounds_radius:.4g} (normalised)")
    lines.append(f"background  {_fmt_vec(data.background)}")
    for w in data.warnings:
        lines.append(f"warning     {w}")
    return "\n".join(lines)


def describe_stream(stream, registration) -> str:
    """The summary text for an RGB-D stream that only `trisplat slam` reads (7-Scenes, ETH3D, ScanNet, or TUM
    without poses), with the colour-to-depth registration `trisplat slam` would use."""
    K = stream.K
    n_ref = sum(f.reference_c2w is not None for f in stream.frames)
    lines = [f"capture     {stream.root}",
             f"format      {stream.format} RGB-D stream (read by `trisplat slam`; `trisplat train` does not read this layout)",
             f"frames      {len(stream)} ({n_ref} with a reference pose)",
             f"resolution  {stream.width}x{stream.height}",
             f"focal       fx {K[0, 0]:.1f}  fy {K[1, 1]:.1f} px, principal point {_fmt_vec(K[:2, 2])} (centres at +0.5)",
             f"depth       scale {stream.depth_scale:g} metres per raw value",
             f"colour      (trisplat slam's --colour-registration auto) {registration.describe(K)}"]
    lines += [f"warning     {w}" for w in stream.warnings]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    cfg = tyro.cli(InfoConfig, args=argv, prog="trisplat info", description=__doc__, config=CLI_STYLE)
    from trisplat.data import load_dataset
    from trisplat.data.rgbd_stream import detect_stream_format

    try:
        data = load_dataset(cfg.path, downscale=cfg.downscale, test_every=cfg.test_every, format=cfg.data_format,
                            prepare="lazy")
    except (ValueError, FileNotFoundError):
        if cfg.data_format != "auto" or not Path(cfg.path).is_dir() or detect_stream_format(cfg.path) is None:
            raise
        from trisplat.data.colour_registration import estimate_colour_registration
        from trisplat.data.rgbd_stream import open_stream

        stream = open_stream(cfg.path)
        print(describe_stream(stream, estimate_colour_registration(stream)))
        return 0
    print(describe(data))
    return 0
