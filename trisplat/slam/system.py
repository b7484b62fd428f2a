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
from trisplat.data.rgbd_stream import FramePrefetch, RGBDStream, _box_down, downscale_depth, load_frame
from trisplat.slam.exposure import apply_exposure, exposure_range, identity, interpolate_exposure, regauge_map, undo_exposure
from trisplat.slam.loop import Edge, LoopCloser, LoopConfig, optimise_pose_graph
from trisplat.slam.map import PruneConfig, SlamMap, SpawnConfig, prune, spawn
from trisplat.slam.mapping import Keyframe, MapConfig, refine
from trisplat.slam.se3 import log_so3_angle, write_tum_trajectory
from trisplat.slam.trajectory import ate_summary
from trisplat.slam.track import TrackConfig, track_frame

CHECKPOINT = "checkpoint.pt"
TRAJECTORY = "trajectory.txt"
MODEL = "model.ply"
MESH = "mesh.ply"
MESH_GLB = "mesh.glb"  # the same mesh for engines and viewers: Y-up, linear COLOR_0, unlit (trisplat.io)
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
    start: int = 0
    """first capture frame used (a later stretch of a capture; frames are numbered from it)"""
    sigma: float = 0.3
    """window sharpness of the soft renderer during SLAM (1 soft ... 0 hard)"""
    sigma_end: float = 0.02
    """sharpness reached by the final refinement (the soft-to-hard schedule's end)"""
    final_ba_rounds: int = 0
    """rounds of a bundle adjustment of the keyframe poses and the map before the final refinement, by blocks: every
    keyframe's pose tracked again against the whole map (the first fixed: the gauge; the other frames follow their
    keyframe's correction), then the map refined over all keyframes (--slam.final-ba-map-iters); 0 skips"""
    final_ba_map_iters: int = 30
    """map iterations per bundle-adjustment round (count)"""
    final_iters: int = 400
    """refinement iterations over all keyframes after the last frame (soft to hard); 0 skips. 7-Scenes, held-out
    map / mesh.ply PSNR: 150 -> 19.9 / 20.1 dB, 400 -> 20.5 / 20.3 (13 s more), 800 -> 20.9 / 19.9 (40 s more)"""
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
    lost_coverage_drop: float = 0.7
    """a tracked frame is also suspect when its coverage falls below this x the median of the last 10 tracked
    frames' ...)"""
    lost_loss_rise: float = 3.0
    """... or its tracking loss rises above this x their median (a sudden jump the tracker slid along a plane to
    follow): it is re-localised, and kept as tracked when nothing better passes the tests"""
    relocalise_iters: int = 3
    """iteration cap of a re-localisation, as a multiple of --slam.track.max-iters (count)"""
    realtime: bool = False
    """keep up with a live stream at --slam.input-fps: a frame that arrives while the previous one is still being
    processed is tracked with half the iterations (one pass, no re-render); a frame whose successor has already
    arrived is dropped (not tracked, no map; its pose is the constant-velocity guess). The count is reported"""
    input_fps: float = 15.0
    """frame rate of the stream that --slam.realtime keeps up with (frames/s)"""
    checkpoint_every: int = 50
    """frames between checkpoints (count; 0 = none)"""
    eval_every: int = 10
    """every this-many-th non-keyframe frame is scored (PSNR / SSIM / depth L1) at its tracked pose"""
    seed: int = 0
    """random seed (torch and numpy) of the run"""
    exposure: bool = True
    """in the final refinement each keyframe sees the map through its own exposure, an affine colour per channel
    solved against the map (trisplat.slam.exposure; the map and the mesh end at the keyframes' mean exposure); other
    frames get the exposure interpolated between the keyframes around them. For cameras with auto
    exposure (7-Scenes' Kinect). Not used while tracking and mapping: there it made keyframes come every other frame
    after a loop closure. Off: photos are taken as they are"""
    mesh: Literal["surface", "delaunay"] = "surface"
    """how mesh.ply is made: 'surface' fuses the map's depth at the keyframes into one connected surface (the
    training switch's path, trisplat.train.switch); 'delaunay' is the restricted Delaunay of the map's vertices
    against its triangles (the paper's; pieces where the map is thin)"""
    mesh_resolution: int = 512
    """'surface' mesh: voxels along the longest side of the fused box (at most twice the processed frames' longer
    side, and fewer when the grid would pass trisplat.train.switch's voxel cap)"""
    mesh_min_piece: float = 0.01
    """'surface' mesh: pieces with fewer faces than this x the largest piece's are dropped as floaters (unitless; the
    training switch drops below 0.02). A room's chairs and the things on its tables can stand apart from the floor
    in the fused surface: on 7-Scenes, two chair pieces of 1.1% and 1.3% of the largest, which 0.02 dropped
    (largest piece 100% -> 97.7%, held-out mesh PSNR 18.07 -> 18.28 dB, uncovered pixels 3.7% -> 2.0%)"""
    texture_size: int = 0
    """'surface' mesh: side of a base-colour texture fitted to the keyframes' photos (their exposure undone) for
    mesh.glb, as `trisplat train` does (trisplat.texture.asset.build_asset: the vertex colours are fitted too, and the
    file keeps whichever of texture and vertex colours scores best on keyframes held out of the fits; mesh.ply holds
    the vertex colours). 0 (the default): the surface's colours from the photos, no fit. On 7-Scenes at 320x240 the
    2048 texture lost to the vertex colours on the held-out keyframes (21.7 against 22.0 dB), the fitted vertex colours
    scored 0.1 dB below the surface's own on the held-out frames, and the fits took 47 s"""
    mesh_unseen: Literal["drop", "drop_but_bridges"] = "drop_but_bridges"
    """'surface' mesh: what happens to fused faces no keyframe saw (trisplat.train.switch.SurfaceConfig.unseen_faces).
    'drop' drops them all; 'drop_but_bridges' keeps the hidden sides that face a seen face within 1 m and join two
    seen pieces of at least --slam.mesh-min-piece of the largest. A table top's underside is never seen; dropped, it
    leaves the top a piece apart from its legs (7-Scenes: largest piece 86% -> 98% for 1,383 more fused faces;
    held-out mesh PSNR and Chamfer unchanged); then each piece still apart is joined to the largest through the
    hidden surface nearest to it, within its own size (trisplat.mesh.hidden_join)"""
    mesh_unseen_depth: float = 0.08
    """'surface' mesh: space no keyframe saw is solid this far behind the surfaces in front of it, as a fraction of
    the fused box's longest side (trisplat.train.switch.SurfaceConfig.max_depth_fraction; training's objects use
    0.01). A room's table hides the floor under it from every keyframe: with 0.01 (4.5 cm on 7-Scenes) the table and
    its chairs stayed a piece apart from the room (frames 200-399: largest piece 76.6%); with 0.08 (36 cm) the
    hidden space under them is solid and its sides join them to the counters (100%; frames 0-199: 100% -> 98.6%);
    held-out mesh.ply at the frames' exposure 22.07 -> 22.53 dB and 23.31 -> 23.13 dB"""
    track: TrackConfig = field(default_factory=TrackConfig)
    spawn: SpawnConfig = field(default_factory=SpawnConfig)
    mapping: MapConfig = field(default_factory=MapConfig)
    prune: PruneConfig = field(default_factory=PruneConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)


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
    edges: list[Edge] = field(default_factory=list)
    """the keyframe pose graph's edges (odometry and verified loops; keyframe numbers)"""
    track_coverage: list[float] = field(default_factory=list)
    """per frame: the tracked coverage (0 for the first, dropped and lost ones)"""
    dropped: list[int] = field(default_factory=list)
    """--slam.realtime: frames dropped to keep up (numbers in the run's sequence)"""
    hurried: int = 0
    """--slam.realtime: frames tracked with fewer iterations to keep up"""
    exposure: list[np.ndarray] = field(default_factory=list)
    """per keyframe (in keyframe_ids' order): its exposure [2,3] (--slam.exposure; empty when off)"""


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
        "track_coverage": [float(v) for v in state.track_coverage], "dropped": [int(v) for v in state.dropped],
        "hurried": int(state.hurried),
        "exposure": torch.as_tensor(np.array(state.exposure).reshape(-1, 2, 3), dtype=torch.float64),
        "graph_ij": torch.tensor([[e.i, e.j, int(e.loop)] for e in state.edges], dtype=torch.int64).reshape(-1, 3),
        "graph_Z": torch.as_tensor(np.array([e.Z for e in state.edges]).reshape(-1, 4, 4), dtype=torch.float64),
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
    st.dropped, st.hurried = list(b.get("dropped", [])), int(b.get("hurried", 0))
    st.track_coverage = list(b.get("track_coverage", [0.0] * len(st.c2w)))
    st.exposure = [e.numpy().copy() for e in b.get("exposure", torch.zeros(0, 2, 3))]
    if "graph_ij" in b:
        st.edges = [Edge(int(i), int(j), Z.numpy().copy(), bool(lp)) for (i, j, lp), Z in zip(b["graph_ij"].tolist(),
                                                                                               b["graph_Z"])]
    return st, int(b["frames_done"])


def _fmt_s(s: float) -> str:
    return f"{int(s // 60)}m{int(s % 60):02d}s"


# settings that number the frames and keyframes or change what a frame holds: a resumed run keeps the saved ones
RESUME_FIXED = {"capture": "CAPTURE", "format": "CAPTURE", "depth_scale": "--depth-scale",
                "stride": "--slam.stride", "downscale": "--slam.downscale", "start": "--slam.start",
                "colour_registration": "--colour-registration"}


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
                         "and keyframes are numbered (and coloured) by it. Give the saved value, or start a new run with --force.")
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


def interpolate_correction(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """The rigid transform a fraction t in [0, 1] of the way from `a` to `b` (4x4): rotation along the geodesic
    R_a exp(t log(R_a^T R_b)), translation linearly."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    step = Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).as_rotvec()
    out[:3, :3] = a[:3, :3] @ Rotation.from_rotvec(t * step).as_matrix()
    out[:3, 3] = (1.0 - t) * a[:3, 3] + t * b[:3, 3]
    return out


def apply_pose_correction(state: SlamState, keyframes: list[Keyframe], new_kf_c2w: list[np.ndarray],
                          move_map: bool = True) -> float:
    """Move everything to the optimised keyframe poses: keyframe k's correction C_k = T_k' T_k^-1 (world frame) is
    applied to each keyframe, to the frames between keyframes k and k + 1 interpolated between C_k and C_k+1 by
    their place in between (rotation along the geodesic, translation linearly: the drift a frame carries lies between
    its two keyframes'; frames after the newest keyframe get its correction), and (move_map) to the map's triangles
    spawned at keyframe k (their vertices). Returns the largest keyframe-centre move (metres)."""
    corr = [new @ np.linalg.inv(kf.c2w) for new, kf in zip(new_kf_c2w, keyframes)]
    kf_frames = np.array(state.keyframe_ids)
    for n in range(len(state.c2w)):
        k = max(0, int(np.searchsorted(kf_frames, n, side="right")) - 1)
        C = corr[k]
        if k + 1 < len(corr) and n > kf_frames[k]:
            C = interpolate_correction(corr[k], corr[k + 1], (n - kf_frames[k]) / (kf_frames[k + 1] - kf_frames[k]))
        state.c2w[n] = C @ state.c2w[n]
    moved = 0.0
    for kf, new in zip(keyframes, new_kf_c2w):
        moved = max(moved, float(np.linalg.norm(new[:3, 3] - kf.c2w[:3, 3])))
        kf.c2w = new.copy()
    sm = state.smap
    if sm.num_faces and move_map:
        faces = sm.scene.faces.long()
        vb = torch.zeros(sm.scene.num_vertices, dtype=torch.int64)
        vb[faces] = sm.birth[:, None].expand(-1, 3)
        C = torch.as_tensor(np.array(corr), dtype=torch.float64)[vb.clamp_max(len(corr) - 1)]
        p = sm.scene.positions.detach().double()
        sm.scene.positions = (torch.einsum("vij,vj->vi", C[:, :3, :3], p) + C[:, :3, 3]).to(
            sm.scene.positions.dtype).contiguous()
    return moved


def bundle_adjust(state: SlamState, keyframes: list[Keyframe], K: np.ndarray, cfg: SlamConfig,
                  rng: np.random.Generator) -> float:
    """One round of the block bundle adjustment: each keyframe but the first tracked again (track_frame) against the
    whole map from its pose, kept where the result passes the lost-frame tests; the other frames follow their
    keyframe's correction (the map is not moved); then cfg.final_ba_map_iters map iterations over every keyframe.
    Returns the largest keyframe-centre move (metres)."""
    sm = state.smap
    args = (sm.scene.positions, sm.scene.faces, sm.colors(), sm.scene.opacities(), cfg.sigma)
    new = [keyframes[0].c2w.copy()]
    for kf in keyframes[1:]:
        r = track_frame(*args, _pyramid(kf.rgb.numpy(), kf.depth.numpy(), K, cfg.track.levels),
                        np.linalg.inv(kf.c2w), cfg.track)
        new.append(np.linalg.inv(r.w2c) if _track_ok(r, cfg) else kf.c2w.copy())
    moved = apply_pose_correction(state, keyframes, new, move_map=False)
    refine(sm, keyframes, K, cfg.sigma, cfg.final_ba_map_iters, cfg.mapping, rng, window=0)
    return moved


def close_loops(state: SlamState, keyframes: list[Keyframe], closer: LoopCloser, rgb: np.ndarray, depth: np.ndarray,
                label: str, log) -> int:
    """Register the newest keyframe with the loop closer; when it verifies a revisit, optimise the keyframe pose
    graph and correct the poses and the map (apply_pose_correction). Returns the number of loop edges found."""
    found = closer.add_keyframe([kf.c2w for kf in keyframes], rgb, depth)
    state.edges = closer.edges
    if not found:
        return 0
    new, rep = optimise_pose_graph([kf.c2w for kf in keyframes], closer.edges, closer.cfg)
    moved = apply_pose_correction(state, keyframes, new)
    pairs = ", ".join(f"keyframe {keyframes[e.j].frame} ~ {keyframes[e.i].frame}" for e in found)
    log(f"{label}: loop closed ({pairs}); pose graph of {len(keyframes)} keyframes, "
        f"{sum(e.loop for e in closer.edges)} loop edges: cost {rep['cost_before']:.3g} -> {rep['cost_after']:.3g}, "
        f"keyframes moved up to {moved * 100:.1f} cm", flush=True)
    return len(found)


def _track_ok(r, cfg: SlamConfig) -> bool:
    return r.coverage >= cfg.lost_coverage and r.residual <= cfg.lost_residual


def _recent(state: SlamState, count: int = 10) -> tuple[float, float] | None:
    """(median coverage, median loss) of the last `count` tracked frames (not the first, lost or dropped), or None
    when there are fewer than 3."""
    bad = set(state.lost) | set(state.dropped)
    good = [k for k in range(1, len(state.track_loss)) if k not in bad and state.track_iters[k] > 0][-count:]
    if len(good) < 3:
        return None
    return (float(np.median([state.track_coverage[k] for k in good])),
            float(np.median([state.track_loss[k] for k in good])))


def _consistent(r, cfg: SlamConfig, recent) -> str:
    """'' when the result is in line with the recent frames, else why not."""
    if recent is None:
        return ""
    cov, loss = recent
    if r.coverage < cfg.lost_coverage_drop * cov:
        return f"; coverage fell from {cov:.0%}"
    if loss > 0 and r.loss > cfg.lost_loss_rise * loss:
        return f"; loss {r.loss:.3g}, {r.loss / loss:.1f}x the recent frames'"
    return ""


def _describe(r) -> str:
    return (f"{r.coverage:.0%} of the valid depth covered, depth residual {r.residual * 100:.1f} cm, "
            f"{'converged' if r.converged else 'not converged'} in {r.iterations} iterations")


def track_with_relocalisation(state: SlamState, pyr, cfg: SlamConfig, n: int, label: str, log,
                              closer: LoopCloser | None = None, keyframes: list[Keyframe] | None = None):
    """Track frame n from the motion guess; when the result is lost (too little of the valid depth covered, or the
    depth residual too high), track again with relocalise_iters x the iterations from the poses the frame's SIFT
    features give against the newest keyframes' (verified with depth: LoopCloser.relocalise; a sudden jump), from
    the last tracked pose and from the last keyframe's pose, and keep the best that is not lost.
    Returns (TrackResult, lost: bool)."""
    import dataclasses

    sm = state.smap
    lost = set(state.lost)
    args = (sm.scene.positions, sm.scene.faces, sm.colors(), sm.scene.opacities(), cfg.sigma, pyr)
    r = track_frame(*args, motion_guess(state.c2w, lost), cfg.track)
    recent = _recent(state)
    first_ok, why = _track_ok(r, cfg), _consistent(r, cfg, recent)
    if first_ok and not why:
        return r, False
    log(f"{label}: tracking lost ({_describe(r)}{why}); re-localising from SIFT matches against the newest "
        "keyframes, the last tracked pose and the last keyframe's", flush=True)
    more = dataclasses.replace(cfg.track, max_iters=tuple(int(i) * max(1, cfg.relocalise_iters)
                                                         for i in cfg.track.max_iters))
    last_good = max(k for k in range(len(state.c2w)) if k not in lost)
    starts = [last_good] + ([state.keyframe_ids[-1]] if state.keyframe_ids[-1] != last_good else [])
    guesses = [np.linalg.inv(state.c2w[k]) for k in starts]
    if closer is not None and keyframes:
        rgb, depth, _ = (t.numpy() for t in pyr[-1])
        found = closer.relocalise(rgb, depth, [kf.c2w for kf in keyframes], n)
        if found:
            log(f"{label}: {len(found)} pose(s) from SIFT matches with depth against the newest keyframes", flush=True)
        guesses = [np.linalg.inv(c) for c in found] + guesses
    tries = [r] + [track_frame(*args, g, more) for g in guesses]
    ok = [t for t in tries[1:] if _track_ok(t, cfg)]
    agree = [t for t in ok if not _consistent(t, cfg, recent)]
    if agree:
        best = min(agree, key=lambda t: t.loss)
        log(f"{label}: re-localised ({_describe(best)})", flush=True)
        return best, False
    if first_ok or ok:  # nothing in line with the recent frames, but tracked: keep the best (e.g. a blurred frame)
        best = min(([r] if first_ok else []) + ok, key=lambda t: t.loss)
        log(f"{label}: kept the best attempt ({_describe(best)}): no re-localisation matched the recent frames",
            flush=True)
        return best, False
    best = max(tries, key=lambda t: (t.coverage, -t.loss))
    log(f"{label}: re-localisation failed ({_describe(best)}); frame skipped: no map is made from it and its pose "
        "in the trajectory is the best attempt's", flush=True)
    return best, True


def run_slam(stream: RGBDStream, out: Path, cfg: SlamConfig, resume: bool = False, log=print,
             force: bool = False, compile_s: float | None = None) -> dict:
    """Run SLAM over the stream, writing RUN outputs; returns the metrics dict (also RUN/metrics.json).
    compile_s: seconds the caller spent compiling the kernels beforehand (trisplat.slam.warmup), recorded as
    metrics.json `compile_seconds`; not part of the run's frames/s.

    The run rules of `trisplat train` (trisplat.run): a non-empty `out` is refused unless `force` (it is then moved
    aside, never deleted) or `resume`; a resume keeps the settings that number the frames (RESUME_FIXED); config,
    state, checkpoint and metrics are written atomically."""
    out = Path(out)
    prepare_run_dir(out, resume, force, checkpoint=CHECKPOINT)
    D = cfg.downscale
    K = stream.K_at(D)
    if not 0 <= cfg.start < len(stream):
        raise ValueError(f"--slam.start {cfg.start} is outside the capture's {len(stream)} frames "
                         f"(0 to {len(stream) - 1})")
    ids = list(range(cfg.start, len(stream), cfg.stride))
    if cfg.max_frames:
        ids = ids[: cfg.max_frames]
    record = {"capture": str(Path(stream.root).resolve()), "format": stream.format,
              "depth_scale": float(stream.depth_scale), "colour_registration": stream.colour_registration.as_option(),
              **asdict(cfg)}
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
        state.exposure = [kf.exposure for kf in keyframes] if all(kf.exposure is not None for kf in keyframes) else []
        save_checkpoint(ckpt, state, done)
        atomic_write_text(out / STATE, json.dumps({"finished": False, "step": done, "total_steps": len(ids),
                                                   "refined": state.refined}))

    keyframes: list[Keyframe] = []
    closer = LoopCloser(K, cfg.loop, state.edges, seed=cfg.seed)
    for i, k in enumerate(state.keyframe_ids):  # reload keyframe observations of a resumed run
        rgb, depth = load_frame(stream, ids[k], D)
        e = state.exposure[i] if i < len(state.exposure) else None  # solved in the final refinement
        keyframes.append(Keyframe(k, torch.from_numpy(rgb), torch.from_numpy(depth), state.c2w[k], exposure=e))
        closer.observe(rgb, depth)
    t0 = time.time() - state.elapsed_s
    t_session = time.time()
    import dataclasses

    hurried_cfg = dataclasses.replace(cfg, track=dataclasses.replace(
        cfg.track, max_iters=tuple(max(1, int(i) // 2) for i in cfg.track.max_iters), rerender_m=float("inf"),
        rerender_deg=float("inf")))
    # the next frame decodes while this one is tracked (load_frame looked up here: tests stand in for it)
    with FramePrefetch(stream, ids, D, load=load_frame) as frames:
        for n in range(start, len(ids)):
            if cfg.realtime and n > start:
                # frame n arrives (n - start) / input_fps after the session's first; behind = how late we are for it
                behind = (time.time() - t_session) - (n - start) / cfg.input_fps
                if behind > 1.0 / cfg.input_fps:  # frame n + 1 has arrived too: drop n
                    state.c2w.append(np.linalg.inv(motion_guess(state.c2w, set(state.lost))))
                    state.track_loss.append(float("nan"))
                    state.track_iters.append(0)
                    state.track_coverage.append(0.0)
                    state.dropped.append(n)
                    state.elapsed_s = time.time() - t0
                    continue
            else:
                behind = 0.0
            rgb, depth = frames.get(n)
            lost = False
            if n == 0:
                c2w = np.eye(4)
                res_loss, res_it, coverage = 0.0, 0, 0.0
            else:
                hurry = cfg.realtime and behind > 0
                state.hurried += int(hurry)
                r, lost = track_with_relocalisation(state, _pyramid(rgb, depth, K, cfg.track.levels),
                                                    hurried_cfg if hurry else cfg, n,
                                                    f"frame {n + 1}/{len(ids)} (capture frame {ids[n]})", log,
                                                    closer=closer, keyframes=keyframes)
                c2w = np.linalg.inv(r.w2c)
                res_loss, res_it, coverage = r.loss, r.iterations, r.coverage
            state.c2w.append(c2w)
            state.track_coverage.append(0.0 if lost else coverage)
            state.track_loss.append(res_loss)
            state.track_iters.append(res_it)
            if lost:
                state.lost.append(n)
            is_kf = n == 0
            # a frame with a flat (e.g. black) picture is tracked on its depth alone and never becomes a keyframe: its
            # colours would paint the map
            flat = float(rgb.std()) < 1e-3
            if flat and n:
                log(f"frame {n + 1}/{len(ids)} (capture frame {ids[n]}): flat picture (colour std {float(rgb.std()):.1e}): "
                    "tracked on its depth only, not a keyframe", flush=True)
            if not is_kf and not lost and not flat:
                last = state.c2w[state.keyframe_ids[-1]]
                rel = np.linalg.inv(last) @ c2w
                is_kf = (n - state.keyframe_ids[-1] >= cfg.keyframe_every
                         or np.linalg.norm(rel[:3, 3]) > cfg.keyframe_translation
                         or np.degrees(log_so3_angle(rel[:3, :3])) > cfg.keyframe_rotation_deg
                         or coverage < cfg.keyframe_coverage)
            if is_kf:
                state.keyframe_ids.append(n)
                keyframes.append(Keyframe(n, torch.from_numpy(rgb), torch.from_numpy(depth), c2w))
                close_loops(state, keyframes, closer, rgb, depth, f"frame {n + 1}/{len(ids)} (capture frame {ids[n]})", log)
                c2w = state.c2w[n]
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
                    + (f"dropped {len(state.dropped)}  " if cfg.realtime else "")
                    + f"elapsed {_fmt_s(state.elapsed_s)}  eta {_fmt_s((len(ids) - done) / max(rate, 1e-9))}", flush=True)
            if cfg.checkpoint_every and done % cfg.checkpoint_every == 0 and done < len(ids):
                checkpoint(done)
    slam_s = state.elapsed_s
    if cfg.realtime:
        log(f"realtime at {cfg.input_fps:g} frames/s: dropped {len(state.dropped)} of {len(ids)} frames (their poses "
            f"are constant-velocity guesses), {state.hurried} tracked with half the iterations", flush=True)
    # Soft to hard: refine over every keyframe while the window sharpens to sigma_end.
    if state.refined:
        log(f"final refinement: already done ({ckpt}); writing the outputs", flush=True)
    else:
        tf = time.time()
        for rnd in range(cfg.final_ba_rounds if len(keyframes) > 1 else 0):
            moved = bundle_adjust(state, keyframes, K, cfg, rng)
            log(f"bundle adjustment round {rnd + 1}/{cfg.final_ba_rounds}: {len(keyframes) - 1} keyframe poses "
                f"tracked again against the map (moved up to {moved * 100:.2f} cm), map refined", flush=True)
        if cfg.exposure:  # every keyframe's exposure solved against the map (the ridge holds the gauge near identity)
            for kf in keyframes:
                kf.exposure, kf.fit_exposure = identity(), True
        if cfg.final_iters:
            log(f"final refinement: {cfg.final_iters} iterations over {len(keyframes)} keyframes, "
                f"sigma {cfg.sigma} -> {cfg.sigma_end}" + (", each keyframe's exposure solved" if cfg.exposure else ""),
                flush=True)
            refine(state.smap, keyframes, K, cfg.sigma, cfg.final_iters, cfg.mapping, rng, sigma_end=cfg.sigma_end,
                   window=0)
            prune(state.smap, cfg.prune)
        if cfg.exposure and len(keyframes) > 1:
            m = regauge_map(state.smap, keyframes)
            log(f"exposure: {len(keyframes)} keyframes, gains {exposure_range(keyframes, 0)}, "
                f"biases {exposure_range(keyframes, 1)}; "
                f"the map moved to their mean (gain {np.round(m[0], 3).tolist()}, bias {np.round(m[1], 3).tolist()})",
                flush=True)
        state.final_s = time.time() - tf
        state.refined = True
        checkpoint(len(ids))  # before the outputs: a failure there resumes straight to them, not to a second refinement
    metrics = write_outputs(stream, out, cfg, state, ids, keyframes, slam_s, state.final_s, log, compile_s)
    atomic_write_text(out / STATE, json.dumps({"finished": True, "step": len(ids), "total_steps": len(ids),
                                               "refined": True}))
    return metrics


def evaluate_frames(stream: RGBDStream, smap: SlamMap, c2ws, ids, frame_numbers, cfg: SlamConfig,
                    exposure=None) -> dict:
    """PSNR / SSIM / depth L1 (metres, on pixels with valid observed depth and rendered alpha > 0.5) of the map
    rendered hard-ish (sigma_end) at the tracked poses of the given frames (numbers in the run's sequence).
    exposure: frame number -> its exposure [2,3] (interpolated between keyframes, never fitted to the scored photo),
    applied to the render; the PSNR without it is reported too ("psnr_without_exposure")."""
    from trisplat.eval.image_metrics import psnr, ssim

    K = stream.K_at(cfg.downscale)
    W, H = stream.size_at(cfg.downscale)
    ps, ss, dl, raw = [], [], [], []
    for n in frame_numbers:
        rgb, depth = load_frame(stream, ids[n], cfg.downscale)
        with torch.no_grad():
            o = smap.render(np.linalg.inv(c2ws[n]), K, W, H, cfg.sigma_end)
        img = o.rgb.clamp(0, 1)
        raw.append(psnr(img.numpy(), rgb))
        if exposure is not None:
            img = apply_exposure(img, exposure(n), o.alpha)
        img = img.numpy()
        ps.append(psnr(img, rgb))
        ss.append(ssim(img, rgb))
        a = o.alpha.numpy()
        m = (depth > 0) & (a > 0.5)
        if m.any():
            dl.append(float(np.abs(o.depth.numpy()[m] / a[m] - depth[m]).mean()))
    mean = lambda v: float(np.mean(v)) if v else None
    return {"frames": len(frame_numbers), "psnr": mean(ps), "ssim": mean(ss), "depth_l1_m": mean(dl), "lpips": None,
            "psnr_without_exposure": mean(raw) if exposure is not None else None}


def _mesh_asset(verts: np.ndarray, faces: np.ndarray, colours: np.ndarray, texture=None, exposure=None):
    """The spec renderer's asset of a mesh file's content (vertex colours, or a TextureMap), its colours seen through
    `exposure` [2,3] when given (the texels as the vertex colours: sRGB values)."""
    import dataclasses

    from trisplat.eval.spec_render import mesh_asset

    if exposure is not None:
        colours = apply_exposure(torch.from_numpy(np.asarray(colours, np.float32)), exposure).numpy()
        if texture is not None:
            img = apply_exposure(torch.from_numpy(texture.image.astype(np.float32) / 255.0), exposure).numpy()
            texture = dataclasses.replace(texture, image=np.round(img * 255.0).astype(np.uint8))
    return mesh_asset(verts, faces, colours, texture)  # the map's frame, as the cameras


def evaluate_mesh_frames(stream: RGBDStream, verts: np.ndarray, faces: np.ndarray, colours: np.ndarray, c2ws, ids,
                         frame_numbers, downscale: int, supersample: int = 2, exposure=None, texture=None) -> dict:
    """PSNR / SSIM of the mesh a user gets (sRGB vertex colours, unlit, as a viewer shows it:
    trisplat.eval.spec_render at `supersample` x `supersample` samples, black where it shows nothing) at the tracked
    poses of the given frames (numbers in the run's sequence). exposure: as evaluate_frames' (the photo's exposure
    applied to what the viewer shows; "psnr_without_exposure" without it). texture: the file's TextureMap (mesh.glb),
    if it holds one."""
    from trisplat.eval.image_metrics import psnr, ssim
    from trisplat.eval.spec_render import render_asset

    if len(faces) == 0 or not frame_numbers:
        return {"frames": 0, "psnr": None, "ssim": None}
    K = stream.K_at(downscale)
    W, H = stream.size_at(downscale)
    asset = _mesh_asset(verts, faces, colours, texture)
    ps, ss, raw = [], [], []
    for n in frame_numbers:
        rgb, _ = load_frame(stream, ids[n], downscale)
        w2c = np.linalg.inv(c2ws[n])
        img = render_asset(asset, w2c, K, W, H, background=(0.0, 0.0, 0.0), supersample=supersample)
        raw.append(psnr(img, rgb))
        if exposure is not None:  # the surface's colours as this photo's exposure shows them
            img = render_asset(_mesh_asset(verts, faces, colours, texture, exposure(n)), w2c, K, W, H,
                               background=(0.0, 0.0, 0.0), supersample=supersample)
        ps.append(psnr(img, rgb))
        ss.append(ssim(img, rgb))
    return {"frames": len(frame_numbers), "psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)),
            "supersample": supersample, "psnr_without_exposure": float(np.mean(raw)) if exposure is not None else None}


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
                         unseen_faces=cfg.mesh_unseen, min_component_fraction=cfg.mesh_min_piece,
                         max_depth_fraction=cfg.mesh_unseen_depth)
    surface, rep = soup_to_surface(smap.scene.detached(), cams, render, None, scfg,
                                   lambda m: log(f"mesh: {m}", flush=True),
                                   images=lambda n: undo_exposure(keyframes[n].rgb.numpy(), keyframes[n].exposure))
    log(f"mesh: {rep.summary()}", flush=True)
    cols = sh_dc_to_rgb(surface.sh[:, 0, :]).numpy()
    info = {"method": "the map's depth at the keyframes fused into one surface (trisplat.train.switch)",
            "switch": rep.to_dict()}
    return surface.positions.numpy().astype(np.float64), surface.faces.numpy().astype(np.int64), cols, info


@dataclass
class KeyframeViews:
    """The keyframes as the texture fit reads a training capture (trisplat.texture.asset.build_asset's `data`):
    cameras, photos (exposure undone: the colours the map holds), every keyframe a training view, black background
    (what the map shows where it has nothing)."""

    keyframes: list[Keyframe]
    cameras: list
    background: tuple = (0.0, 0.0, 0.0)

    @property
    def train_indices(self) -> list[int]:
        return list(range(len(self.keyframes)))

    def load_image(self, i: int) -> np.ndarray:
        kf = self.keyframes[i]
        return undo_exposure(kf.rgb.numpy(), kf.exposure)


def fit_mesh_colours(verts: np.ndarray, faces: np.ndarray, cols: np.ndarray, keyframes: list[Keyframe],
                     stream: RGBDStream, cfg: SlamConfig, log) -> tuple[np.ndarray, object, dict]:
    """The surface's file colours fitted to the keyframes' photos as a glTF viewer shows them, as training's are
    (build_asset): vertex colours, and a texture of cfg.texture_size when it beats them on held-out keyframes.
    Returns (vertex colours [V,3], TextureMap or None, a report)."""
    from trisplat.cameras import Camera
    from trisplat.scene.model import TriangleScene
    from trisplat.texture.asset import build_asset, choice_message

    t = time.time()
    K = stream.K_at(cfg.downscale)
    W, H = stream.size_at(cfg.downscale)
    views = KeyframeViews(keyframes, [Camera(np.linalg.inv(kf.c2w), K, W, H, name=f"keyframe {kf.frame}")
                                      for kf in keyframes])
    scene = TriangleScene.from_rgb(torch.from_numpy(np.asarray(verts, np.float32)),
                                   torch.from_numpy(np.asarray(faces, np.int32)), torch.from_numpy(cols.astype(np.float32)))
    asset = build_asset(scene, views, texture_size=cfg.texture_size)
    report = {"vertex_colours": asset.colour_report, "texture": asset.texture_report,
              "file": "texture" if asset.texture is not None else "vertex colours", "seconds": time.time() - t}
    log(f"mesh: colours fitted to the {len(keyframes)} keyframes' photos in {report['seconds']:.0f} s; mesh.glb holds "
        + (f"a {asset.texture.image.shape[1]}x{asset.texture.image.shape[0]} texture" if asset.texture is not None
           else "vertex colours") + f" ({choice_message(asset.texture_report) or 'the texture kept'})", flush=True)
    return np.clip(asset.colors, 0, 1), asset.texture, report


def write_outputs(stream, out: Path, cfg: SlamConfig, state: SlamState, ids, keyframes, slam_s, final_s, log,
                  compile_s: float | None = None) -> dict:
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
    cols = np.clip(cols, 0, 1)  # what the files hold and what is scored
    texture = None
    if len(faces) and cfg.mesh == "surface" and cfg.texture_size > 0:
        cols, texture, mesh_info["colours"] = fit_mesh_colours(verts, faces, cols, keyframes, stream, cfg, log)
    if len(faces):
        export_mesh(out / MESH, verts, faces, cols)
        export_mesh(out / MESH_GLB, verts, faces, cols, texture=texture)
        nc, lab = face_components(faces, len(verts))
        mesh_info.update(components=int(nc), largest_component_fraction=float(np.bincount(lab).max() / len(lab)))
    mesh_info["seconds"] = time.time() - tm
    kf_set = set(state.keyframe_ids)
    held = [n for n in range(len(ids)) if n not in kf_set][:: max(1, cfg.eval_every)]
    exposed = [kf for kf in keyframes if kf.exposure is not None]
    frame_exposure = None
    if cfg.exposure and len(exposed) == len(keyframes) > 0:
        kf_frames, kf_exp = [kf.frame for kf in keyframes], [kf.exposure for kf in keyframes]
        frame_exposure = lambda n: interpolate_exposure(kf_frames, kf_exp, n)  # noqa: E731
    te = time.time()
    held_map = {**evaluate_frames(stream, state.smap, state.c2w, ids, held, cfg, frame_exposure),
                "frame_numbers": [int(n) for n in held]}
    held_mesh = evaluate_mesh_frames(stream, verts, faces, cols, state.c2w, ids, held, cfg.downscale,
                                     exposure=frame_exposure)
    held_glb = (evaluate_mesh_frames(stream, verts, faces, cols, state.c2w, ids, held, cfg.downscale,
                                     exposure=frame_exposure, texture=texture) if texture is not None else held_mesh)
    eval_s = time.time() - te
    metrics = {
        "capture": str(stream.root), "format": stream.format, "frames": len(ids),
        "colour_registration": stream.colour_registration.as_dict(),
        "resolution": list(stream.size_at(cfg.downscale)), "keyframes": len(state.keyframe_ids),
        "triangles": state.smap.num_faces, "slam_seconds": slam_s, "final_refine_seconds": final_s,
        "fps": len(ids) / max(slam_s, 1e-9), "mean_track_iterations": float(np.mean(state.track_iters[1:] or [0])),
        "lost_frames": [int(n) for n in state.lost], "mesh": mesh_info,
        "realtime": ({"input_fps": cfg.input_fps, "dropped_frames": len(state.dropped), "dropped": state.dropped,
                      "hurried_frames": state.hurried} if cfg.realtime else None),
        "loop_closures": [[int(state.keyframe_ids[e.i]), int(state.keyframe_ids[e.j])] for e in state.edges if e.loop],
        "held_out": held_map, "held_out_mesh": held_mesh, "held_out_glb": held_glb,
        "exposure": ({"keyframes": [int(kf.frame) for kf in keyframes],
                      "gain": [np.round(kf.exposure[0], 4).tolist() for kf in keyframes],
                      "bias": [np.round(kf.exposure[1], 4).tolist() for kf in keyframes],
                      "held_out": "each held-out frame's exposure is interpolated between the keyframes around it "
                                  "(never fitted to the scored photo); psnr_without_exposure: the map and mesh as "
                                  "they are"} if frame_exposure is not None else None),
        "eval_seconds": eval_s,  # scoring the held-out frames (not part of SLAM: the bench reports it apart)
        "compile_seconds": compile_s,  # the kernels compiled (or loaded) before the run (trisplat.slam.warmup)
    }
    ate = ate_summary(state.c2w, [stream.frames[i].reference_c2w for i in ids])
    if ate is not None:
        metrics["ate"] = ate
        log(f"ATE RMSE {ate['rmse_m'] * 100:.2f} cm over {ate['frames']} frames (after rigid SE(3) alignment, no "
            "scale)")
    hm, hs = metrics["held_out"], metrics["held_out_mesh"]
    if hm["psnr"] is not None:
        log(f"held-out frames ({hm['frames']}, not keyframes): the map renders {hm['psnr']:.2f} dB"
            + (f", {MESH} as a viewer shows it {hs['psnr']:.2f} dB" if hs["psnr"] is not None else "")
            + (f", {MESH_GLB} (textured) {held_glb['psnr']:.2f} dB" if texture is not None else "")
            + (f" (at each frame's exposure from the keyframes around it; as they are: {hm['psnr_without_exposure']:.2f}"
               + (f" / {hs['psnr_without_exposure']:.2f}" if hs.get("psnr_without_exposure") is not None else "")
               + " dB)" if hm.get("psnr_without_exposure") is not None else ""))
    atomic_write_text(out / METRICS, json.dumps(metrics, indent=2))
    log(f"wrote {out / TRAJECTORY}, {out / MODEL}, {out / MESH} and {MESH_GLB} ({mesh_info.get('faces', 0)} faces, largest "
        f"component {mesh_info.get('largest_component_fraction', 0):.1%}), {out / METRICS}")
    return metrics
