"""The Open3D baseline for `trisplat slam` benchmarks: frame-to-frame RGB-D odometry (hybrid photometric + geometric
term) chained into a trajectory, and TSDF fusion of the same frames into a mesh; also a TSDF mesh fused
with the capture's reference poses (the geometry reference both systems' meshes are compared with).

Open3D is a benchmark dependency only (`pip install open3d-cpu==0.20.0`, the `bench` extra); nothing in trisplat
imports it at run time. Frames are chosen as `trisplat slam` chooses them (every stride-th, then the first max-frames).
Usage: python -m trisplat.slam.open3d_baseline CAPTURE --out DIR [--downscale 2] [--max-frames N] [--stride S]
(`trisplat bench slam` runs it beside `trisplat slam`).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from trisplat.data.rgbd_stream import load_frame, open_stream
from trisplat.slam.trajectory import ate_summary, write_tum_trajectory

VOXEL_M = 0.01  # TSDF voxel edge (metres)
SDF_TRUNC_M = 0.04  # TSDF truncation distance (metres): 4 voxels
DEPTH_TRUNC_M = 4.0  # depth beyond this is not used (metres)
MAX_VOXELS_PER_SIDE = 400  # the uniform TSDF grid is at most this many voxels per side (coarser voxels beyond)


MISSING_OPEN3D = ("the Open3D baseline needs open3d: pip install open3d-cpu==0.20.0 (or pip install -e '.[bench]'; "
                  "a benchmark-only dependency)")
# system libraries the open3d wheels load but do not ship, and the Debian / Ubuntu package that installs each (Open3D's
# docs list libegl1, libgl1, libgomp1; a fresh Debian machine also lacks libusb-1.0-0)
SYSTEM_LIBRARIES = {"libusb-1.0": "libusb-1.0-0", "libGL.so": "libgl1", "libgomp": "libgomp1", "libEGL": "libegl1"}


def open3d_load_error(exc: BaseException) -> str:
    """What to do when open3d is installed but fails to import: a shared library it needs is missing (the message
    names the library; for the known ones also the system package, e.g. `sudo apt install libusb-1.0-0`)."""
    text = str(exc)
    for lib, package in SYSTEM_LIBRARIES.items():
        if lib.lower() in text.lower():
            return (f"open3d is installed but cannot load: {text}. It needs the system library {lib}, which its wheel "
                    f"does not ship: sudo apt install {package} (Debian / Ubuntu)")
    return (f"open3d is installed but cannot load: {text} (a system library missing? the message names it; "
            f"or reinstall: pip install --force-reinstall open3d-cpu==0.20.0)")


def _o3d():
    """The open3d module, imported lazily. ImportError naming `pip install open3d-cpu` when it is not installed,
    and the missing system library and its package when it is installed but cannot load (libusb on a fresh
    Debian machine: ImportError or OSError from the loader)."""
    try:
        import open3d as o3d
    except ModuleNotFoundError as exc:
        if exc.name not in (None, "open3d"):  # open3d itself is there; something it imports is not
            raise ImportError(open3d_load_error(exc)) from None
        raise ImportError(MISSING_OPEN3D) from None
    except (ImportError, OSError) as exc:
        raise ImportError(open3d_load_error(exc)) from None
    return o3d


def frame_ids(n_frames: int, max_frames: int = 0, stride: int = 1, start: int = 0) -> list[int]:
    """The capture frames used: every stride-th from frame `start`, then the first max_frames (0 = all), as
    trisplat.slam.system."""
    if start < 0 or (n_frames and start >= n_frames):
        raise ValueError(f"start frame {start} is outside the capture's {n_frames} frames (0 to {n_frames - 1})")
    ids = list(range(start, n_frames, max(1, stride)))
    return ids[:max_frames] if max_frames else ids


def _intrinsic(o3d, stream, downscale: int):
    W, H = stream.size_at(downscale)
    K = stream.K_at(downscale)
    # Open3D puts pixel centres at integers; ours are at +0.5 (docs/conventions.md).
    return o3d.camera.PinholeCameraIntrinsic(W, H, K[0, 0], K[1, 1], K[0, 2] - 0.5, K[1, 2] - 0.5), K


def _load_frames(stream, ids, downscale: int) -> list:
    frames = []
    for i in ids:
        rgb, depth = load_frame(stream, i, downscale)
        frames.append((np.ascontiguousarray((rgb * 255 + 0.5).astype(np.uint8)), np.ascontiguousarray(depth)))
    return frames


def reference_tsdf_mesh(capture: Path, out_ply: Path, downscale: int = 2, max_frames: int = 0, stride: int = 1,
                        depth_scale: float | None = None, voxel_m: float = VOXEL_M, start: int = 0) -> dict:
    """TSDF mesh of the selected frames fused at the capture's reference poses (frames without one are skipped),
    written to out_ply: the geometry reference both SLAM meshes are compared with. Returns its facts."""
    o3d = _o3d()
    stream = open_stream(capture, depth_scale=depth_scale)
    ids = [i for i in frame_ids(len(stream), max_frames, stride, start) if stream.frames[i].reference_c2w is not None]
    if not ids:
        raise ValueError(f"{capture}: no reference poses among the selected frames: no reference mesh")
    t0 = time.time()
    intrinsic, K = _intrinsic(o3d, stream, downscale)
    rm = tsdf_mesh(o3d, _load_frames(stream, ids, downscale), [stream.frames[i].reference_c2w for i in ids],
                   intrinsic, K, voxel_m)
    Path(out_ply).parent.mkdir(parents=True, exist_ok=True)
    o3d.io.write_triangle_mesh(str(out_ply), rm)
    return {"path": str(out_ply), "frames": len(ids), "faces": len(rm.triangles), "vertices": len(rm.vertices),
            "voxel_m": voxel_m, "seconds": time.time() - t0}


def _bounds(frames, c2ws, K, stride: int = 8, every: int = 10, sdf_trunc: float = SDF_TRUNC_M):
    """Box [2,3] (world, metres) of the depth points of every `every`-th frame under the given poses."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for (_, depth), c2w in list(zip(frames, c2ws))[::every]:
        v, u = np.nonzero(depth[::stride, ::stride] > 0)
        z = depth[::stride, ::stride][v, u]
        z = z[z < DEPTH_TRUNC_M]
        if not len(z):
            continue
        v, u = v[: len(z)] * stride, u[: len(z)] * stride
        p = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * z, (v + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1)
        p = p @ c2w[:3, :3].T + c2w[:3, 3]
        lo, hi = np.minimum(lo, p.min(0)), np.maximum(hi, p.max(0))
    return np.stack([lo - 2 * sdf_trunc, hi + 2 * sdf_trunc])


def tsdf_mesh(o3d, frames, c2ws, intrinsic, K, voxel_m: float = VOXEL_M):
    """Fuse (rgb uint8, depth float32 metres) frames at camera-to-world poses; returns an Open3D TriangleMesh.

    A UniformTSDFVolume over the frames' box: with open3d-cpu 0.20.0 on the benchmark machine, ScalableTSDFVolume
    and the tensor VoxelBlockGrid both returned empty meshes even for a single frame at the identity pose."""
    sdf_trunc = SDF_TRUNC_M * voxel_m / VOXEL_M
    box = _bounds(frames, c2ws, K, sdf_trunc=sdf_trunc)
    length = float((box[1] - box[0]).max())
    res = int(min(MAX_VOXELS_PER_SIDE, np.ceil(length / voxel_m)))
    vol = o3d.pipelines.integration.UniformTSDFVolume(
        length=length, resolution=res, sdf_trunc=sdf_trunc,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8, origin=box[0].reshape(3, 1))
    for (rgb, depth), c2w in zip(frames, c2ws):
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(rgb), o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=DEPTH_TRUNC_M,
            convert_rgb_to_intensity=False)
        vol.integrate(rgbd, intrinsic, np.linalg.inv(c2w))
    return vol.extract_triangle_mesh()


def largest_component_fraction(o3d, mesh) -> float:
    labels, counts, _ = mesh.cluster_connected_triangles()
    counts = np.asarray(counts)
    return float(counts.max() / counts.sum()) if counts.size else 0.0


def run(capture: Path, out: Path, downscale: int = 2, max_frames: int = 0, reference_mesh: bool = True,
        stride: int = 1, depth_scale: float | None = None, log=print, voxel_m: float = VOXEL_M,
        colour_registration: str = "off", start: int = 0) -> dict:
    """Odometry + TSDF over the selected frames; writes OUT/trajectory.txt (TUM), OUT/mesh.ply, OUT/metrics.json
    (and OUT/reference_tsdf_mesh.ply with reference_mesh); returns the metrics dict. colour_registration: as
    `trisplat slam --colour-registration` (the bench gives both methods the same colour)."""
    from trisplat.data.colour_registration import apply_colour_registration

    o3d = _o3d()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stream = open_stream(capture, depth_scale=depth_scale)
    reg = apply_colour_registration(stream, colour_registration)
    ids = frame_ids(len(stream), max_frames, stride, start)
    n = len(ids)
    W, H = stream.size_at(downscale)
    intrinsic, K = _intrinsic(o3d, stream, downscale)
    t_load = time.time()
    frames = _load_frames(stream, ids, downscale)
    load_s = time.time() - t_load

    t0 = time.time()
    option = o3d.pipelines.odometry.OdometryOption()
    option.depth_max = DEPTH_TRUNC_M
    jac = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd_intensity(k):
        rgb, depth = frames[k]
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(rgb), o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=DEPTH_TRUNC_M,
            convert_rgb_to_intensity=True)

    c2w = [np.eye(4)]
    failures = 0
    prev = rgbd_intensity(0)
    velocity = np.eye(4)
    for k in range(1, n):
        cur = rgbd_intensity(k)
        # source = frame k, target = frame k-1: T maps frame-k camera points into frame k-1 (constant-velocity init)
        ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(cur, prev, intrinsic, velocity, jac, option)
        if not ok:
            failures += 1
            T = velocity
        velocity = T
        c2w.append(c2w[-1] @ T)
        prev = cur
        if (k + 1) % 50 == 0:
            log(f"odometry frame {k + 1}/{n}  {(k + 1) / (time.time() - t0):.1f} fps", flush=True)
    odo_s = time.time() - t0
    t1 = time.time()
    mesh = tsdf_mesh(o3d, frames, c2w, intrinsic, K, voxel_m)
    tsdf_s = time.time() - t1
    stamps = [stream.frames[i].stamp if stream.frames[i].stamp is not None else float(i) for i in ids]
    write_tum_trajectory(out / "trajectory.txt", stamps, c2w)
    o3d.io.write_triangle_mesh(str(out / "mesh.ply"), mesh)
    res = {
        "capture": str(capture), "frames": n, "start": start, "stride": max(1, stride), "resolution": [W, H],
        "odometry_failures": failures,
        "colour_registration": reg.as_dict(),
        "load_seconds": load_s, "odometry_seconds": odo_s, "tsdf_seconds": tsdf_s, "seconds": odo_s + tsdf_s,
        "mesh": {"faces": len(mesh.triangles), "vertices": len(mesh.vertices),
                 "largest_component_fraction": largest_component_fraction(o3d, mesh)},
        "tsdf": {"volume": "UniformTSDFVolume", "voxel_m": voxel_m, "sdf_trunc_m": SDF_TRUNC_M * voxel_m / VOXEL_M,
                 "depth_trunc_m": DEPTH_TRUNC_M},
        "open3d": o3d.__version__,
    }
    ref = [stream.frames[i].reference_c2w for i in ids]
    have = [k for k, r in enumerate(ref) if r is not None]
    if len(have) >= 3:
        res["ate"] = ate_summary(c2w, ref)
        if reference_mesh:
            t2 = time.time()
            rm = tsdf_mesh(o3d, [frames[k] for k in have], [ref[k] for k in have], intrinsic, K, voxel_m)
            o3d.io.write_triangle_mesh(str(out / "reference_tsdf_mesh.ply"), rm)
            res["reference_tsdf_mesh"] = {"path": str(out / "reference_tsdf_mesh.ply"), "faces": len(rm.triangles),
                                          "seconds": time.time() - t2}
    (out / "metrics.json").write_text(json.dumps(res, indent=2))
    log(json.dumps(res, indent=2))
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m trisplat.slam.open3d_baseline", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--max-frames", type=int, default=0)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--depth-scale", type=float, default=None)
    ap.add_argument("--no-reference-mesh", action="store_true")
    ap.add_argument("--colour-registration", default="off", help="'auto', 'off' or 'SCALE,DX,DY' (trisplat slam's)")
    a = ap.parse_args(argv)
    run(a.capture, a.out, a.downscale, a.max_frames, not a.no_reference_mesh, a.stride, a.depth_scale,
        colour_registration=a.colour_registration)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
