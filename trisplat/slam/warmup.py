"""Compile SLAM's kernels before the clock starts: a few frames of a tiny synthetic capture through `run_slam`.

Numba compiles each kernel on its first call and caches it (next to the source, once per install). Inside a run, that
first call costs about 50 s on 2 cores: the first frame of a fresh install takes 40 s, and `--slam.realtime` would
then drop every frame it is late for. `trisplat slam` runs this warm-up first, as `trisplat train` compiles its
renderer before its budget starts, and reports the seconds apart (metrics.json `compile_seconds`). With the kernels
already cached it takes a few seconds."""
from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from pathlib import Path

from trisplat.slam.system import SlamConfig

WIDTH, HEIGHT, FRAMES = 80, 60, 8


def write_capture(root: Path, width: int = WIDTH, height: int = HEIGHT, frames: int = FRAMES) -> Path:
    """`frames` frames of the built-in demo scene (trisplat.synth.scenes.demo_mesh) ray-cast along a short arc that
    ends where it began, in the 7-Scenes layout, into `root`."""
    from trisplat.synth.orbit import intrinsics, look_at
    from trisplat.synth.rgbd_room import write_noiseless_sequence
    from trisplat.synth.scenes import demo_mesh

    path = []
    for k in range(frames):
        th = math.radians(-30 + 8 * math.sin(math.pi * k / max(frames - 1, 1)))  # out and back
        path.append(look_at((2.3 * math.cos(th), 2.3 * math.sin(th), 1.1), (0.0, 0.0, 0.25)))
    return write_noiseless_sequence(root, demo_mesh(seed=0), path, intrinsics(width, height, 60.0), width, height)


def warm_up(cfg: SlamConfig, log=print) -> float:
    """Run `cfg`'s code paths (tracking, mapping, loop detection, the final refinement, the mesh, the held-out
    scoring) on a tiny synthetic capture in a temporary folder, so that their kernels are compiled (or loaded from
    the cache). Returns the seconds taken. Never fails the user's run: an error is reported and the kernels then
    compile where they are first used."""
    from trisplat.data.rgbd_stream import open_stream
    from trisplat.slam.system import run_slam

    t0 = time.perf_counter()
    small = dataclasses.replace(
        cfg, downscale=1, max_frames=0, stride=1, start=0, checkpoint_every=0, realtime=False, keyframe_every=2,
        final_iters=min(cfg.final_iters, 4), final_ba_rounds=min(cfg.final_ba_rounds, 1), final_ba_map_iters=2,
        eval_every=1, mesh_resolution=64,
        mapping=dataclasses.replace(cfg.mapping, iters=2, first_iters=3))
    try:
        with tempfile.TemporaryDirectory(prefix="trisplat-warmup-") as tmp:
            stream = open_stream(write_capture(Path(tmp) / "capture"))
            run_slam(stream, Path(tmp) / "run", small, log=lambda *a, **k: None)
    except Exception as exc:  # noqa: BLE001 - a warm-up that fails must not cost the user's run
        log(f"warning: the kernel warm-up failed ({type(exc).__name__}: {exc}); kernels compile during the run "
            "instead, and its frames/s count that time", flush=True)
    return time.perf_counter() - t0
