"""The SLAM loop: frames in order -> track (constant-velocity guess) -> keyframe? spawn + refine + prune ->
progress; at the end the soft-to-hard refinement and the outputs (trajectory, model, mesh, metrics)."""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from trisplat.io.atomic import atomic_write_text
from trisplat.run import move_aside, prepare_run_dir
from trisplat.data.rgbd_stream import RGBDStream, _box_down, downscale_depth, load_frame
from trisplat.slam.map import PruneConfig, SlamMap, SpawnConfig, prune, spawn
from trisplat.slam.mapping import Keyframe, MapConfig, refine
from trisplat.slam.se3 import ate_rmse, log_so3_angle, write_tum_trajectory
from trisplat.slam.track import TrackConfig, track_frame

CHECKPOINT = "checkpoint.pt"
TRAJECTORY = "trajectory.txt"
MODEL = "model.ply"
MESH = "mesh.ply"
METRICS = "metrics.json"
CONFIG = "config.json"
STATE = "state.json"  # {"finished", "step" (frames done), "total_steps", "refined"}, as a training run's


@dataclass
class SlamConfig:
    """Settings of one SLAM run (saved as RUN/config.json)."""

    downscale: int = 2
    """process frames at 1/downscale of the capture's resolution (integer)"""
    max_frames: int = 0
    """stop after this many frames (0 = all)"""
    stride: int = 1
    """use every stride-th frame"""
    sigma: float = 0.3
    """window sharpness of the soft renderer during SLAM (1 soft ... 0 hard)"""
    sigma_end: float = 0.02
    """sharpness reached by the final refinement (the soft-to-hard schedule's end)"""
    final_iters: int = 150
    """refinement iterations over all keyframes after the last frame (soft to hard); 0 skips"""
    keyframe_every: int = 8
    """a new keyframe at least every this many frames (count) ..."""
    keyframe_translation: float = 0.08
    """... or when the camera moved more than this (metres) from the last keyframe ..."""
    keyframe_rotation_deg: float = 8.0
    """... or rotated more than this (degrees) ..."""
    keyframe_coverage: float = 0.85
    """... or when fewer than this fraction of the valid-depth pixels were covered while tracking"""
    lost_coverage: float = 0.3
    """a tracked frame is lost when fewer than this fraction of its valid-depth pixels are covered by the map at the
    tracked pose within --slam.track.outlier-depth of the observed depth (unitless) ..."""
    lost_residual: float = 0.05
    """... or when the mean depth residual of those pixels is above this (metres). A lost frame is tracked again
    from the last tracked pose and from the last keyframe's (relocalise_iters x the iterations); when that fails too
    it is skipped: no keyframe, no map from it, its pose not used for the next guess"""
    relocalise_iters: int = 3
    """iteration cap of a re-localisation, as a multiple of --slam.track.max-iters (count)"""
    checkpoint_every: int = 50
    """frames between checkpoints (count; 0 = none)"""
    eval_every: int = 10
    """every this-many-th non-keyframe frame is scored (PSNR / SSIM / depth L1) at its tracked pose"""
    seed: int = 0
    """random seed (torch and numpy) of the run"""
    mesh: Literal["surface", "delaunay"] = "surface"
    """how mesh.ply is made: 'surface' fuses the map's depth at the keyframes into one connected surface (the
    training switch's path, trisplat.train.switch); 'delaunay' is the restricted Delaunay of the map's vertices
    against its triangles (the paper's; pieces where the map is thin)"""
    mesh_resolution: int = 512
    """'surface' mesh: voxels along the longest side of the fused box (at most twice the processed frames' longer
    side, and fewer when the grid would pass trisplat.train.switch's voxel cap)"""
    track: TrackConfig = field(default_factory=TrackConfig)
    spawn: SpawnConfig = field(default_factory=SpawnConfig)
    mapping: MapConfig = field(default_factory=MapConfig)
    prune: PruneConfig = field(default_factory=PruneConfig)


@dataclass
class SlamState:
    """Everything needed to continue a run: the map, the poses so far, the keyframe frame indices, timing."""

    smap: SlamMap
    c2w: list[np.ndarray] = field(default_factory=list)
    keyframe_ids: list[int] = field(default_factory=list)
    track_loss: list[float] = field(default_factory=list)
    track_iters: list[int] = field(default_factory=list)
    elapsed_s: float = 0.0
    lost: list[int] = field(default_factory=list)
    """frame numbers (in the run's sequence) whose tracking failed even after re-localisation: skipped"""
    refined: bool = False
    """the final refinement is done (a resumed run goes straight to the outputs)"""
    final_s: float = 0.0
    rng_state: str = ""
    """the run's numpy generator state (JSON), so a resumed run draws what the uninterrupted one would"""


def _pyramid(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, levels) -> list:
    out = []
    for lv in levels:
        Kl = K.copy()
        Kl[:2] /= lv
        r = rgb if lv == 1 else _box_down(rgb, lv).astype(np.float32)
        out.append((torch.from_numpy(np.ascontiguousarray(r)), torch.from_numpy(downscale_depth(depth, lv)),
                    torch.from_numpy(Kl)))
    return out


def save_checkpoint(path: Path, state: SlamState, frames_done: int) -> None:
    sc = state.smap.scene
    blob = {
        "frames_done": frames_done,
        "positions": sc.positions.detach(), "sh": sc.sh.detach(), "opacity_logit": sc.opacity_logit.detach(),
        "faces": sc.faces, "spawn_edge": state.smap.spawn_edge, "birth": state.smap.birth,
        "c2w": torch.as_tensor(np.array(state.c2w).reshape(-1, 4, 4), dtype=torch.float64),
        "keyframe_ids": [int(k) for k in state.keyframe_ids], "track_loss": [float(v) for v in state.track_loss],
        "track_iters": [int(v) for v in state.track_iters], "elapsed_s": float(state.elapsed_s),
        "lost": [int(v) for v in state.lost], "refined": bool(state.refined), "final_s": float(state.final_s),
        "rng_state": state.rng_state,
    }
    from trisplat.train.checkpoint import atomic_torch_save

    atomic_torch_save(blob, path)


def load_checkpoint(path: Path) -> tuple[SlamState, int]:
    from trisplat.scene.model import TriangleScene

    try:
        b = torch.load(path, map_location="cpu", weights_only=True)  # plain tensors and numbers: no code runs
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the same user error
        raise ValueError(f"{path}: unreadable SLAM checkpoint ({exc})") from None
    sc = TriangleScene(b["positions"], b["sh"], b["opacity_logit"], b["faces"])
    st = SlamState(SlamMap(sc, b["spawn_edge"], b["birth"]), [m for m in b["c2w"].numpy()], list(b["keyframe_ids"]),
                   list(b["track_loss"]), list(b["track_iters"]), float(b["elapsed_s"]), list(b.get("lost", [])),
                   bool(b.get("refined", False)), float(b.get("final_s", 0.0)), str(b.get("rng_state", "")))
    return st, int(b["frames_done"])


def _fmt_s(s: float) -> str:
    return f"{int(s // 60)}m{int(s % 60):02d}s"


# settings that number the frames and keyframes or change what a frame holds: a resumed run keeps the saved ones
RESUME_FIXED = {"capture": "CAPTURE", "format": "CAPTURE", "depth_scale": "--depth-scale",
                "stride": "--slam.stride", "downscale": "--slam.downscale"}


def check_resume(out: Path, saved: dict, given: dict, frames_done: int, frames: int) -> None:
    """Refuse a resume whose settings would re-index the run's frames and keyframes (RESUME_FIXED) or end it before
    the frames already done, naming the option. Other settings may change: they apply to the frames still to do."""
    def same(k):
        a, b = saved.get(k), given.get(k)
        if k == "capture":
            return a is None or Path(a).resolve() == Path(b).resolve()
        if isinstance(a, float) or isinstance(b, float):
            return a is None or b is None or abs(float(a) - float(b)) <= 1e-12 * max(abs(float(a)), 1e-300)
        return a is None or a == b
    changed = [k for k in RESUME_FIXED if not same(k)]
    if changed:
        what = ", ".join(f"{RESUME_FIXED[k]} ({k}: saved {saved.get(k)!r}, given {given.get(k)!r})" for k in changed)
        raise ValueError(f"{out}: --resume continues the saved run and cannot change {what}: the checkpoint's frames "
                         "and keyframes are numbered by it. Give the saved value, or start a new run with --force.")
    if frames < frames_done:
        raise ValueError(f"{out}: --resume with --slam.max-frames {given.get('max_frames')} ends the run at {frames} "
                         f"frames, but {frames_done} are already done; give a larger --slam.max-frames (or 0: all)")


def motion_guess(c2w: list[np.ndarray], lost: set[int]) -> np.ndarray:
    """world_to_camera guess of the next frame: constant velocity from the last two frames (w2c_n = w2c_{n-1} dT),
    or the last tracked pose (zero velocity) when there is only one, or one of the two was lost."""
    n = len(c2w)
    good = [k for k in range(n) if k not in lost]
    prev = np.linalg.inv(c2w[good[-1]])
    if len(good) < 2 or good[-1] != n - 1 or good[-2] != n - 2:
        return prev
    return prev @ c2w[-2] @ prev


def _track_ok(r, cfg: SlamConfig) -> bool:
    return r.coverage >= cfg.lost_coverage and r.residual <= cfg.lost_residual


def _describe(r) -> str:
    return (f"{r.coverage:.0%} of the valid depth covered, depth residual {r.residual * 100:.1f} cm, "
            f"{'converged' if r.converged else 'not converged'} in {r.iterations} iterations")


def track_with_relocalisation(state: SlamState, pyr, cfg: SlamConfig, n: int, label: str, log):
    """Track frame n from the motion guess; when the result is lost (too little of the valid depth covered, or the
    depth residual too high), track again from the last tracked pose and from the last keyframe's pose with
    relocalise_iters x the iterations and keep the best that is not lost. Returns (TrackResult, lost: bool)."""
    import dataclasses

    sm = state.smap
    lost = set(state.lost)
    args = (sm.scene.positions, sm.scene.faces, sm.colors(), sm.scene.opacities(), cfg.sigma, pyr)
    r = track_frame(*args, motion_guess(state.c2w, lost), cfg.track)
    if _track_ok(r, cfg):
        return r, False
    log(f"{label}: tracking lost ({_describe(r)}); re-localising from the last tracked pose and the last "
        "keyframe's", flush=True)
    more = dataclasses.replace(cfg.track, max_iters=tuple(int(i) * max(1, cfg.relocalise_iters)
                                                         for i in cfg.track.max_iters))
    last_good = max(k for k in range(len(state.c2w)) if k not in lost)
    starts = [last_good] + ([state.keyframe_ids[-1]] if state.keyframe_ids[-1] != last_good else [])
    tries = [r] + [track_frame(*args, np.linalg.inv(state.c2w[k]), more) for k in starts]
    ok = [t for t in tries[1:] if _track_ok(t, cfg)]
    if ok:
        best = min(ok, key=lambda t: t.loss)
        log(f"{label}: re-localised ({_describe(best)})", flush=True)
        return best, False
    best = max(tries, key=lambda t: (t.coverage, -t.loss))
    log(f"{label}: re-localisation failed ({_describe(best)}); frame skipped: no map is made from it and its pose "
        "in the trajectory is the best attempt's", flush=True)
    return best, True


def run_slam(stream: RGBDStream, out: Path, cfg: SlamConfig, resume: bool = False, log=print,
             force: bool = False) -> dict:
    """Run SLAM over the stream, writing RUN outputs; returns the metrics dict (also RUN/metrics.json).

    The run rules of `trisplat train` (trisplat.run): a non-empty `out` is refused unless `force` (it is then moved
    aside, never deleted) or `resume`; a resume keeps the settings that number the frames (RESUME_FIXED); config,
    state, checkpoint and metrics are written atomically."""
    out = Path(out)
    prepare_run_dir(out, resume, force, checkpoint=CHECKPOINT)
    D = cfg.downscale
    K = stream.K_at(D)
    ids = list(range(0, len(stream), cfg.stride))
    if cfg.max_frames:
        ids = ids[: cfg.max_frames]
    record = {"capture": str(Path(stream.root).resolve()), "format": stream.format,
              "depth_scale": float(stream.depth_scale), **asdict(cfg)}
    ckpt = out / CHECKPOINT
    start, state = 0, None
    if resume and ckpt.is_file():
        state, start = load_checkpoint(ckpt)
    if resume and (out / CONFIG).is_file():
        try:
            saved = json.loads((out / CONFIG).read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{out / CONFIG}: malformed JSON ({exc})") from None
        check_resume(out, saved, record, start, len(ids))
    if force and not resume:
        move_aside(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / CONFIG, json.dumps(record, indent=2))
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    if state is not None:
        if state.rng_state:
            rng.bit_generator.state = json.loads(state.rng_state)
        log(f"resumed from {ckpt}: {start} frames done, {state.smap.num_faces} triangles")
    else:
        if resume:
            log(f"no checkpoint at {ckpt}: starting from the first frame")
        state = SlamState(SlamMap.empty())
    if start < len(ids):
        state.refined = False  # more frames: the refinement runs again at the end

    def checkpoint(done: int) -> None:
        state.rng_state = json.dumps(rng.bit_generator.state)
        save_checkpoint(ckpt, state, done)
        atomic_write_text(out / STATE, json.dumps({"finished": False, "step": done, "total_steps": len(ids),
                                                   "refined": state.refined}))

    keyframes: list[Keyframe] = []
    for k in state.keyframe_ids:  # reload keyframe observations of a resumed run
        rgb, depth = load_frame(stream, ids[k], D)
        keyframes.append(Keyframe(k, torch.from_numpy(rgb), torch.from_numpy(depth), state.c2w[k]))
    t0 = time.time() - state.elapsed_s
    t_session = time.time()
    for n in range(start, len(ids)):
        rgb, depth = load_frame(stream, ids[n], D)
        lost = False
        if n == 0:
            c2w = np.eye(4)
            res_loss, res_it, coverage = 0.0, 0, 0.0
        else:
            r, lost = track_with_relocalisation(state, _pyramid(rgb, depth, K, cfg.track.levels), cfg, n,
                                                f"frame {n + 1}/{len(ids)} (capture frame {ids[n]})", log)
            c2w = np.linalg.inv(r.w2c)
            res_loss, res_it, coverage = r.loss, r.iterations, r.coverage
        state.c2w.append(c2w)
        state.track_loss.append(res_loss)
        state.track_iters.append(res_it)
        if lost:
            state.lost.append(n)
        is_kf = n == 0
        if not is_kf and not lost:
            last = state.c2w[state.keyframe_ids[-1]]
            rel = np.linalg.inv(last) @ c2w
            is_kf = (n - state.keyframe_ids[-1] >= cfg.keyframe_every
                     or np.linalg.norm(rel[:3, 3]) > cfg.keyframe_translation
                     or np.degrees(log_so3_angle(rel[:3, :3])) > cfg.keyframe_rotation_deg
                     or coverage < cfg.keyframe_coverage)
        if is_kf:
            state.keyframe_ids.append(n)
            keyframes.append(Keyframe(n, torch.from_numpy(rgb), torch.from_numpy(depth), c2w))
            spawn(state.smap, rgb, depth, c2w, K, len(keyframes) - 1, cfg.spawn, cfg.sigma, rng)
            iters = cfg.mapping.first_iters if n == 0 else cfg.mapping.iters
            refine(state.smap, keyframes, K, cfg.sigma, iters, cfg.mapping, rng)
            prune(state.smap, cfg.prune)
        state.elapsed_s = time.time() - t0
        done = n + 1
        if done % 10 == 0 or done == len(ids) or n == start:
            rate = (done - start) / max(time.time() - t_session, 1e-9)
            log(f"frame {done}/{len(ids)}  {rate:.2f} fps  triangles {state.smap.num_faces}  "
                f"track loss {res_loss:.4f} ({res_it} it)  keyframes {len(keyframes)}  "
                + (f"lost {len(state.lost)}  " if state.lost else "")
                + f"elapsed {_fmt_s(state.elapsed_s)}  eta {_fmt_s((len(ids) - done) / max(rate, 1e-9))}", flush=True)
        if cfg.checkpoint_every and done % cfg.checkpoint_every == 0 and done < len(ids):
            checkpoint(done)
    slam_s = state.elapsed_s
    # Soft to hard: refine over every keyframe while the window sharpens to sigma_end.
    if state.refined:
        log(f"final refinement: already done ({ckpt}); writing the outputs", flush=True)
    else:
        tf = time.time()
        if cfg.final_iters:
            log(f"final refinement: {cfg.final_iters} iterations over {len(keyframes)} keyframes, "
                f"sigma {cfg.sigma} -> {cfg.sigma_end}", flush=True)
            refine(state.smap, keyframes, K, cfg.sigma, cfg.final_iters, cfg.mapping, rng, sigma_end=cfg.sigma_end,
                   window=0)
            prune(state.smap, cfg.prune)
        state.final_s = time.time() - tf
        state.refined = True
        checkpoint(len(ids))  # before the outputs: a failure there resumes straight to them, not to a second refinement
    metrics = write_outputs(stream, out, cfg, state, ids, keyframes, slam_s, state.final_s, log)
    atomic_write_text(out / STATE, json.dumps({"finished": True, "step": len(ids), "total_steps": len(ids),
                                               "refined": True}))
    return metrics


def evaluate_frames(stream: RGBDStream, smap: SlamMap, c2ws, ids, frame_numbers, cfg: SlamConfig) -> dict:
    """PSNR / SSIM / depth L1 (metres, on pixels with valid observed depth and rendered alpha > 0.5) of the map
    rendered hard-ish (sigma_end) at the tracked poses of the given frames (numbers in the run's sequence)."""
    from trisplat.eval.image_metrics import psnr, ssim

    K = stream.K_at(cfg.downscale)
    W, H = stream.size_at(cfg.downscale)
    ps, ss, dl = [], [], []
    for n in frame_numbers:
        rgb, depth = load_frame(stream, ids[n], cfg.downscale)
        with torch.no_grad():
            o = smap.render(np.linalg.inv(c2ws[n]), K, W, H, cfg.sigma_end)
        img = o.rgb.clamp(0, 1).numpy()
        ps.append(psnr(img, rgb))
        ss.append(ssim(img, rgb))
        a = o.alpha.numpy()
        m = (depth > 0) & (a > 0.5)
        if m.any():
            dl.append(float(np.abs(o.depth.numpy()[m] / a[m] - depth[m]).mean()))
    mean = lambda v: float(np.mean(v)) if v else None
    return {"frames": len(frame_numbers), "psnr": mean(ps), "ssim": mean(ss), "depth_l1_m": mean(dl), "lpips": None}


def map_surface(smap: SlamMap, keyframes: list[Keyframe], stream: RGBDStream, cfg: SlamConfig, log
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """The map as one connected surface: its depth rendered at every keyframe's pose, fused (TSDF) and meshed by
    trisplat.train.switch.soup_to_surface, vertex colours from the keyframes' photos. Pixels the map leaves empty
    are unknown here, not free space: seen from inside a room, an empty pixel is a hole in the map, and taking it
    for free space would carve through walls. Returns vertices [V,3], faces [F,3], colours [V,3], a report."""
    from trisplat.cameras import Camera
    from trisplat.scene.sh import sh_dc_to_rgb
    from trisplat.train.switch import SurfaceConfig, soup_to_surface

    K = stream.K_at(cfg.downscale)
    W, H = stream.size_at(cfg.downscale)
    cams = [Camera(np.linalg.inv(kf.c2w), K, W, H, name=f"keyframe {kf.frame}") for kf in keyframes]

    def render(n: int):
        with torch.no_grad():
            return smap.render(cams[n].world_to_camera, K, W, H, cfg.sigma_end)

    scfg = SurfaceConfig(resolution=int(min(cfg.mesh_resolution, 2 * max(W, H))), empty_is_free=False,
                         unseen_faces="drop")
    surface, rep = soup_to_surface(smap.scene.detached(), cams, render, None, scfg,
                                   lambda m: log(f"mesh: {m}", flush=True),
                                   images=lambda n: keyframes[n].rgb.numpy())
    log(f"mesh: {rep.summary()}", flush=True)
    cols = sh_dc_to_rgb(surface.sh[:, 0, :]).numpy()
    info = {"method": "the map's depth at the keyframes fused into one surface (trisplat.train.switch)",
            "switch": rep.to_dict()}
    return surface.positions.numpy().astype(np.float64), surface.faces.numpy().astype(np.int64), cols, info


def write_outputs(stream, out: Path, cfg: SlamConfig, state: SlamState, ids, keyframes, slam_s, final_s, log) -> dict:
    from trisplat.io import export_mesh
    from trisplat.io.model_ply import save_model_ply
    from trisplat.mesh.cleanup import face_components
    from trisplat.mesh.connect import ConnectConfig, connect_faces

    stamps = [stream.frames[i].stamp if stream.frames[i].stamp is not None else float(i) for i in ids]
    write_tum_trajectory(out / TRAJECTORY, stamps, state.c2w)
    sc = state.smap.scene.detached()
    save_model_ply(out / MODEL, sc, np.eye(4))
    tm = time.time()
    if cfg.mesh == "surface":
        verts, faces, cols, mesh_info = map_surface(state.smap, keyframes, stream, cfg, log)
    elif cfg.mesh == "delaunay":
        cleaned, _ = connect_faces(sc.positions.numpy().astype(np.float64), sc.faces.numpy(),
                                   ConnectConfig(repair_non_manifold_edges=True, drop_unreferenced_vertices=True))
        verts, faces = cleaned.vertices, cleaned.faces
        cols = state.smap.colors().detach().numpy()[cleaned.vertex_source]
        mesh_info = {"method": "restricted Delaunay of the map's vertices against its triangles (trisplat.mesh)"}
    else:
        raise ValueError(f"--slam.mesh must be 'surface' or 'delaunay', got {cfg.mesh!r}")
    mesh_info.update(faces=int(len(faces)), vertices=int(len(verts)))
    if len(faces):
        export_mesh(out / MESH, verts, faces, np.clip(cols, 0, 1))
        nc, lab = face_components(faces, len(verts))
        mesh_info.update(components=int(nc), largest_component_fraction=float(np.bincount(lab).max() / len(lab)))
    mesh_info["seconds"] = time.time() - tm
    kf_set = set(state.keyframe_ids)
    held = [n for n in range(len(ids)) if n not in kf_set][:: max(1, cfg.eval_every)]
    metrics = {
        "capture": str(stream.root), "format": stream.format, "frames": len(ids),
        "resolution": list(stream.size_at(cfg.downscale)), "keyframes": len(state.keyframe_ids),
        "triangles": state.smap.num_faces, "slam_seconds": slam_s, "final_refine_seconds": final_s,
        "fps": len(ids) / max(slam_s, 1e-9), "mean_track_iterations": float(np.mean(state.track_iters[1:] or [0])),
        "lost_frames": [int(n) for n in state.lost], "mesh": mesh_info,
        "held_out": evaluate_frames(stream, state.smap, state.c2w, ids, held, cfg),
    }
    ref = [stream.frames[i].reference_c2w for i in ids]
    have = [k for k, r in enumerate(ref) if r is not None]
    if len(have) >= 3:
        est = np.array([state.c2w[k] for k in have])
        rmse, err = ate_rmse(est, np.array([ref[k] for k in have]))
        metrics["ate"] = {"rmse_m": rmse, "max_m": float(err.max()), "median_m": float(np.median(err)),
                          "frames": len(have),
                          "alignment": "rigid SE(3) (Horn/Umeyama, no scale) of estimated onto reference camera centres"}
        log(f"ATE RMSE {rmse * 100:.2f} cm over {len(have)} frames (after rigid SE(3) alignment, no scale)")
    atomic_write_text(out / METRICS, json.dumps(metrics, indent=2))
    log(f"wrote {out / TRAJECTORY}, {out / MODEL}, {out / MESH} ({mesh_info.get('faces', 0)} faces, largest "
        f"component {mesh_info.get('largest_component_fraction', 0):.1%}), {out / METRICS}")
    return metrics
