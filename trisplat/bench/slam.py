"""`trisplat bench slam`: `trisplat slam` beside two Open3D pipelines on the same frames: RGB-D odometry + TSDF, and
Open3D's dense SLAM (frame-to-model tracking on a voxel block grid).

All methods run on the same frames of one RGB-D capture (every --stride-th from --start, the first --max-frames, at
1/--downscale): `trisplat slam` through its Python entry (trisplat.commands.slam.main, options after `--` are passed
to it verbatim, e.g. `-- --slam.final-iters 50`), then trisplat.slam.open3d_baseline (`open3d`: frame-to-frame hybrid
RGB-D odometry chained into a trajectory, TSDF fusion into a mesh), then trisplat.slam.open3d_dense_slam
(`open3d-slam`: open3d.t.pipelines.slam at its dense-SLAM example's defaults; --open3d-slam-downscale runs it at
another resolution, e.g. 1 for the full frames the example reads). Reported per method: ATE RMSE / max (camera centres,
rigid SE(3) alignment onto the reference poses, no scale), wall time of the whole method (loading, tracking,
mapping, meshing, trisplat's held-out evaluation and its kernel warm-up), frames/s (= frames / wall) and without
the scoring and the warm-up, mesh faces and the share of faces in
the largest vertex-connected piece (trisplat.mesh.stats), the Chamfer distance (trisplat.eval.geometry: mean of the
two mean nearest-sample distances, metres) and F-score between the method's mesh and a TSDF mesh fused from the same
frames at the reference poses (each mesh moved into the reference's world by the rigid alignment of its whole
poses, rotations included, onto the reference poses), and
trisplat's held-out PSNR / depth L1 (from its metrics.json: its map rendered at frames that were not keyframes),
and the PSNR of each method's mesh.ply at the same frames (vertex colours shown unlit, as a viewer shows them: what
a user of the mesh gets; trisplat.slam.system.evaluate_mesh_frames). The 1-minute load average before and after each method
is recorded: the machine may be shared.

Open3D is a benchmark dependency (`pip install open3d-cpu`, or the `bench` extra); this suite stops at once, naming
it, when it is not installed. The whole 400-frame sequence at half resolution takes tens of minutes on 2 cores, so
`trisplat bench all` does not run this suite.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from trisplat.commands.style import CLI_STYLE
from trisplat.bench.common import BenchTable

DEFAULT_CAPTURE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "sevenscenes_rgbd"
METHODS = ("trisplat", "open3d", "open3d-slam")
COLUMNS = ["method", "frames", "resolution", "ATE RMSE m", "ATE max m", "RPE m/s", "RPE deg/s", "wall s", "frames/s",
           "scoring s", "compile s", "frames/s without scoring or compiling", "mesh faces", "largest component",
           "Chamfer m", "accuracy m",
           "completeness m", "F-score", "held-out PSNR", "held-out PSNR without exposure",
           "held-out depth L1 m", "held-out PSNR of mesh.ply", "held-out PSNR of mesh.ply at the frames' exposure",
           "load before", "load after"]  # fmt: skip


@dataclass
class SlamBenchArgs:
    """`trisplat slam` and the Open3D RGB-D odometry + TSDF baseline on the same frames of an RGB-D capture with
    reference poses: ATE, time, mesh connectivity and Chamfer to a reference-pose TSDF mesh. Options after `--` go
    to `trisplat slam` unchanged (e.g. `-- --slam.final-iters 50`). Not part of `trisplat bench all` (long)."""

    capture: Path = DEFAULT_CAPTURE
    """RGB-D capture with reference poses (default ../shared/data/sevenscenes_rgbd: 400 frames 640x480)"""
    out: Path = Path("bench_results")
    """folder for slam.json, slam.md, slam_details.json; the runs go to OUT/slam_trisplat/ and OUT/slam_open3d/, the
    reference mesh to OUT/slam_reference_tsdf.ply"""
    downscale: int = 2
    """process frames at 1/downscale of the capture's resolution (both methods; trisplat's --slam.downscale)"""
    max_frames: int = 0
    """use the first this-many selected frames (0 = all; trisplat's --slam.max-frames)"""
    stride: int = 1
    """use every stride-th frame (trisplat's --slam.stride)"""
    start: int = 0
    """first capture frame used (trisplat's --slam.start): a later stretch of a capture, scored on its own"""
    depth_scale: float | None = None
    """metres per raw depth unit (default per capture format)"""
    methods: tuple[str, ...] = METHODS
    """which to run: trisplat, open3d (odometry + TSDF), open3d-slam (Open3D's dense SLAM)"""
    open3d_slam_downscale: int | None = None
    """resolution of Open3D's dense SLAM: 1/this of the capture's (default: --downscale; its example reads full
    frames)"""
    chamfer_samples: int = 200_000
    """points sampled on each mesh for the Chamfer distance and F-score"""
    fps: float = 30.0
    """frame rate of a capture without timestamps (7-Scenes, ScanNet, Redwood): frame i is at i / fps seconds for
    the RPE per second"""
    tsdf_voxel: float = 0.01
    """TSDF voxel edge (metres) of the Open3D baseline's mesh and of the reference mesh (truncation 4 voxels; at most
    400 voxels a side, coarser beyond)"""
    colour_registration: str = "auto"
    """colour onto the depth camera ('auto', 'off' or 'SCALE,DX,DY', as `trisplat slam`'s): trisplat measures it
    itself inside its run; Open3D and the held-out scoring get the bench's measurement, so all see the same colour"""


def _split(argv: list[str]) -> tuple[list[str], list[str]]:
    """(bench options, options passed through to `trisplat slam`): the latter are what follows a lone `--`."""
    if "--" in argv:
        k = argv.index("--")
        return argv[:k], argv[k + 1:]
    return argv, []


def _aligned_mesh(mesh_path: Path, est_c2w: np.ndarray, ref_c2w: np.ndarray):
    """The mesh as a trisplat.eval.geometry.Surface moved into the reference's world by the rigid alignment of its
    whole poses onto the reference's (trisplat.sfm.align.align_poses), or None when
    the file has no faces."""
    from trisplat.eval.geometry import Surface, load_surface
    from trisplat.sfm.align import align_poses

    if not mesh_path.is_file():
        return None
    try:
        s = load_surface(mesh_path)
    except ValueError:  # an empty mesh (no vertices)
        return None
    if not s.is_mesh:
        return None
    R, t = align_poses(est_c2w, ref_c2w)
    return Surface(np.asarray(s.vertices, np.float64) @ R.T + t, np.asarray(s.faces))


def score_run(run_dir: Path, ref_c2w: list, reference, samples: int, stamps: list[float] | None = None) -> dict:
    """ATE, RPE per second (stamps in seconds, one per frame), mesh statistics and geometry metrics of one method's
    RUN (trajectory.txt + mesh.ply)."""
    from trisplat.eval.geometry import compare_surfaces
    from trisplat.mesh.stats import mesh_statistics
    from trisplat.slam.trajectory import ate_rmse, read_tum_trajectory, rpe_per_second

    _, est = read_tum_trajectory(run_dir / "trajectory.txt")
    if len(est) != len(ref_c2w):
        raise ValueError(f"{run_dir / 'trajectory.txt'}: {len(est)} poses for {len(ref_c2w)} frames")
    have = [k for k, r in enumerate(ref_c2w) if r is not None]
    out: dict = {"ate": None, "rpe": None, "mesh": None, "geometry": None}
    if len(have) < 3:
        return out
    e, r = est[have], np.array([ref_c2w[k] for k in have])
    rmse, err = ate_rmse(e, r)
    out["ate"] = {"rmse_m": rmse, "max_m": float(err.max()), "median_m": float(np.median(err)), "frames": len(have)}
    if stamps is not None:
        out["rpe"] = rpe_per_second(e, r, np.array([stamps[k] for k in have]))
    surf = _aligned_mesh(run_dir / "mesh.ply", e, r)
    if surf is None:
        out["mesh"] = {"num_faces": 0, "largest_component_fraction": None}
        return out
    out["mesh"] = mesh_statistics(surf.vertices, surf.faces, check_self_intersections=False).to_dict()
    if reference is not None and surf.is_mesh:
        out["geometry"] = compare_surfaces(surf, reference, samples=samples).to_dict()
    return out


def mesh_psnr(run_dir: Path, stream, ids: list[int], frames: list[int], downscale: int) -> dict:
    """PSNR of a method's mesh.ply (sRGB vertex colours, shown unlit as a viewer shows them) at its own tracked
    poses of the given frames (numbers in the benchmark's sequence): the picture a user of its mesh gets."""
    import trimesh

    from trisplat.slam.system import evaluate_mesh_frames
    from trisplat.slam.trajectory import read_tum_trajectory

    path = run_dir / "mesh.ply"
    if not path.is_file():
        return {"frames": 0, "psnr": None, "ssim": None}
    mesh = trimesh.load(path, process=False)
    cols = getattr(mesh.visual, "vertex_colors", None)
    if cols is None or len(cols) != len(mesh.vertices):
        raise ValueError(f"{path}: no vertex colours to score")
    _, est = read_tum_trajectory(run_dir / "trajectory.txt")
    return evaluate_mesh_frames(stream, np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                np.asarray(cols, np.float64)[:, :3] / 255.0, list(est), ids, frames, downscale)


def _run_trisplat(args: SlamBenchArgs, run_dir: Path, extra: list[str]) -> dict:
    from trisplat.commands.slam import main as slam_main

    argv = [str(args.capture), "--out", str(run_dir), "--slam.downscale", str(args.downscale),
            "--slam.max-frames", str(args.max_frames), "--slam.stride", str(args.stride),
            "--slam.start", str(args.start),
            "--colour-registration", args.colour_registration]
    if args.depth_scale is not None:
        argv += ["--depth-scale", str(args.depth_scale)]
    argv += extra
    print("trisplat slam " + " ".join(argv), flush=True)
    rc = slam_main(argv)
    if rc:
        raise RuntimeError(f"trisplat slam exited with status {rc}")
    return json.loads((run_dir / "metrics.json").read_text())


def _run_open3d(args: SlamBenchArgs, run_dir: Path, registration: str) -> dict:
    from trisplat.slam import open3d_baseline

    return open3d_baseline.run(args.capture, run_dir, args.downscale, args.max_frames, reference_mesh=False,
                               stride=args.stride, depth_scale=args.depth_scale, log=lambda *a, **k: None,
                               voxel_m=args.tsdf_voxel, colour_registration=registration, start=args.start)


def _run_open3d_slam(args: SlamBenchArgs, run_dir: Path, registration: str) -> dict:
    from trisplat.slam import open3d_dense_slam

    down = args.open3d_slam_downscale or args.downscale
    return open3d_dense_slam.run(args.capture, run_dir, down, args.max_frames, args.stride, args.start,
                                 args.depth_scale, log=lambda *a, **k: None, colour_registration=registration)


RUNNERS = {"open3d": _run_open3d, "open3d-slam": _run_open3d_slam}


def main(argv: list[str]) -> int:
    own, extra = _split(list(argv))
    args = tyro.cli(SlamBenchArgs, args=own, prog="trisplat bench slam", description=__doc__, config=CLI_STYLE)
    unknown = [m for m in args.methods if m not in METHODS]
    if unknown or not args.methods:
        raise ValueError(f"--methods: {unknown or 'none given'}; choose from {', '.join(METHODS)}")
    from trisplat.slam import open3d_baseline

    try:  # the reference mesh and the baseline need Open3D: stop before the long trisplat run, not after it
        open3d_baseline._o3d()
    except ImportError as exc:
        print(f"trisplat bench slam: {exc}", file=sys.stderr)
        return 2
    from trisplat.data.colour_registration import apply_colour_registration
    from trisplat.data.rgbd_stream import open_stream
    from trisplat.eval.geometry import load_surface

    stream = open_stream(args.capture, depth_scale=args.depth_scale)
    reg = apply_colour_registration(stream, args.colour_registration)  # the held-out photos and Open3D's colour
    print(reg.describe(stream.K), flush=True)
    registration = reg.as_option()
    if args.open3d_slam_downscale is not None and args.open3d_slam_downscale < 1:
        raise ValueError(f"--open3d-slam-downscale must be a positive integer, got {args.open3d_slam_downscale}")
    ids = open3d_baseline.frame_ids(len(stream), args.max_frames, args.stride, args.start)
    ref_c2w = [stream.frames[i].reference_c2w for i in ids]
    stamps = [stream.frames[i].stamp if stream.frames[i].stamp is not None else i / args.fps for i in ids]
    if sum(r is not None for r in ref_c2w) < 3:
        raise ValueError(f"{args.capture}: fewer than 3 of the {len(ids)} selected frames have reference poses: "
                         "nothing to score against")
    W, H = stream.size_at(args.downscale)
    args.out.mkdir(parents=True, exist_ok=True)

    print(f"reference: TSDF of {len(ids)} frames at the reference poses", flush=True)
    ref_ply = args.out / "slam_reference_tsdf.ply"
    ref_info = open3d_baseline.reference_tsdf_mesh(args.capture, ref_ply, args.downscale, args.max_frames,
                                                   args.stride, args.depth_scale, args.tsdf_voxel, args.start)
    reference = load_surface(ref_ply) if ref_info["faces"] else None

    table = BenchTable("slam", COLUMNS)
    held_frames = list(range(0, len(ids), 10))  # every 10th frame, unless trisplat's run names its held-out frames
    details: dict = {"capture": str(args.capture), "frames": len(ids), "start": args.start, "stride": args.stride,
                     "colour_registration": reg.as_dict(),
                     "downscale": args.downscale, "resolution": [W, H], "trisplat_slam_extra_args": extra,
                     "reference_tsdf_mesh": ref_info, "methods": {}}
    for method in args.methods:
        run_dir = args.out / f"slam_{method}"
        if run_dir.exists():
            shutil.rmtree(run_dir)  # a fresh run: no stale checkpoint or outputs
        down = (args.open3d_slam_downscale or args.downscale) if method == "open3d-slam" else args.downscale
        Wm, Hm = stream.size_at(down)
        print(f"== {method}: {len(ids)} frames at {Wm}x{Hm}", flush=True)
        load0 = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), time.process_time()
        metrics = (_run_trisplat(args, run_dir, extra) if method == "trisplat"
                   else RUNNERS[method](args, run_dir, registration))
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        load1 = os.getloadavg()[0]
        scores = score_run(run_dir, ref_c2w, reference, args.chamfer_samples, stamps)
        ate, mesh, geo = scores["ate"] or {}, scores["mesh"] or {}, scores["geometry"] or {}
        rpe = scores["rpe"] or {}
        held = metrics.get("held_out") or {}
        scoring = float(metrics.get("eval_seconds") or 0.0)  # trisplat's own held-out scoring, inside its wall
        compiling = float(metrics.get("compile_seconds") or 0.0)  # trisplat's kernel warm-up, inside its wall
        if held.get("frame_numbers"):
            held_frames = list(held["frame_numbers"])
        scores["held_out_mesh"] = mesh_psnr(run_dir, stream, ids, held_frames, args.downscale)
        row = [method, len(ids), f"{Wm}x{Hm}", ate.get("rmse_m"), ate.get("max_m"), rpe.get("translation_m_per_s"),
               rpe.get("rotation_deg_per_s"), wall, len(ids) / max(wall, 1e-9), scoring, compiling,
               len(ids) / max(wall - scoring - compiling, 1e-9),
               mesh.get("num_faces"), mesh.get("largest_component_fraction"), geo.get("chamfer"),
               geo.get("accuracy"), geo.get("completeness"), geo.get("fscore"), held.get("psnr"),
               held.get("psnr_without_exposure"), held.get("depth_l1_m"), scores["held_out_mesh"]["psnr"],
               (metrics.get("held_out_mesh") or {}).get("psnr") if held.get("psnr_without_exposure") is not None
               else None, load0, load1]
        table.add(*row)
        details["methods"][method] = {"wall_seconds": wall, "cpu_seconds": cpu, "load_before": load0,
                                      "load_after": load1, "run_dir": str(run_dir), "metrics": metrics, **scores}
        print(dict(zip(table.columns, row)), flush=True)

    thr = next((m["geometry"]["threshold"] for m in details["methods"].values() if m.get("geometry")), None)
    table.notes.append(
        f"Capture {args.capture.name}: {len(ids)} frames (capture frames {ids[0]} to {ids[-1]}, stride {args.stride}) "
        f"at {W}x{H} (1/{args.downscale}). "
        "ATE: camera centres after the rigid SE(3) alignment (no scale) onto the reference poses. RPE: the relative "
        "pose error over 1 s (TUM's definition; frames without timestamps at 1/--fps s), RMSE of its translation and "
        "rotation per second (trisplat.slam.trajectory.rpe_per_second). Wall s: the whole "
        "method (loading, tracking, mapping, meshing; trisplat also its held-out scoring); frames/s = frames / wall s; "
        "scoring s: trisplat's held-out scoring (its metrics.json `eval_seconds`), not part of SLAM; compile s: "
        "trisplat's kernel warm-up before its run (`compile_seconds`: compiling on the first run of an install, "
        "loading the cached kernels after; trisplat.slam.warmup); frames/s without scoring or compiling = frames / "
        "(wall s - scoring s - compile s). "
        "Largest component: share of the mesh's faces in its largest vertex-connected piece (trisplat.mesh.stats). "
        f"Chamfer / accuracy / completeness (metres) and F-score (threshold {thr if thr is None else f'{thr:.3f} m'}, "
        "1% of the reference box diagonal) against the TSDF mesh of the same frames fused at the reference poses "
        f"({ref_info['faces']} faces; voxel {ref_info['voxel_m']} m), each mesh moved by the rigid alignment of "
        f"its poses (rotations and centres) onto the reference poses, {args.chamfer_samples} samples a side "
        "(trisplat.eval.geometry); the reference is fused from the same depth maps by the same TSDF as the Open3D "
        "baseline, which favours the baseline's Chamfer. Held-out: trisplat's frames "
        "that were not keyframes, rendered at their tracked poses (its metrics.json), at each frame's exposure "
        "interpolated between the keyframes around it (trisplat.slam.exposure: from the keyframes, never fitted to "
        "the scored photo); without exposure: the map as it is. Held-out PSNR of mesh.ply: "
        "each method's mesh file as it is (vertex colours, unlit, 2x2 samples, black where empty) at its own poses of "
        "the same frames (trisplat's held-out frames when trisplat ran; Open3D fused every frame, those included); at "
        "the frames' exposure: trisplat's mesh through each frame's interpolated exposure (its metrics.json; Open3D "
        "has no exposure model). Open3D: "
        "RGB-D odometry (hybrid term) frame to frame + UniformTSDFVolume (trisplat.slam.open3d_baseline). "
        "Open3D dense SLAM (open3d-slam): open3d.t.pipelines.slam.Model, frame-to-model point-to-plane tracking "
        "against the voxel block grid's ray-cast depth, every frame fused, at its dense_slam.py example's defaults "
        "(voxel 5.8 mm, truncation 8 voxels, depth 0.1-3 m, mesh at weight 3; trisplat.slam.open3d_dense_slam); its "
        "wall includes loading its frames. "
        "Load = 1-minute load average before and after each method (the machine may be shared). "
        f"Colour: {reg.describe(stream.K)} (trisplat.data.colour_registration; the held-out photos both methods are "
        "scored on are read the same way)."
        + (f" trisplat slam extra options: `{' '.join(extra)}`." if extra else ""))
    (args.out / "slam_details.json").write_text(json.dumps(details, indent=2, default=float))
    md = table.write(args.out, "trisplat bench slam " + " ".join(argv))
    print(md.read_text())
    return 0
