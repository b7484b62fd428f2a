"""`trisplat bench poses`: `trisplat poses` on a capture's photos, scored against the capture's own COLMAP model.

Reported: registered fraction, camera-centre error after a similarity alignment onto the reference model (mean and
max, as % of the reference camera-path extent: the largest distance between two reference centres), reprojection
error, points, and wall / CPU time per stage with the load average (the machine may be shared).
"""
from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from trisplat.commands.style import CLI_STYLE
from trisplat.bench.common import BenchTable, peak_rss_mb

DEFAULT_CAPTURE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "fox"


@dataclass
class PosesBenchArgs:
    """Structure from motion on the photos of a COLMAP capture, compared with its model."""

    capture: Path = DEFAULT_CAPTURE
    """capture with images/ and a reference model in sparse/0 (default ../shared/data/fox)"""
    camera_models: list[str] = field(default_factory=lambda: ["auto"])
    """one run per COLMAP camera model"""
    out: Path = Path("bench_results")
    """folder for poses.json and poses.md; the captures go to OUT/poses_<model>/"""
    keep: bool = True
    """keep the computed captures (to train on them)"""


def main(argv: list[str]) -> int:
    args = tyro.cli(PosesBenchArgs, args=argv, prog="trisplat bench poses", description=__doc__, config=CLI_STYLE)
    from trisplat.data.colmap import find_model_dir
    from trisplat.sfm import PosesOptions, camera_centre_error, run_poses
    from trisplat.sfm.align import centres_from_model

    images = args.capture / "images"
    ref_dir = find_model_dir(args.capture)
    if not images.is_dir() or ref_dir is None:
        raise FileNotFoundError(f"{args.capture}: need images/ and a COLMAP model (sparse/0) to compare against")
    reference = centres_from_model(ref_dir)
    table = BenchTable("poses", [
        "capture", "camera model", "images", "registered", "registered %", "centre error mean %", "centre error max %",
        "reproj px", "points", "features s", "matching s", "mapping s", "undistort s", "total s", "cpu s",
        "load before", "load after", "peak RSS MiB"])
    for model in args.camera_models:
        out = args.out / f"poses_{model}"
        if out.exists():
            shutil.rmtree(out)
        load0 = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), time.process_time()
        report = run_poses(images, out, PosesOptions(camera_model=model))
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        load1 = os.getloadavg()[0]
        err = camera_centre_error(centres_from_model(out / "sparse" / "0"), reference)
        t = report.times
        row = [args.capture.name, model, report.n_input, len(report.registered), 100 * report.registered_fraction,
               100 * err.mean_fraction, 100 * err.max_fraction, report.mean_reprojection_error_px, report.points,
               t.get("features"), t.get("matching"), t.get("mapping"), t.get("undistortion"), wall, cpu, load0,
               load1, peak_rss_mb()]
        table.add(*row)
        print(dict(zip(table.columns, row)), flush=True)
        if not args.keep:
            shutil.rmtree(out)
    table.notes.append("Centre error: camera centres aligned onto the reference model by the least-squares "
                       "similarity (Umeyama), as % of the reference camera-path extent (largest distance between two "
                       "reference centres). Times are wall seconds; 'cpu s' is this process's CPU time (all threads); "
                       "load = 1-minute load average before and after (the machine is shared).")
    md = table.write(args.out, "trisplat bench poses " + " ".join(argv))
    print(md.read_text())
    return 0
