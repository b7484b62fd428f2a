"""Open3D's own dense RGB-D SLAM as a second benchmark baseline: `open3d.t.pipelines.slam.Model`, frame-to-model
tracking (point-to-plane ICP of each frame's depth against the depth ray-cast from the voxel-block TSDF at the last
pose) with every frame fused into the voxel block grid, then the grid's mesh. This is the loop of Open3D's
examples/python/t_reconstruction_system/dense_slam.py at that example's defaults (default_config.yml): voxel
0.0058 m, 16^3 voxel blocks, 40000 blocks pre-allocated, truncation 8 voxels, depth 0.1-3.0 m, correspondences
within 0.07 m, mesh at surface weight 3. The example does nothing when tracking fails; neither does this runner (each
frame's ICP fitness and RMSE are recorded, and the count of frames with no correspondence at all; Open3D raises on
a singular 6x6 system, where the example would stop: such a frame keeps the previous pose and is counted so).

Frames are chosen as `trisplat slam` chooses them (trisplat.slam.open3d_baseline.frame_ids) and loaded by the same
reader at the same 1/downscale, colour registered as the bench says, depth handed over in millimetres (uint16, depth
scale 1000, as the example reads its PNGs). Open3D is a benchmark dependency only (the `bench` extra).
Usage: python -m trisplat.slam.open3d_dense_slam CAPTURE --out DIR [--downscale 2] [--max-frames N] [--stride S]
[--start K] (`trisplat bench slam --methods open3d-slam` runs it beside the others).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from trisplat.data.rgbd_stream import open_stream
from trisplat.slam.open3d_baseline import _intrinsic, _load_frames, _o3d, frame_ids, largest_component_fraction
from trisplat.slam.trajectory import ate_summary, write_tum_trajectory


@dataclass
class DenseSlamConfig:
    """The dense-SLAM example's settings (Open3D's t_reconstruction_system/default_config.yml)."""

    voxel_m: float = 0.0058
    block_resolution: int = 16
    block_count: int = 40000
    depth_min_m: float = 0.1
    depth_max_m: float = 3.0
    trunc_voxel_multiplier: float = 8.0
    odometry_distance_m: float = 0.07
    surface_weight: float = 3.0

    def check(self) -> None:
        bad = [f"{k}={v}" for k, v in asdict(self).items() if not (np.isfinite(v) and v > 0)]
        if bad:
            raise ValueError(f"Open3D dense SLAM settings must be positive: {', '.join(bad)}")
        if self.depth_min_m >= self.depth_max_m:
            raise ValueError(f"Open3D dense SLAM: depth_min_m {self.depth_min_m} must be below depth_max_m "
                             f"{self.depth_max_m}")


MIN_WIDTH, MIN_HEIGHT = 160, 120


def track_sequence(o3d, frames, intrinsic, cfg: DenseSlamConfig, log=print) -> tuple[list[np.ndarray], list, object]:
    """Frame-to-model SLAM over (rgb uint8 [h,w,3], depth float32 metres [h,w]) frames: the first frame is the world
    (identity), each later one is tracked against the model ray-cast at the previous pose, then fused. Returns
    (camera-to-world 4x4 per frame, per-frame (fitness, inlier RMSE) or None for the first, the slam.Model)."""
    cfg.check()
    dev = o3d.core.Device("CPU:0")
    K = o3d.core.Tensor(np.asarray(intrinsic.intrinsic_matrix, np.float64))
    H, W = frames[0][1].shape
    if W < MIN_WIDTH or H < MIN_HEIGHT:
        # measured: on the tests' 80x60 frames its first ray-cast reports "allocated 0 fragments" and never
        # returns; 160x120 and 320x240 run
        raise ValueError(f"Open3D's dense SLAM needs frames of at least {MIN_WIDTH}x{MIN_HEIGHT} (it hangs in its "
                         f"ray-cast on smaller ones); these are {W}x{H}: use a smaller downscale "
                         "(`trisplat bench slam --open3d-slam-downscale`)")
    pose = o3d.core.Tensor(np.eye(4))
    model = o3d.t.pipelines.slam.Model(cfg.voxel_m, cfg.block_resolution, cfg.block_count, pose, dev)
    current = o3d.t.pipelines.slam.Frame(H, W, K, dev)
    raycast = o3d.t.pipelines.slam.Frame(H, W, K, dev)
    c2w, quality = [], []
    t0 = time.time()
    for k, (rgb, depth) in enumerate(frames):
        if depth.shape != (H, W) or rgb.shape[:2] != (H, W):
            raise ValueError(f"frame {k}: {rgb.shape[1]}x{rgb.shape[0]} colour / {depth.shape[1]}x{depth.shape[0]} "
                             f"depth, expected {W}x{H}")
        mm = np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16)
        current.set_data_from_image("depth", o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(mm))))
        current.set_data_from_image("color", o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(rgb))))
        if k > 0:
            try:
                res = model.track_frame_to_model(current, raycast, 1000.0, cfg.depth_max_m, cfg.odometry_distance_m)
            except RuntimeError as exc:  # "Singular 6x6 linear system detected, tracking failed": the example stops
                if "tracking failed" not in str(exc):
                    raise
                quality.append((0.0, float("nan")))  # counted as a frame without correspondences; pose kept
            else:
                pose = pose @ res.transformation
                quality.append((float(res.fitness), float(res.inlier_rmse)))
        else:
            quality.append(None)
        c2w.append(pose.cpu().numpy().astype(np.float64))
        model.update_frame_pose(k, pose)
        model.integrate(current, 1000.0, cfg.depth_max_m, cfg.trunc_voxel_multiplier)
        model.synthesize_model_frame(raycast, 1000.0, cfg.depth_min_m, cfg.depth_max_m, cfg.trunc_voxel_multiplier,
                                     False)
        if (k + 1) % 50 == 0:
            log(f"open3d dense slam: frame {k + 1}/{len(frames)}  {(k + 1) / (time.time() - t0):.2f} fps", flush=True)
    return c2w, quality, model


def extract_mesh(o3d, model, cfg: DenseSlamConfig):
    """The model's TSDF mesh (legacy TriangleMesh, vertex colours in [0, 1]) at the example's surface weight."""
    mesh = model.extract_trianglemesh(weight_threshold=cfg.surface_weight).to_legacy()
    if mesh.has_vertex_colors():
        cols = np.asarray(mesh.vertex_colors)
        if cols.size and cols.max() > 1.0 + 1e-6:  # the grid keeps colour in 0..255
            mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(cols / 255.0, 0.0, 1.0))
    return mesh


def run(capture: Path, out: Path, downscale: int = 2, max_frames: int = 0, stride: int = 1, start: int = 0,
        depth_scale: float | None = None, log=print, colour_registration: str = "off",
        cfg: DenseSlamConfig | None = None) -> dict:
    """Open3D dense SLAM over the selected frames; writes OUT/trajectory.txt (TUM), OUT/mesh.ply, OUT/metrics.json;
    returns the metrics dict (seconds: tracking + fusion, and the mesh extraction, apart from loading)."""
    from trisplat.data.colour_registration import apply_colour_registration

    cfg = cfg or DenseSlamConfig()
    cfg.check()
    o3d = _o3d()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stream = open_stream(capture, depth_scale=depth_scale)
    reg = apply_colour_registration(stream, colour_registration)
    ids = frame_ids(len(stream), max_frames, stride, start)
    if len(ids) < 2:
        raise ValueError(f"{capture}: {len(ids)} frame(s) selected (start {start}, stride {stride}, max frames "
                         f"{max_frames}, {len(stream)} in the capture): dense SLAM needs at least 2")
    W, H = stream.size_at(downscale)
    intrinsic, _ = _intrinsic(o3d, stream, downscale)
    t_load = time.time()
    frames = _load_frames(stream, ids, downscale)
    load_s = time.time() - t_load
    t0 = time.time()
    c2w, quality, model = track_sequence(o3d, frames, intrinsic, cfg, log)
    slam_s = time.time() - t0
    t1 = time.time()
    mesh = extract_mesh(o3d, model, cfg)
    mesh_s = time.time() - t1
    stamps = [stream.frames[i].stamp if stream.frames[i].stamp is not None else float(i) for i in ids]
    write_tum_trajectory(out / "trajectory.txt", stamps, c2w)
    o3d.io.write_triangle_mesh(str(out / "mesh.ply"), mesh)
    fit = np.array([q[0] for q in quality[1:]])
    res = {
        "method": "open3d.t.pipelines.slam (frame-to-model, Open3D's dense_slam.py example defaults)",
        "capture": str(capture), "frames": len(ids), "start": start, "stride": max(1, stride),
        "resolution": [W, H], "colour_registration": reg.as_dict(), "settings": asdict(cfg),
        "load_seconds": load_s, "slam_seconds": slam_s, "mesh_seconds": mesh_s, "seconds": slam_s + mesh_s,
        "fps": len(ids) / max(slam_s, 1e-9),
        "tracking": {"fitness_median": float(np.median(fit)), "fitness_min": float(fit.min()),
                     "frames_without_correspondences": int((fit <= 0).sum()),
                     "inlier_rmse_median_m": float(np.nanmedian([q[1] for q in quality[1:]]))},
        "mesh": {"faces": len(mesh.triangles), "vertices": len(mesh.vertices),
                 "largest_component_fraction": largest_component_fraction(o3d, mesh) if len(mesh.triangles) else 0.0},
        "open3d": o3d.__version__,
    }
    ate = ate_summary(c2w, [stream.frames[i].reference_c2w for i in ids])
    if ate is not None:
        res["ate"] = ate
    (out / "metrics.json").write_text(json.dumps(res, indent=2))
    log(json.dumps({k: res[k] for k in ("frames", "resolution", "fps", "tracking", "mesh", "ate") if k in res}))
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m trisplat.slam.open3d_dense_slam", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--max-frames", type=int, default=0)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--start", type=int, default=0, help="first capture frame used")
    ap.add_argument("--depth-scale", type=float, default=None)
    ap.add_argument("--colour-registration", default="off", help="'auto', 'off' or 'SCALE,DX,DY' (trisplat slam's)")
    a = ap.parse_args(argv)
    run(a.capture, a.out, a.downscale, a.max_frames, a.stride, a.start, a.depth_scale,
        colour_registration=a.colour_registration)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
