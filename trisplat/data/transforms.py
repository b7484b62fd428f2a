"""Blender / NeRF-synthetic (transforms_{train,test}.json) and instant-ngp (transforms.json) readers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from trisplat.data.capture import RawCapture, RawView, SourceCamera
from trisplat.data.images import image_size

# OpenGL camera axes (x right, y up, z back) -> OpenCV (x right, y down, z forward).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
# NeRF-synthetic objects lie within this box of their own frame (half side, scene units).
BLENDER_OBJECT_HALF_SIDE = 1.5
# instant-ngp / nerfstudio model names we accept in "camera_model".
JSON_CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "OPENCV_FISHEYE")
BLENDER_SPLITS = ("train", "test")


def read_json(path: Path) -> dict:
    """Parse a JSON object; malformed files raise ValueError naming the file and the position."""
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: malformed JSON: not UTF-8 text ({exc})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: malformed JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: malformed JSON: expected an object at the top level, got {type(data).__name__}")
    return data


def _number(d: dict, key: str, path: Path, where: str) -> float | None:
    if key not in d:
        return None
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"{path}: {where}: {key!r} must be a finite number, got {v!r}")
    return float(v)


def _resolve_image(root: Path, file_path: str) -> Path:
    p = (root / file_path).resolve() if not Path(file_path).is_absolute() else Path(file_path)
    if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp"):
        return p
    for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG"):
        if p.with_name(p.name + ext).exists():
            return p.with_name(p.name + ext)
    return p.with_name(p.name + ".png")  # NeRF-synthetic default; a missing file is reported later


def _pose(frame: dict, path: Path, where: str) -> np.ndarray:
    if "transform_matrix" not in frame:
        raise ValueError(f"{path}: {where}: missing 'transform_matrix'")
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {where}: 'transform_matrix' is not a numeric matrix") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"{path}: {where}: 'transform_matrix' must be a finite 4x4 (or 3x4) matrix, got {m.shape}")
    R = m[:3, :3]
    if abs(np.linalg.det(R)) < 1e-9:
        raise ValueError(f"{path}: {where}: 'transform_matrix' has a singular rotation")
    c2w_cv = m @ GL_TO_CV
    return np.linalg.inv(c2w_cv)


def _camera(meta: dict, frame: dict, img: Path, path: Path, where: str) -> SourceCamera:
    """Intrinsics from frame values, else file-level values (instant-ngp allows per-frame intrinsics)."""

    def get(key: str) -> float | None:
        v = _number(frame, key, path, where)
        return v if v is not None else _number(meta, key, path, "top level")

    w, h = get("w"), get("h")
    if w is None or h is None:
        w, h = image_size(img)
    w, h = int(round(w)), int(round(h))
    fx, fy = get("fl_x"), get("fl_y")
    ax, ay = get("camera_angle_x"), get("camera_angle_y")
    if fx is None and ax is not None:
        fx = 0.5 * w / math.tan(0.5 * ax)
    if fy is None and ay is not None:
        fy = 0.5 * h / math.tan(0.5 * ay)
    if fx is None and fy is None:
        raise ValueError(f"{path}: {where}: no focal length (need 'fl_x'/'fl_y' or 'camera_angle_x')")
    fx = fx if fx is not None else fy
    fy = fy if fy is not None else fx
    cx = get("cx")
    cy = get("cy")
    cx = w / 2.0 if cx is None else cx
    cy = h / 2.0 if cy is None else cy
    model = frame.get("camera_model", meta.get("camera_model"))
    fisheye = bool(frame.get("is_fisheye", meta.get("is_fisheye", False)))
    if model is None:
        model = "OPENCV_FISHEYE" if fisheye else "OPENCV"
    if model not in JSON_CAMERA_MODELS:
        raise ValueError(
            f"{path}: {where}: unknown camera model {model!r} (supported: {', '.join(JSON_CAMERA_MODELS)})"
        )
    k = {key: (get(key) or 0.0) for key in ("k1", "k2", "k3", "k4", "p1", "p2")}
    if model in ("PINHOLE", "SIMPLE_PINHOLE") or not any(k.values()):
        return SourceCamera("PINHOLE", w, h, (fx, fy, cx, cy))
    if model == "OPENCV_FISHEYE":
        return SourceCamera("OPENCV_FISHEYE", w, h, (fx, fy, cx, cy, k["k1"], k["k2"], k["k3"], k["k4"]))
    if k["k3"] or k["k4"]:
        return SourceCamera(
            "FULL_OPENCV", w, h, (fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"], k["k3"], k["k4"], 0.0, 0.0)
        )
    return SourceCamera("OPENCV", w, h, (fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"]))


def _frames(meta: dict, path: Path) -> list[dict]:
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise ValueError(f"{path}: missing or malformed 'frames' list")
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
            raise ValueError(f"{path}: frame {i}: needs a 'file_path' string")
    return frames


def _check_one_image_size(views: list[RawView], files: list[Path]) -> None:
    """A Blender capture gives one field of view (camera_angle_x) for all frames: an image of another size would
    silently get another focal length. Refuse it, naming the file and the size of the others."""
    from collections import Counter

    sizes = Counter((v.camera.width, v.camera.height) for v in views)
    if len(sizes) > 1:
        (w, h), n = sizes.most_common(1)[0]
        odd = [v for v in views if (v.camera.width, v.camera.height) != (w, h)]
        raise ValueError(
            f"{odd[0].image_path}: image is {odd[0].camera.width}x{odd[0].camera.height}, but {n} of the "
            f"{len(views)} images of this capture are {w}x{h} ({len(odd)} differ); "
            f"{', '.join(f.name for f in files)} give one camera_angle_x for every frame, so all images must have "
            "one size")


def read_blender(root: Path) -> RawCapture:
    """NeRF-synthetic: transforms_train.json + transforms_test.json (val is ignored); RGBA images."""
    views: list[RawView] = []
    split: list[str] = []
    files = []
    for name in BLENDER_SPLITS:
        path = root / f"transforms_{name}.json"
        if not path.is_file():
            if name == "train":
                raise FileNotFoundError(f"{path}: missing (a Blender capture needs transforms_train.json)")
            continue
        files.append(path)
        meta = read_json(path)
        for i, fr in enumerate(_frames(meta, path)):
            where = f"frame {i} ({fr['file_path']})"
            img = _resolve_image(root, fr["file_path"])
            if not img.is_file():
                raise FileNotFoundError(f"{img}: image listed in {path} ({where}) does not exist")
            views.append(
                RawView(
                    name=f"{name}/{img.name}",
                    world_to_camera=_pose(fr, path, where),
                    camera=_camera(meta, fr, img, path, where),
                    image_path=img,
                )
            )
            split.append(name)
    if not views:
        raise ValueError(f"{root}: empty scene: no frames in {', '.join(str(f) for f in files)}")
    _check_one_image_size(views, files)
    half = BLENDER_OBJECT_HALF_SIDE
    points, colors = read_point_ply(root / BLENDER_POINTS) if (root / BLENDER_POINTS).is_file() else (None, None)
    return RawCapture(
        format="blender",
        root=root,
        views=views,
        split=split,
        points=points,
        point_colors=colors,
        object_bounds=np.array([[-half] * 3, [half] * 3]),
        source_files=files + ([root / BLENDER_POINTS] if points is not None else []),
    )


BLENDER_POINTS = "points3d.ply"  # optional sparse points beside a Blender capture (trisplat's synthetic scenes)


def read_point_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points float64 [P,3] (capture frame) and RGB float32 [P,3] in [0,1] (None without colours) from a PLY."""
    import trimesh

    try:
        cloud = trimesh.load(path, process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types for malformed files
        raise ValueError(f"{path}: not a readable point cloud PLY ({exc})") from exc
    pts = np.asarray(getattr(cloud, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
        raise ValueError(f"{path}: no points in this PLY")
    if not np.isfinite(pts).all():
        raise ValueError(f"{path}: non-finite point coordinates")
    col = getattr(cloud, "colors", None)
    colors = np.asarray(col, dtype=np.float32)[:, :3] / 255.0 if col is not None and len(col) == len(pts) else None
    return pts, colors


def read_ngp(root: Path, path: Path | None = None) -> RawCapture:
    """instant-ngp: one transforms.json with fl_x fl_y cx cy k1 k2 p1 p2 (per-frame values allowed).

    Frames whose image file does not exist are skipped and counted in the warnings.
    """
    path = path or root / "transforms.json"
    meta = read_json(path)
    views: list[RawView] = []
    missing: list[str] = []
    for i, fr in enumerate(_frames(meta, path)):
        where = f"frame {i} ({fr['file_path']})"
        img = _resolve_image(path.parent, fr["file_path"])
        if not img.is_file():
            missing.append(fr["file_path"])
            continue
        views.append(
            RawView(
                name=str(Path(fr["file_path"]).name),
                world_to_camera=_pose(fr, path, where),
                camera=_camera(meta, fr, img, path, where),
                image_path=img,
            )
        )
    warnings = []
    if missing:
        warnings.append(
            f"skipped {len(missing)} of {len(missing) + len(views)} frames of {path.name} whose image file does not "
            f"exist (first: {missing[0]})"
        )
    if not views:
        raise ValueError(f"{path}: empty scene: none of its {len(missing)} frames has an existing image")
    views.sort(key=lambda v: v.name)
    return RawCapture(format="ngp", root=root, views=views, warnings=warnings, source_files=[path])
