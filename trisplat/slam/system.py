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
                   list(b["track_loss"]), list(b["track_iters"]), float(b["elapsed_s"]))
    return st, int(b["frames_done"])


def _fmt_s(s: float) -> str:
    return f"{int(s // 60)}m{int(s % 60):02d}s"


def run_slam(stream: RGBDStream, out: Path, cfg: SlamConfig, resume: bool = False, log=print) -> dict:
    """Run SLAM over the stream, writing RUN outputs; returns the metrics dict (also RUN/metrics.json)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    D = cfg.downscale
    K = stream.K_at(D)
    W, H = stream.size_at(D)
    ids = list(range(0, len(stream), cfg.stride))
    if cfg.max_frames:
        ids = ids[: cfg.max_frames]
    (out / CONFIG).write_text(json.dumps({"capture": str(stream.root), "format": stream.format, **asdict(cfg)},
                                         indent=2))
    ckpt = out / CHECKPOINT
    start = 0
    if resume and ckpt.is_file():
        state, start = load_checkpoint(ckpt)
        log(f"resumed from {ckpt}: {start} frames done, {state.smap.num_faces} triangles")
    else:
        if resume:
            log(f"no checkpoint at {ckpt}: starting from the first frame")
        state = SlamState(SlamMap.empty())
    keyframes: list[Keyframe] = []
    for k in state.keyframe_ids:  # reload keyframe observations of a resumed run
        rgb, depth = load_frame(stream, ids[k], D)
        keyframes.append(Keyframe(k, torch.from_numpy(rgb), torch.from_numpy(depth), state.c2w[k]))
    t0 = time.time() - state.elapsed_s
    t_session = time.time()
    for n in range(start, len(ids)):
        rgb, depth = load_frame(stream, ids[n], D)
        if n == 0:
            c2w = np.eye(4)
            res_loss, res_it, coverage = 0.0, 0, 0.0
        else:
            prev = np.linalg.inv(state.c2w[-1])
            guess = prev if n < 2 else prev @ state.c2w[-2] @ prev  # constant velocity: w2c_n = w2c_{n-1} dT
            sm = state.smap
            r = track_frame(sm.scene.positions, sm.scene.faces, sm.colors(), sm.scene.opacities(), cfg.sigma,
                            _pyramid(rgb, depth, K, cfg.track.levels), guess, cfg.track)
            c2w = np.linalg.inv(r.w2c)
            res_loss, res_it, coverage = r.loss, r.iterations, r.coverage
        state.c2w.append(c2w)
        state.track_loss.append(res_loss)
        state.track_iters.append(res_it)
        is_kf = n == 0
        if not is_kf:
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
                f"elapsed {_fmt_s(state.elapsed_s)}  eta {_fmt_s((len(ids) - done) / max(rate, 1e-9))}", flush=True)
        if cfg.checkpoint_every and done % cfg.checkpoint_every == 0 and done < len(ids):
            save_checkpoint(ckpt, state, done)
    slam_s = state.elapsed_s
    # Soft to hard: refine over every keyframe while the window sharpens to sigma_end.
    tf = time.time()
    if cfg.final_iters:
        log(f"final refinement: {cfg.final_iters} iterations over {len(keyframes)} keyframes, "
            f"sigma {cfg.sigma} -> {cfg.sigma_end}", flush=True)
        refine(state.smap, keyframes, K, cfg.sigma, cfg.final_iters, cfg.mapping, rng, sigma_end=cfg.sigma_end,
               window=0)
        prune(state.smap, cfg.prune)
    final_s = time.time() - tf
    save_checkpoint(ckpt, state, len(ids))
    return write_outputs(stream, out, cfg, state, ids, keyframes, slam_s, final_s, log)


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
        "mesh": mesh_info,
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
