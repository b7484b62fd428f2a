"""RGB-D streams for SLAM: frames in order (colour, depth, timestamp, optional reference pose) from TUM RGB-D,
ETH3D SLAM, ScanNet (SensReader export), 7-Scenes / 3DMatch frame folders and the Redwood/ICL layout; decoding of one
frame at a chosen resolution."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from trisplat.data.colour_registration import IDENTITY, ColourRegistration, register_colour
from trisplat.data.images import image_size, read_image
from trisplat.data.rgbd import (
    INTRINSIC_FILES,
    TUM_DEPTH_SCALE,
    _read_tum_list,
    read_depth_raw,
    read_open3d_intrinsics,
)

SEVENSCENES_DEPTH_SCALE = 1.0 / 1000.0  # metres per raw unit: 7-Scenes / 3DMatch depth PNGs are in millimetres
INVALID_DEPTH_RAW = (0, 65535)  # raw 16-bit depth values that mean "no measurement"
TUM_ASSOC_MAX_DT = 0.02  # seconds: colour/depth (and reference pose) stamps further apart are not associated
# OpenCV-style K files (7-Scenes camera-intrinsics.txt, TUM's published values) put pixel centres at integers;
# ours are at +0.5 (docs/conventions.md).
INTEGER_CENTRE_SHIFT = 0.5
# Published TUM RGB-D colour intrinsics (fx, fy, cx, cy; integer-centred), chosen by the sequence folder's name.
TUM_FREIBURG_INTRINSICS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
SEVENSCENES_COLOR = re.compile(r"^frame-(\d+)\.color\.(jpg|jpeg|png)$", re.IGNORECASE)


@dataclass(frozen=True)
class StreamFrame:
    """One RGB-D frame: files, timestamp (seconds; None when the format has none) and the capture's reference
    camera-to-world [4,4] (OpenCV axes, metres) or None."""

    index: int
    color_path: Path
    depth_path: Path
    stamp: float | None = None
    reference_c2w: np.ndarray | None = None


@dataclass
class RGBDStream:
    """An ordered RGB-D sequence with one pinhole camera, the depth camera's, shared by colour once registered to it
    (load_frame resamples colour when colour_registration is applied; trisplat.data.colour_registration).

    K: float64 [3,3] at width x height, pixel centres at +0.5. depth_scale: metres per raw depth unit.
    """

    format: str
    root: Path
    frames: list[StreamFrame]
    width: int
    height: int
    K: np.ndarray
    depth_scale: float
    warnings: list[str] = field(default_factory=list)
    resize_color: bool = False
    """colour images are resampled to width x height (the depth's size) when read (ScanNet: 1296x968 colour, 640x480
    depth)"""
    colour_registration: ColourRegistration = IDENTITY
    """how colour maps onto the depth camera's pixels (trisplat.data.colour_registration); load_frame resamples colour
    into the depth camera when applied"""

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def has_reference(self) -> bool:
        return any(f.reference_c2w is not None for f in self.frames)

    def K_at(self, downscale: int) -> np.ndarray:
        """K for images downscaled by an integer factor (corner-based: fx, fy, cx, cy divided by the factor)."""
        K = self.K.copy()
        K[:2] /= downscale
        return K

    def size_at(self, downscale: int) -> tuple[int, int]:
        return self.width // downscale, self.height // downscale


def _read_k_txt(path: Path) -> np.ndarray:
    try:
        K = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: malformed intrinsics: expected a 3x3 matrix of numbers ({exc})") from None
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{path}: malformed intrinsics: expected a 3x3 matrix with positive focal lengths")
    K = K.copy()
    K[0, 2] += INTEGER_CENTRE_SHIFT
    K[1, 2] += INTEGER_CENTRE_SHIFT
    return K


def _read_pose_txt(path: Path) -> np.ndarray | None:
    """A 4x4 camera-to-world matrix; None for 7-Scenes' placeholder of invalid poses (non-finite entries)."""
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: malformed pose: expected a 4x4 matrix of numbers ({exc})") from None
    if m.shape != (4, 4):
        raise ValueError(f"{path}: malformed pose: expected a 4x4 matrix, got shape {m.shape}")
    return m if np.isfinite(m).all() else None


def read_sevenscenes(root: Path, depth_scale: float | None = None) -> RGBDStream:
    """7-Scenes / 3DMatch frames: frame-NNNNNN.color.{jpg,png} + frame-NNNNNN.depth.png (+ .pose.txt),
    camera-intrinsics.txt (3x3, integer-centred principal point). Depth in millimetres unless depth_scale is given."""
    root = Path(root)
    colors = sorted(
        ((int(m.group(1)), p) for p in root.iterdir() if (m := SEVENSCENES_COLOR.match(p.name))), key=lambda t: t[0]
    )
    if not colors:
        raise FileNotFoundError(f"{root}: no frame-NNNNNN.color.jpg|png files (7-Scenes / 3DMatch layout)")
    intr = root / "camera-intrinsics.txt"
    if not intr.is_file():
        raise FileNotFoundError(f"{intr}: 7-Scenes capture needs camera-intrinsics.txt (3x3 K)")
    K = _read_k_txt(intr)
    frames, missing_pose = [], 0
    for i, (_num, cpath) in enumerate(colors):
        stem = cpath.name[: cpath.name.lower().index(".color.")]
        dpath = root / f"{stem}.depth.png"
        if not dpath.is_file():
            raise FileNotFoundError(f"{dpath}: depth file of {cpath.name} does not exist")
        ppath = root / f"{stem}.pose.txt"
        pose = _read_pose_txt(ppath) if ppath.is_file() else None
        missing_pose += pose is None
        frames.append(StreamFrame(index=i, color_path=cpath, depth_path=dpath, stamp=None, reference_c2w=pose))
    w, h = image_size(frames[0].color_path)
    warnings = []
    if 0 < missing_pose < len(frames):
        warnings.append(f"{missing_pose} of {len(frames)} frames have no (valid) reference pose")
    return RGBDStream("7scenes", root, frames, w, h, K, depth_scale or SEVENSCENES_DEPTH_SCALE, warnings)


def _tum_intrinsics(root: Path) -> np.ndarray:
    intr = next((root / f for f in INTRINSIC_FILES if (root / f).is_file()), None)
    if intr is not None:
        return read_open3d_intrinsics(intr)[2]
    if (root / "camera-intrinsics.txt").is_file():
        return _read_k_txt(root / "camera-intrinsics.txt")
    for key, (fx, fy, cx, cy) in TUM_FREIBURG_INTRINSICS.items():
        if key in root.resolve().name:
            return np.array([[fx, 0, cx + INTEGER_CENTRE_SHIFT], [0, fy, cy + INTEGER_CENTRE_SHIFT], [0, 0, 1.0]])
    raise FileNotFoundError(
        f"{root}: TUM capture needs intrinsics: one of {INTRINSIC_FILES}, camera-intrinsics.txt, or a folder name "
        f"containing {'/'.join(TUM_FREIBURG_INTRINSICS)}"
    )


def _associate(query: np.ndarray, stamps: np.ndarray, max_dt: float) -> np.ndarray:
    """Index of the nearest stamp per query stamp, -1 where the nearest is further than max_dt."""
    order = np.argsort(stamps)
    s = stamps[order]
    j = np.clip(np.searchsorted(s, query), 1, len(s) - 1) if len(s) > 1 else np.zeros(len(query), int)
    if len(s) > 1:
        j = np.where(np.abs(s[j - 1] - query) <= np.abs(s[j] - query), j - 1, j)
    out = order[j]
    return np.where(np.abs(stamps[out] - query) <= max_dt, out, -1)


def read_tum(root: Path, depth_scale: float | None = None, max_dt: float = TUM_ASSOC_MAX_DT,
             K: np.ndarray | None = None) -> RGBDStream:
    """TUM RGB-D: rgb.txt and depth.txt (stamp + relative path per line) associated by nearest timestamp within
    max_dt seconds; groundtruth.txt (stamp tx ty tz qx qy qz qw, camera-to-world), if present, gives the
    reference poses. Colour frames with no depth in time are dropped with a warning; none matched is an error."""
    root = Path(root)
    rgb_txt, depth_txt, gt_txt = root / "rgb.txt", root / "depth.txt", root / "groundtruth.txt"
    for p in (rgb_txt, depth_txt):
        if not p.is_file():
            raise FileNotFoundError(f"{p}: TUM capture needs rgb.txt and depth.txt")
    rgb, depth = _read_tum_list(rgb_txt), _read_tum_list(depth_txt)
    for p, lst in ((rgb_txt, rgb), (depth_txt, depth)):
        if not lst:
            raise ValueError(f"{p}: lists no frames")
        bad = next((k for k, (_, toks) in enumerate(lst) if not toks), None)
        if bad is not None:
            raise ValueError(f"{p}: entry {bad} (stamp {lst[bad][0]}) has no file name")
    rs = np.array([t for t, _ in rgb])
    ds = np.array([t for t, _ in depth])
    di = _associate(rs, ds, max_dt)
    if (di < 0).all():
        raise ValueError(
            f"{depth_txt}: unmatched timestamps: no depth stamp within {max_dt} s of any colour stamp in {rgb_txt} "
            f"(colour {rs.min():.3f}-{rs.max():.3f} s, depth {ds.min():.3f}-{ds.max():.3f} s)"
        )
    gi = np.full(len(rs), -1)
    gt = []
    if gt_txt.is_file():
        gt = _read_tum_list(gt_txt)
        for k, (_, toks) in enumerate(gt):
            if len(toks) < 7:
                raise ValueError(f"{gt_txt}: entry {k}: malformed pose (need stamp tx ty tz qx qy qz qw)")
        if gt:
            gi = _associate(rs, np.array([t for t, _ in gt]), max_dt)
    frames = []
    for k in np.nonzero(di >= 0)[0]:
        cpath, dpath = root / rgb[k][1][0], root / depth[di[k]][1][0]
        for p, lst in ((cpath, rgb_txt), (dpath, depth_txt)):
            if not p.is_file():
                raise FileNotFoundError(f"{p}: listed in {lst} but does not exist")
        pose = None
        if gi[k] >= 0:
            vals = [float(v) for v in gt[gi[k]][1][:7]]
            pose = np.eye(4)
            pose[:3, :3] = Rotation.from_quat(vals[3:]).as_matrix()  # TUM's qx qy qz qw: scalar last, as scipy
            pose[:3, 3] = vals[:3]
        frames.append(StreamFrame(len(frames), cpath, dpath, float(rs[k]), pose))
    warnings = []
    if (di < 0).any():
        warnings.append(f"dropped {int((di < 0).sum())} colour frame(s) of {rgb_txt} with no depth within {max_dt} s")
    w, h = image_size(frames[0].color_path)
    return RGBDStream("tum", root, frames, w, h, _tum_intrinsics(root) if K is None else K,
                      depth_scale or TUM_DEPTH_SCALE, warnings)


def read_eth3d(root: Path, depth_scale: float | None = None, max_dt: float = TUM_ASSOC_MAX_DT) -> RGBDStream:
    """ETH3D SLAM: the TUM lists (rgb.txt, depth.txt, groundtruth.txt when given; depth PNGs at 1/5000 m) and
    calibration.txt with one line 'fx fy cx cy' (pixel centres at +0.5, the COLMAP convention of ETH3D's data)."""
    root = Path(root)
    cal = root / "calibration.txt"
    try:
        vals = [float(v) for v in cal.read_text().split()]
    except OSError as exc:
        raise FileNotFoundError(f"{cal}: ETH3D SLAM capture needs calibration.txt ({exc.strerror})") from None
    except ValueError:
        raise ValueError(f"{cal}: malformed calibration: expected 'fx fy cx cy' (4 numbers)") from None
    if len(vals) != 4 or vals[0] <= 0 or vals[1] <= 0:
        raise ValueError(f"{cal}: malformed calibration: expected 'fx fy cx cy' (4 numbers, positive focal lengths), "
                         f"got {len(vals)} numbers")
    fx, fy, cx, cy = vals
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    tum = read_tum(root, depth_scale, max_dt, K=K)
    tum.format = "eth3d"
    return tum


SCANNET_FRAME = re.compile(r"^(\d+)\.(jpg|jpeg|png)$", re.IGNORECASE)


def read_scannet(root: Path, depth_scale: float | None = None) -> RGBDStream:
    """ScanNet as exported by its SensReader: color/N.jpg, depth/N.png (millimetres), pose/N.txt (4x4
    camera-to-world; '-inf' rows mark frames without one) and intrinsic/intrinsic_depth.txt (4x4; integer-centred).
    The depth camera's size and K are the stream's; colour (1296x968) is resampled to it when read, as ScanNet's
    SLAM evaluations do."""
    root = Path(root)
    cdir, ddir, pdir = root / "color", root / "depth", root / "pose"
    intr = root / "intrinsic" / "intrinsic_depth.txt"
    for p in (cdir, ddir):
        if not p.is_dir():
            raise FileNotFoundError(f"{p}: ScanNet capture needs color/ and depth/ folders")
    if not intr.is_file():
        raise FileNotFoundError(f"{intr}: ScanNet capture needs the depth camera's intrinsics")
    try:
        M = np.loadtxt(intr, dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{intr}: malformed intrinsics: expected a 4x4 matrix of numbers ({exc})") from None
    if M.shape != (4, 4) or M[0, 0] <= 0 or M[1, 1] <= 0:
        raise ValueError(f"{intr}: malformed intrinsics: expected a 4x4 matrix with positive focal lengths")
    K = M[:3, :3].copy()
    K[0, 2] += INTEGER_CENTRE_SHIFT
    K[1, 2] += INTEGER_CENTRE_SHIFT
    colors = sorted(((int(m.group(1)), p) for p in cdir.iterdir() if (m := SCANNET_FRAME.match(p.name))),
                    key=lambda t: t[0])
    if not colors:
        raise FileNotFoundError(f"{cdir}: no N.jpg colour frames (ScanNet layout)")
    frames, missing = [], 0
    for i, (num, cpath) in enumerate(colors):
        dpath = ddir / f"{num}.png"
        if not dpath.is_file():
            raise FileNotFoundError(f"{dpath}: depth file of {cpath.name} does not exist")
        ppath = pdir / f"{num}.txt"
        pose = _read_pose_txt(ppath) if ppath.is_file() else None
        missing += pose is None
        frames.append(StreamFrame(i, cpath, dpath, None, pose))
    from trisplat.data.rgbd import read_depth_raw as _raw

    h, w = _raw(frames[0].depth_path).shape
    warnings = []
    if 0 < missing < len(frames):
        warnings.append(f"{missing} of {len(frames)} frames have no (valid) reference pose in {pdir}")
    cw, ch = image_size(frames[0].color_path)
    if (cw, ch) != (w, h):
        warnings.append(f"colour {cw}x{ch} is resampled to the depth's {w}x{h} (ScanNet's depth intrinsics used)")
    return RGBDStream("scannet", root, frames, w, h, K, depth_scale or SEVENSCENES_DEPTH_SCALE, warnings,
                      resize_color=(cw, ch) != (w, h))


def read_redwood(root: Path, depth_scale: float | None = None) -> RGBDStream:
    """Redwood / ICL-NUIM: colour/ and depth/ folders, camera.json, a .log trajectory (the reference poses)."""
    from trisplat.data.rgbd import read_rgbd

    raw = read_rgbd(Path(root), depth_scale)
    cam = raw.views[0].camera
    frames = [
        StreamFrame(i, v.image_path, v.depth_path, None, np.linalg.inv(v.world_to_camera))
        for i, v in enumerate(raw.views)
    ]
    return RGBDStream("redwood", Path(root), frames, cam.width, cam.height, cam.pinhole_K(),
                      raw.views[0].depth_scale, list(raw.warnings))


def detect_stream_format(root: Path) -> str | None:
    """'eth3d', 'tum', 'scannet', '7scenes', 'redwood' or None."""
    root = Path(root)
    if (root / "rgb.txt").is_file() and (root / "depth.txt").is_file():
        return "eth3d" if (root / "calibration.txt").is_file() else "tum"
    if (root / "color").is_dir() and (root / "depth").is_dir() and (root / "intrinsic").is_dir():
        return "scannet"
    if (root / "camera-intrinsics.txt").is_file() or any(SEVENSCENES_COLOR.match(p.name) for p in root.glob("frame-*")):
        return "7scenes"
    from trisplat.data.rgbd import find_rgbd_layout

    if find_rgbd_layout(root) is not None:
        return "redwood"
    return None


def open_stream(root: str | Path, depth_scale: float | None = None, format: str | None = None) -> RGBDStream:
    """Read an RGB-D capture folder as an ordered stream (format detected unless given)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: capture folder does not exist")
    fmt = format or detect_stream_format(root)
    readers = {"tum": read_tum, "eth3d": read_eth3d, "scannet": read_scannet, "7scenes": read_sevenscenes,
               "redwood": read_redwood}
    if fmt not in readers:
        raise ValueError(
            f"{root}: not an RGB-D stream: expected TUM (rgb.txt + depth.txt), ETH3D SLAM (TUM's lists + "
            "calibration.txt), ScanNet (color/ + depth/ + intrinsic/intrinsic_depth.txt [+ pose/]), 7-Scenes "
            "(frame-NNNNNN.color.jpg + .depth.png + camera-intrinsics.txt) or Redwood (color/ + depth/ + *.log)"
        )
    if depth_scale is not None and not depth_scale > 0:
        raise ValueError(f"depth_scale must be > 0 metres per raw unit, got {depth_scale}")
    return readers[fmt](root, depth_scale)


def _box_down(a: np.ndarray, f: int) -> np.ndarray:
    """[H,W,...] -> [H//f,W//f,...]: the mean of each f x f block (float32, or float64 for float64 input), summed
    from f*f strided slices (a reshape's mean over axes 1 and 3 is several times slower)."""
    H, W = a.shape[0] // f, a.shape[1] // f
    out = a[0: H * f: f, 0: W * f: f].astype(np.result_type(a.dtype, np.float32), copy=True)
    for i in range(f):
        for j in range(f):
            if i or j:
                out += a[i: H * f: f, j: W * f: f]
    out *= 1.0 / (f * f)
    return out


def downscale_depth(depth: np.ndarray, f: int) -> np.ndarray:
    """Depth [H,W] (0 = invalid) downscaled by f: the mean of each f x f block's valid values, 0 when a block has
    fewer than half valid or spans a depth edge (max/min > 1.1), so no depth is invented across discontinuities."""
    if f == 1:
        return depth
    H, W = depth.shape[0] // f, depth.shape[1] // f
    n = np.zeros((H, W), np.int32)
    total = np.zeros((H, W), np.float64)
    mx = np.full((H, W), -np.inf)
    mn = np.full((H, W), np.inf)
    for i in range(f):
        for j in range(f):
            b = depth[i: H * f: f, j: W * f: f]
            valid = b > 0
            n += valid
            total += b * valid
            np.maximum(mx, b, out=mx)
            np.minimum(mn, np.where(valid, b, np.inf), out=mn)
    mean = total / np.maximum(n, 1)
    ok = (n * 2 >= f * f) & (mx <= 1.1 * mn)
    return np.where(ok, mean, 0.0).astype(np.float32)


def load_frame(stream: RGBDStream, i: int, downscale: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Frame i as (rgb float32 [h,w,3] in [0,1], depth float32 [h,w] metres, 0 = invalid), downscaled by an
    integer factor (box filter; depth edge-aware, see downscale_depth); colour registered to the depth camera first
    when the stream's colour_registration says so. Wrong sizes raise naming the file."""
    fr = stream.frames[i]
    img = read_image(fr.color_path)
    if stream.resize_color and img.shape[:2] != (stream.height, stream.width):
        from PIL import Image

        img = np.asarray(Image.fromarray(img[..., :3]).resize((stream.width, stream.height), Image.Resampling.BOX))
    if img.shape[:2] != (stream.height, stream.width):
        raise ValueError(
            f"{fr.color_path}: colour is {img.shape[1]}x{img.shape[0]} but the stream is {stream.width}x{stream.height}"
        )
    raw = read_depth_raw(fr.depth_path)
    if raw.shape != (stream.height, stream.width):
        raise ValueError(
            f"{fr.depth_path}: depth is {raw.shape[1]}x{raw.shape[0]} but the colour image {fr.color_path.name} is "
            f"{stream.width}x{stream.height} (depth must be registered to colour)"
        )
    invalid = np.isin(raw, INVALID_DEPTH_RAW) | ~np.isfinite(raw)
    depth = np.where(invalid, 0.0, raw * stream.depth_scale).astype(np.float32)
    rgb = register_colour(img[..., :3], stream.colour_registration, stream.K) / 255.0
    if downscale > 1:
        rgb = _box_down(rgb, downscale).astype(np.float32)
        depth = downscale_depth(depth, downscale)
    return rgb, depth


class FramePrefetch:
    """Frames of a stream in order, each one decoded in a background thread while the caller works on the one
    before (image decoding and downscaling release the GIL, so it runs beside the tracker's kernels).

    get(n) returns load_frame(stream, ids[n], downscale) and starts loading ids[n + 1]; asking for a frame out of
    order loads it in the caller's thread. Errors (a missing or corrupt file) are raised by the get() of that
    frame, as load_frame raises them. A context manager: the thread is joined on exit."""

    def __init__(self, stream: RGBDStream, ids: list[int], downscale: int = 1, load=None):
        from concurrent.futures import ThreadPoolExecutor

        self.stream, self.ids, self.downscale = stream, list(ids), int(downscale)
        self._load = load_frame if load is None else load  # load(stream, i, downscale): load_frame or a stand-in
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="trisplat-frames")
        self._next: tuple[int, object] | None = None

    def _submit(self, n: int) -> None:
        self._next = (n, self._pool.submit(self._load, self.stream, self.ids[n], self.downscale))

    def get(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        ahead, self._next = self._next, None
        if ahead is not None and ahead[0] == n:
            out = ahead[1].result()
        else:
            if ahead is not None:
                ahead[1].cancel()
            out = self._load(self.stream, self.ids[n], self.downscale)
        if n + 1 < len(self.ids):
            self._submit(n + 1)
        return out

    def close(self) -> None:
        if self._next is not None:
            self._next[1].cancel()
            self._next = None
        self._pool.shutdown(wait=True)

    def __enter__(self) -> FramePrefetch:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = [
    "FramePrefetch",
    "RGBDStream",
    "StreamFrame",
    "open_stream",
    "load_frame",
    "read_tum",
    "read_sevenscenes",
    "read_redwood",
    "read_eth3d",
    "read_scannet",
    "detect_stream_format",
    "downscale_depth",
]
