"""COLMAP reader (binary or text, rigs/frames of COLMAP 3.12+) via pycolmap, with file-precise validation."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from trisplat.data.capture import CAMERA_MODELS, RawCapture, RawView, SourceCamera

MODEL_FILES = ("cameras", "images", "points3D")
# COLMAP model ids (src/colmap/sensor/models.h) -> (name, number of parameters).
COLMAP_MODEL_IDS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
COLMAP_MODEL_NAMES = {name: n for name, n in COLMAP_MODEL_IDS.values()}


def find_model_dir(root: Path) -> Path | None:
    """The folder holding cameras/images/points3D (.bin or .txt): root/sparse/0, root/sparse or root itself."""
    for cand in (root / "sparse" / "0", root / "sparse", root):
        for ext in (".bin", ".txt"):
            if all((cand / f"{name}{ext}").is_file() for name in MODEL_FILES):
                return cand
    return None


class _Reader:
    """Bounds-checked little-endian reads from one binary file (errors name the file)."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def read(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise ValueError(
                f"{self.path}: malformed COLMAP binary file: truncated while reading {what} "
                f"(offset {self.pos}, file size {len(self.data)} bytes)"
            )
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def skip(self, nbytes: int, what: str) -> None:
        if nbytes < 0 or self.pos + nbytes > len(self.data):
            raise ValueError(f"{self.path}: malformed COLMAP binary file: truncated while reading {what}")
        self.pos += nbytes

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise ValueError(f"{self.path}: malformed COLMAP binary file: unterminated {what}")
        s = self.data[self.pos : end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return s

    def count(self, record_min_bytes: int, what: str) -> int:
        (n,) = self.read("Q", f"number of {what}")
        if n * record_min_bytes > len(self.data) - self.pos:
            raise ValueError(
                f"{self.path}: malformed COLMAP binary file: claims {n} {what} but holds only "
                f"{len(self.data) - self.pos} more bytes"
            )
        return n

    def finish(self) -> None:
        if self.pos != len(self.data):
            raise ValueError(
                f"{self.path}: malformed COLMAP binary file: {len(self.data) - self.pos} unexpected trailing bytes"
            )


def _check_pose(path: Path, what: str, quaternion, translation) -> None:
    """Refuse a non-finite pose or a zero quaternion (pycolmap would silently turn it into the identity)."""
    q, t = np.asarray(quaternion, np.float64), np.asarray(translation, np.float64)
    if not (np.isfinite(q).all() and np.isfinite(t).all()) or np.linalg.norm(q) < 1e-12:
        raise ValueError(f"{path}: {what}: invalid pose (quaternion {', '.join(f'{v:g}' for v in q)}, translation "
                         f"{', '.join(f'{v:g}' for v in t)}); rotations must be finite non-zero quaternions")


def validate_binary_model(model_dir: Path) -> None:
    """Walk cameras.bin, images.bin and points3D.bin record by record; raise ValueError naming a bad file.

    pycolmap reads corrupt files without bounds checks (garbage counts can exhaust memory), so this runs first.
    """
    r = _Reader(model_dir / "cameras.bin")
    for i in range(r.count(24, "cameras")):
        cam_id, model_id, w, h = r.read("iiQQ", f"camera {i}")
        if model_id not in COLMAP_MODEL_IDS:
            raise ValueError(f"{r.path}: unknown camera model id {model_id} (camera record {i})")
        name, n_params = COLMAP_MODEL_IDS[model_id]
        if name not in CAMERA_MODELS:
            raise ValueError(
                f"{r.path}: unsupported camera model {name} (camera record {i}); "
                f"supported: {', '.join(CAMERA_MODELS)}"
            )
        params = r.read(f"{n_params}d", f"parameters of camera {i}")
        n_focal = 1 if name == "SIMPLE_PINHOLE" or "RADIAL" in name else 2  # f, or fx fy, lead the parameters
        if not np.isfinite(params).all() or w <= 0 or h <= 0 or min(params[:n_focal]) <= 0:
            raise ValueError(f"{r.path}: camera {cam_id} ({name}, {w}x{h}): invalid values (parameters "
                             f"{', '.join(f'{p:g}' for p in params)}; focal lengths and sizes must be positive and "
                             "finite)")
    r.finish()

    r = _Reader(model_dir / "images.bin")
    for i in range(r.count(64 + 1 + 8, "images")):
        record = r.read("I7dI", f"image {i}")
        name = r.cstring(f"name of image {i}")
        _check_pose(r.path, f"image {record[0]} ({name})", record[1:5], record[5:8])
        (n2d,) = r.read("Q", f"point count of image {i}")
        r.skip(24 * n2d, f"2D points of image {i}")
    r.finish()

    r = _Reader(model_dir / "points3D.bin")
    for i in range(r.count(43 + 8, "points")):
        r.read("Q3d3Bd", f"point {i}")
        (n,) = r.read("Q", f"track length of point {i}")
        r.skip(8 * n, f"track of point {i}")
    r.finish()


def validate_text_model(model_dir: Path) -> None:
    """Check cameras/images/points3D.txt line by line (numbers parse, model names known, token counts)."""

    def lines(path: Path):
        try:
            text = path.read_text()
        except UnicodeDecodeError as exc:
            raise ValueError(f"{path}: malformed COLMAP text file: not UTF-8 text ({exc})") from None
        for no, line in enumerate(text.splitlines(), 1):
            if line.strip() and not line.lstrip().startswith("#"):
                yield no, line.split()

    def numbers(path: Path, no: int, toks: list[str], what: str) -> None:
        try:
            [float(t) for t in toks]
        except ValueError:
            raise ValueError(f"{path}:{no}: malformed COLMAP text file: non-numeric {what}: {' '.join(toks)}") from None

    path = model_dir / "cameras.txt"
    for no, toks in lines(path):
        if len(toks) < 4:
            raise ValueError(f"{path}:{no}: malformed COLMAP text file: camera line needs ID MODEL WIDTH HEIGHT PARAMS")
        model = toks[1]
        if model not in COLMAP_MODEL_NAMES:
            raise ValueError(f"{path}:{no}: unknown camera model {model!r}")
        if model not in CAMERA_MODELS:
            raise ValueError(f"{path}:{no}: unsupported camera model {model} (supported: {', '.join(CAMERA_MODELS)})")
        numbers(path, no, [toks[0], *toks[2:]], "camera values")
        if len(toks) - 4 != COLMAP_MODEL_NAMES[model]:
            raise ValueError(
                f"{path}:{no}: camera model {model} takes {COLMAP_MODEL_NAMES[model]} parameters, got {len(toks) - 4}"
            )

    path = model_dir / "images.txt"
    # Image lines alternate: header (ID QW QX QY QZ TX TY TZ CAMERA_ID NAME) then 2D points (may be empty).
    text = path.read_text(errors="replace").splitlines()
    body = [(no, l) for no, l in enumerate(text, 1) if not l.lstrip().startswith("#")]
    while body and not body[-1][1].strip():
        body.pop()
    for k in range(0, len(body), 2):
        no, line = body[k]
        toks = line.split()
        if len(toks) < 10:
            raise ValueError(f"{path}:{no}: malformed COLMAP text file: image line needs 10 fields, got {len(toks)}")
        numbers(path, no, toks[:9], "image pose")
        _check_pose(path, f"line {no}, image {toks[0]} ({toks[9]})", [float(t) for t in toks[1:5]],
                    [float(t) for t in toks[5:8]])
        if k + 1 < len(body):
            no2, pts = body[k + 1]
            pts_t = pts.split()
            if len(pts_t) % 3:
                raise ValueError(f"{path}:{no2}: malformed COLMAP text file: 2D points must come as X Y POINT3D_ID")
            numbers(path, no2, pts_t, "2D points")

    path = model_dir / "points3D.txt"
    for no, toks in lines(path):
        if len(toks) < 8 or (len(toks) - 8) % 2:
            raise ValueError(f"{path}:{no}: malformed COLMAP text file: point line needs ID X Y Z R G B ERROR TRACK[]")
        numbers(path, no, toks, "point values")


def read_colmap(root: Path, images: str = "images") -> RawCapture:
    """Read a COLMAP capture: root/<images>/ and a model in root/sparse/0, root/sparse or root."""
    import pycolmap

    model_dir = find_model_dir(root)
    if model_dir is None:
        raise FileNotFoundError(f"{root}: no COLMAP model (cameras, images, points3D .bin or .txt) found")
    binary = (model_dir / "cameras.bin").is_file()
    if binary:
        validate_binary_model(model_dir)
    else:
        validate_text_model(model_dir)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # rigs/frames files or anything the validators above do not cover
        raise ValueError(f"{model_dir}: malformed COLMAP model ({type(exc).__name__}: {exc})") from None

    image_dir = root / images
    views: list[RawView] = []
    warnings: list[str] = []
    unposed = 0
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            unposed += 1
            continue
        cam = rec.cameras[image.camera_id]
        src = SourceCamera(cam.model.name, cam.width, cam.height, tuple(cam.params))
        w2c = np.eye(4)
        w2c[:3, :] = image.cam_from_world().matrix()
        views.append(RawView(name=image.name, world_to_camera=w2c, camera=src, image_path=image_dir / image.name))
    if unposed:
        warnings.append(f"skipped {unposed} image(s) without a pose in {model_dir}")
    if not views:
        raise ValueError(f"{model_dir}: empty scene: the COLMAP model has no posed images")

    points = colors = None
    ext = ".bin" if binary else ".txt"
    if len(rec.points3D):
        pts = list(rec.points3D.values())
        points = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
        colors = (np.array([p.color for p in pts], dtype=np.float32) / 255.0).reshape(-1, 3)
        finite = np.isfinite(points).all(axis=1)
        if not finite.all():
            warnings.append(f"{model_dir / ('points3D' + ext)}: dropped {int((~finite).sum())} of {len(points)} "
                            "points with non-finite coordinates")
            points, colors = points[finite], colors[finite]
    if points is None or not len(points):
        warnings.append(f"{model_dir / ('points3D' + ext)}: the model holds no (usable) 3D points: initialisation "
                        "cannot use them (init auto falls back to the visual hull or random triangles)")
        points = colors = None
    return RawCapture(
        format="colmap",
        root=root,
        views=views,
        points=points,
        point_colors=colors,
        warnings=warnings,
        source_files=[model_dir / f"{n}{ext}" for n in MODEL_FILES],
    )
