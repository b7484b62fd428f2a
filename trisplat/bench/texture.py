"""`trisplat bench texture --run RUN`: what texturing a finished run costs (trisplat.texture), stage by stage.

The run's surface (decimated to --faces when given) gets its UV atlas (xatlas), the least-squares problem of the
training photos (rasterising every view, one row per covered pixel) and its conjugate-gradient solve, as
`trisplat export --texture-size` does. Reported per stage: wall seconds and the process's CPU seconds (all its
threads: on a machine shared with other jobs the CPU seconds of a one-thread run are what it would take alone);
the process's resident memory before texturing (model and photos loaded) and its peak above that (psutil samples
every 0.2 s).

Regulariser weights: with --holdout K every K-th training view is left out of the fit and the texture is scored
(PSNR, rendered as the glTF specification defines it, trisplat.eval.spec_render) on those held-out TRAINING views,
once per --smoothness x --prior pair (the atlas and the problem are built once); --test-views N also scores the
first N test views (for the record: weights are chosen on the held-out training views only).
"""
from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro

from trisplat.bench.common import BenchTable, peak_rss_mb
from trisplat.bench.switch_memory import _RssSampler
from trisplat.commands.style import CLI_STYLE


@dataclass
class TextureArgs:
    """Texturing time and memory on a finished run; regulariser weights scored on held-out training views."""

    run: Path
    """run folder written by `trisplat train` (its model and its capture's photos are read, nothing is written)"""
    faces: int | None = None
    """decimate the surface to about this many faces first (default: the run's surface as it is)"""
    texture_size: int = 2048
    """texture side, texels (capped as export caps it: at most the photos' pixel count)"""
    max_views: int | None = None
    """fit on only the first N training views (a quicker look; default: all)"""
    holdout: int = 0
    """leave every K-th training view out of the fit and score the texture on those (0: fit on all)"""
    smoothness: list[float] = field(default_factory=lambda: [])
    """neighbour-term weights to try (default: trisplat.texture.fit.SMOOTHNESS)"""
    prior: list[float] = field(default_factory=lambda: [])
    """prior-term weights to try (default: trisplat.texture.fit.PRIOR)"""
    test_views: int = 0
    """also score the first N test views (not for choosing weights)"""
    tolerance: float | None = None
    """conjugate-gradient relative residual (default: trisplat.texture.fit.CG_TOLERANCE)"""
    asset: bool = False
    """time what a run does instead: trisplat.texture.asset.build_asset, i.e. the vertex colours fitted and the
    texture fitted from one pass over the training views, then the held-out choice between them (no stages, no
    weights)"""
    out: Path = Path("bench_results")
    """folder for texture.json and texture.md"""


def _score(positions, faces, atlas, image, data, indices, near) -> float | None:
    """Mean PSNR of the textured mesh, written as a GLB and rendered per the glTF specification, on `indices`."""
    if not indices:
        return None
    from trisplat.eval.image_metrics import psnr
    from trisplat.eval.spec_render import prepare_asset, render_asset
    from trisplat.io import export_mesh
    from trisplat.io.gltf import TextureMap, read_glb

    with tempfile.TemporaryDirectory(prefix="trisplat-bench-texture-") as tmp:
        path = Path(tmp) / "mesh.glb"
        export_mesh(path, positions, faces, None, up=None,
                    texture=TextureMap(atlas.uv.astype(np.float32), atlas.uv_faces, image))
        asset = prepare_asset(read_glb(path))
    scores = []
    for i in indices:
        cam = data.cameras[i]
        rgb = render_asset(asset, cam.world_to_camera, cam.K, cam.width, cam.height, data.background, 2, near)
        scores.append(psnr(np.asarray(data.load_image(i), np.float32), rgb))
    return float(np.mean(scores))


def main(argv: list[str]) -> int:
    args = tyro.cli(TextureArgs, args=argv, prog="trisplat bench texture", description=__doc__, config=CLI_STYLE)
    import numba

    from trisplat.run import open_run
    from trisplat.scene.sh import sh_dc_to_rgb
    from trisplat.texture import fit as tfit
    from trisplat.texture.asset import decimate, photo_texture_cap
    from trisplat.texture.atlas import build_atlas

    run = open_run(args.run)
    scene, _ = run.load_model()
    data = run.load_scene_data()
    near = float(run.config.get("near", 0.01))
    supersample = int(run.config.get("eval_supersample", 2))
    if args.asset:
        return _bench_asset(args, argv, scene, data, supersample, near)
    positions = scene.positions.detach().cpu().numpy()
    faces = scene.faces.detach().cpu().numpy().astype(np.int64)
    colors = sh_dc_to_rgb(scene.sh[:, 0].detach().cpu()).clamp(0, 1).numpy()
    if args.faces is not None:
        positions, faces, colors = decimate(positions, faces, colors, args.faces)
    train = [int(i) for i in data.train_indices][: args.max_views]
    held = train[:: args.holdout] if args.holdout > 0 else []
    fit_on = [i for i in train if i not in set(held)]
    test = [int(i) for i in data.test_indices][: args.test_views]
    size = min(int(args.texture_size), photo_texture_cap(data))
    smooth = args.smoothness or [tfit.SMOOTHNESS]
    priors = args.prior or [tfit.PRIOR]
    tol = tfit.CG_TOLERANCE if args.tolerance is None else args.tolerance

    table = BenchTable("texture", [
        "faces", "texture", "views", "texels", "threads", "atlas s", "rows s", "solve s", "iterations", "total s",
        "atlas CPU s", "rows CPU s", "solve CPU s", "total CPU s",
        "RSS before MiB", "peak above MiB", "smoothness", "prior", "held-out train PSNR", "test PSNR"])
    rss_before = _RssSampler()._proc.memory_info().rss / 2**20
    sampler = _RssSampler().start()
    t0, c0 = time.perf_counter(), time.process_time()
    atlas = build_atlas(positions, faces, size)
    t_atlas, c_atlas = time.perf_counter() - t0, time.process_time() - c0
    print(f"atlas: {t_atlas:.1f} s, CPU {c_atlas:.1f} s ({len(faces)} faces, {size}x{size})", flush=True)
    t1, c1 = time.perf_counter(), time.process_time()
    views = ((data.cameras[i], np.asarray(data.load_image(i), np.float32)) for i in fit_on)
    problem = tfit.assemble(positions, faces, atlas, views, data.background, colors, supersample, near)
    t_rows, c_rows = time.perf_counter() - t1, time.process_time() - c1
    print(f"rows: {t_rows:.1f} s, CPU {c_rows:.1f} s ({problem.rows.shape[0]} pixels of {problem.views} views, "
          f"{problem.rows.nnz} weights, {problem.rows.shape[1]} texels)", flush=True)
    first = True
    for sw in smooth:
        for pw in priors:
            t2, c2 = time.perf_counter(), time.process_time()
            x, its, rel = tfit.solve(problem, sw, pw, tfit.CG_ITERATIONS, tol)
            image = tfit.texture_image(problem, x)
            t_solve, c_solve = time.perf_counter() - t2, time.process_time() - c2
            peak = sampler.peak if first else None
            if first:
                peak = sampler.stop()
            total = t_atlas + t_rows + t_solve
            print(f"solve (smoothness {sw:g}, prior {pw:g}): {t_solve:.1f} s, CPU {c_solve:.1f} s, {its} iterations, "
                  f"residual {rel:.2e}"
                  + (f"; texturing {total:.1f} s, CPU {c_atlas + c_rows + c_solve:.1f} s, peak "
                     f"{peak - rss_before:.0f} MiB above {rss_before:.0f}"
                     if first else ""), flush=True)
            ph = _score(positions, faces, atlas, image, data, held, near)
            pt = _score(positions, faces, atlas, image, data, test, near)
            if ph is not None or pt is not None:
                print(f"  held-out training views: {ph}, test views: {pt}", flush=True)
            table.add(len(faces), size, problem.views, problem.rows.shape[1], numba.get_num_threads(),
                      round(t_atlas, 1), round(t_rows, 1), round(t_solve, 1), its, round(total, 1),
                      round(c_atlas, 1), round(c_rows, 1), round(c_solve, 1), round(c_atlas + c_rows + c_solve, 1),
                      round(rss_before), round(peak - rss_before) if first else None, sw, pw,
                      None if ph is None else round(ph, 3), None if pt is None else round(pt, 3))
            first = False
    table.notes.append(
        f"Run {args.run}; {problem.views} training views fitted"
        + (f", {len(held)} held out (every {args.holdout}th)" if held else "")
        + (f", {len(test)} test views scored" if test else "")
        + f"; {supersample}x{supersample} samples per pixel; CG tolerance {tol:g}. 'peak above': the process's peak "
          f"resident memory during atlas, rows and the first solve, above its resident memory before (model and "
          f"capture loaded); process peak {peak_rss_mb():.0f} MiB.")
    return _write(table, args, argv)


def _bench_asset(args: TextureArgs, argv: list[str], scene, data, supersample: int, near: float) -> int:
    """--asset: build_asset's seconds (wall, CPU) and peak memory above the loaded run, with what it chose."""
    import numba

    from trisplat.texture.asset import build_asset

    table = BenchTable("texture_asset", [
        "faces", "texture", "threads", "total s", "total CPU s", "vertex fit s", "atlas s", "rows s (shared)",
        "texture solve s", "RSS before MiB", "peak above MiB", "vertex colours", "file colours"])
    rss_before = _RssSampler()._proc.memory_info().rss / 2**20
    sampler = _RssSampler().start()
    t0, c0 = time.perf_counter(), time.process_time()
    asset = build_asset(scene, data, args.texture_size, args.faces, supersample, near)
    total, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = sampler.stop()
    tr, cr = asset.texture_report or {}, asset.colour_report or {}
    chosen = tr.get("chosen", "texture" if asset.texture is not None else "vertex colours")
    print(f"build_asset: {total:.1f} s, CPU {cpu:.1f} s, peak {peak - rss_before:.0f} MiB above {rss_before:.0f}; "
          f"vertex colours {cr.get('chosen', 'fitted')}, the files get {chosen}", flush=True)
    table.add(len(asset.faces), tr.get("size"), numba.get_num_threads(), round(total, 1), round(cpu, 1),
              None if cr.get("fit_seconds") is None else round(cr["fit_seconds"], 1),
              None if tr.get("atlas_seconds") is None else round(tr["atlas_seconds"], 1),
              None if tr.get("fit_seconds_raster") is None else round(tr["fit_seconds_raster"], 1),
              None if tr.get("fit_seconds_solve") is None else round(tr["fit_seconds_solve"], 1),
              round(rss_before), round(peak - rss_before), cr.get("chosen", "fitted"), chosen)
    table.notes.append(
        f"Run {args.run}: build_asset as a run's end calls it (vertex colours and texture fitted from one pass over "
        f"the training views less every 10th, then scored on those to choose); {supersample}x{supersample} samples "
        f"per pixel. 'vertex fit s': the vertex colours' solve (their rows come from the shared pass, 'rows s'). "
        f"'peak above': resident memory above the loaded run's; process peak {peak_rss_mb():.0f} MiB.")
    return _write(table, args, argv)


def _write(table: BenchTable, args: TextureArgs, argv: list[str]) -> int:
    path = table.write(args.out, "trisplat bench texture " + " ".join(argv))
    print(table.markdown())
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))
