"""RGB-D readers: colour + depth folders with a Redwood .log trajectory (Open3D intrinsics) or TUM files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from trisplat.data.capture import RawCapture, RawView, SourceCamera
from trisplat.data.images import read_image
from trisplat.data.transforms import read_json

COLOR_DIRS = ("color", "rgb", "image", "images")
DEPTH_DIRS = ("depth",)
INTRINSIC_FILES = ("camera.json", "intrinsic.json", "intrinsics.json")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DEFAULT_DEPTH_SCALE = 1.0 / 1000.0  # metres per raw unit: 16-bit PNG depth in millimetres (Redwood, ICL-NUIM)
TUM_DEPTH_SCALE = 1.0 / 5000.0  # metres per raw unit in the TUM RGB-D benchmark
TUM_MAX_TIME_DIFF = 0.02  # seconds: colour, depth and pose stamps further apart than this are not associated
POINTS_TARGET = 20_000  # back-projected depth samples kept as the capture's points (all frames together)
POINTS_MAX_FRAMES = 16  # frames (evenly spaced over the training frames) that contribute depth points
# Open3D / Redwood intrinsics put pixel centres at integers; ours are at +0.5 (docs/conventions.md).
OPEN3D_PIXEL_CENTER_SHIFT = 0.5


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def find_rgbd_layout(root: Path) -> tuple[Path, Path] | None:
    color = next((root / d for d in COLOR_DIRS if (root / d).is_dir()), None)
    depth = next((root / d for d in DEPTH_DIRS if (root / d).is_dir()), None)
    return (color, depth) if color is not None and depth is not None else None


def read_redwood_log(path: Path) -> list[np.ndarray]:
    """Camera-to-world [4,4] matrices of a Redwood .log: per entry a line 'i j frame' then 4 matrix rows."""
    lines = [l.split() for l in path.read_text(errors="replace").splitlines() if l.strip()]
    if not lines or len(lines) % 5:
        raise ValueError(
            f"{path}: malformed trajectory: expected blocks of 5 lines (header + 4x4), got {len(lines)} lines"
        )
    poses = []
    for b in range(0, len(lines), 5):
        try:
            m = np.array([[float(v) for v in row] for row in lines[b + 1 : b + 5]])
        except ValueError:
            raise ValueError(f"{path}:{b + 2}: malformed trajectory: non-numeric matrix entry") from None
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise ValueError(f"{path}:{b + 2}: malformed trajectory: entry {b // 5} is not a 4x4 matrix")
        poses.append(m)
    return poses


def read_open3d_intrinsics(path: Path) -> tuple[int, int, np.ndarray]:
    """(width, height, K in our pixel-centre convention) from an Open3D PinholeCameraIntrinsic JSON."""
    meta = read_json(path)
    try:
        w, h = int(meta["width"]), int(meta["height"])
        K = np.asarray(meta["intrinsic_matrix"], dtype=np.float64).reshape(3, 3).T  # stored column-major
    except (KeyError, TypeError, ValueError):
        raise ValueError(
            f"{path}: malformed intrinsics: need 'width', 'height' and 9 'intrinsic_matrix' values"
        ) from None
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{path}: malformed intrinsics: focal lengths must be positive and finite")
    K = K.copy()
    K[0, 2] += OPEN3D_PIXEL_CENTER_SHIFT
    K[1, 2] += OPEN3D_PIXEL_CENTER_SHIFT
    return w, h, K


def read_depth_raw(path: Path) -> np.ndarray:
    """Raw depth values as float32 [H,W] (0 = no depth)."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: depth file does not exist")
    try:
        with Image.open(path) as im:
            d = np.asarray(im, dtype=np.float32)
    except OSError as exc:
        raise ValueError(f"{path}: unreadable depth image ({exc})") from None
    if d.ndim != 2:
        raise ValueError(f"{path}: depth image must have one channel, got shape {d.shape}")
    return d


def _read_tum_list(path: Path) -> list[tuple[float, list[str]]]:
    out = []
    for no, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        toks = line.split()
        try:
            out.append((float(toks[0]), toks[1:]))
        except ValueError:
            raise ValueError(f"{path}:{no}: malformed TUM list: the first column must be a timestamp") from None
    return out


def _nearest(stamps: np.ndarray, t: float) -> int:
    return int(np.argmin(np.abs(stamps - t)))


def _tum_views(root: Path) -> tuple[list[tuple[Path, Path, np.ndarray]], list[str]]:
    rgb = _read_tum_list(root / "rgb.txt")
    depth = _read_tum_list(root / "depth.txt")
    gt = _read_tum_list(root / "groundtruth.txt")
    if not rgb or not depth or not gt:
        raise ValueError(f"{root}: empty scene: rgb.txt, depth.txt or groundtruth.txt lists nothing")
    ds = np.array([t for t, _ in depth])
    gs = np.array([t for t, _ in gt])
    out, dropped = [], 0
    for t, toks in rgb:
        i, j = _nearest(ds, t), _nearest(gs, t)
        if abs(ds[i] - t) > TUM_MAX_TIME_DIFF or abs(gs[j] - t) > TUM_MAX_TIME_DIFF:
            dropped += 1
            continue
        vals = [float(v) for v in gt[j][1][:7]]
        if len(vals) != 7:
            raise ValueError(f"{root / 'groundtruth.txt'}: malformed pose line (need tx ty tz qx qy qz qw)")
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.from_quat(vals[3:]).as_matrix()  # TUM's qx qy qz qw: scipy's scalar-last order
        c2w[:3, 3] = vals[:3]
        out.append((root / toks[0], root / depth[i][1][0], c2w))
    warnings = [f"dropped {dropped} colour frame(s) with no depth/pose within {TUM_MAX_TIME_DIFF} s"] if dropped else []
    return out, warnings


def backproject(depth_m: np.ndarray, K: np.ndarray, c2w: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """World points [N,3] and their (row, col) pixel indices [N,2] of valid depth on a stride grid."""
    H, W = depth_m.shape
    rows, cols = np.mgrid[stride // 2 : H : stride, stride // 2 : W : stride]
    z = depth_m[rows, cols]
    ok = z > 0
    rows, cols, z = rows[ok], cols[ok], z[ok]
    x = (cols + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (rows + 0.5 - K[1, 2]) / K[1, 1] * z
    pc = np.stack([x, y, z], axis=1)
    return pc @ c2w[:3, :3].T + c2w[:3, 3], np.stack([rows, cols], axis=1)


def read_rgbd(root: Path, depth_scale: float | None = None) -> RawCapture:
    """Colour + depth frames with poses: Redwood (trajectory.log + camera.json) or TUM (rgb/depth/groundtruth.txt)."""
    warnings: list[str] = []
    if (root / "rgb.txt").is_file() and (root / "groundtruth.txt").is_file():
        triples, warnings = _tum_views(root)
        intr = next((root / f for f in INTRINSIC_FILES if (root / f).is_file()), None)
        if intr is None:
            raise FileNotFoundError(f"{root}: TUM capture needs intrinsics in one of {INTRINSIC_FILES}")
        w, h, K = read_open3d_intrinsics(intr)
        scale = depth_scale or TUM_DEPTH_SCALE
        sources = [root / "rgb.txt", root / "depth.txt", root / "groundtruth.txt", intr]
    else:
        layout = find_rgbd_layout(root)
        if layout is None:
            raise FileNotFoundError(f"{root}: RGB-D capture needs colour ({'/'.join(COLOR_DIRS)}) and depth/ folders")
        color_dir, depth_dir = layout
        logs = sorted(root.glob("*.log"))
        if not logs:
            raise FileNotFoundError(f"{root}: RGB-D capture needs a Redwood trajectory (*.log)")
        intr = next((root / f for f in INTRINSIC_FILES if (root / f).is_file()), None)
        if intr is None:
            raise FileNotFoundError(f"{root}: RGB-D capture needs intrinsics in one of {INTRINSIC_FILES}")
        w, h, K = read_open3d_intrinsics(intr)
        poses = read_redwood_log(logs[0])
        colors, depths = _list_images(color_dir), _list_images(depth_dir)
        if not colors:
            raise ValueError(f"{color_dir}: empty scene: no colour images")
        if len(colors) != len(depths):
            raise ValueError(
                f"{root}: {len(colors)} colour images in {color_dir} but {len(depths)} depth images in {depth_dir}"
            )
        if len(poses) != len(colors):
            raise ValueError(f"{logs[0]}: {len(poses)} poses for {len(colors)} colour images in {color_dir}")
        triples = list(zip(colors, depths, poses))
        scale = depth_scale or DEFAULT_DEPTH_SCALE
        sources = [logs[0], intr]
    cam = SourceCamera("PINHOLE", w, h, (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    views = [
        RawView(
            name=c.name,
            world_to_camera=np.linalg.inv(c2w),
            camera=cam,
            image_path=c,
            depth_path=d,
            depth_scale=scale,
        )
        for c, d, c2w in triples
    ]
    if not views:
        raise ValueError(f"{root}: empty scene: no associated colour/depth/pose frames")
    return RawCapture(format="rgbd", root=root, views=views, warnings=warnings, source_files=sources)


def depth_points(views: list[RawView], indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """About POINTS_TARGET coloured points back-projected from the depth of up to POINTS_MAX_FRAMES views."""
    if len(indices) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    pick = indices[
        np.unique(np.linspace(0, len(indices) - 1, min(POINTS_MAX_FRAMES, len(indices))).round().astype(int))
    ]
    cam = views[pick[0]].camera
    per_frame = POINTS_TARGET / len(pick)
    stride = max(1, int(np.sqrt(cam.width * cam.height / per_frame)))
    pts, cols = [], []
    for i in pick:
        v = views[i]
        d = read_depth_raw(v.depth_path) * v.depth_scale
        if d.shape != (v.camera.height, v.camera.width):
            raise ValueError(
                f"{v.depth_path}: depth is {d.shape[1]}x{d.shape[0]} but the camera is {v.camera.width}x{v.camera.height}"
            )
        img = read_image(v.image_path)
        p, rc = backproject(d, v.camera.pinhole_K(), np.linalg.inv(v.world_to_camera), stride)
        pts.append(p)
        cols.append(img[rc[:, 0], rc[:, 1], :3].astype(np.float32) / 255.0)
    return np.concatenate(pts), np.concatenate(cols)
