"""load_dataset: detect a capture's format, then normalise, undistort, downscale, cache and split it."""

from __future__ import annotations

import hashlib
import os
import warnings as _warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from PIL import Image

from trisplat.cameras import Camera
from trisplat.data.capture import RawCapture, RawView
from trisplat.data.images import LRUArrays, check_image_file, read_image, save_image_atomic, to_float_rgb
from trisplat.data.normalize import apply_to_points, apply_to_world_to_camera, normalization, robust_box
from trisplat.data.options import LoadOptions
from trisplat.data.types import SceneData
from trisplat.progress import progress_bar
from trisplat.data.undistort import pinhole_camera, undistort_array

CACHE_VERSION = 1  # bump when the derived-image recipe changes: old cache files are then ignored


def detect_format(root: Path) -> str:
    """'blender' | 'ngp' | 'colmap' | 'rgbd' from the files in `root` (FileNotFoundError when none fits). A folder
    holding several captures: the first of `detect_formats`' list (see there)."""
    return detect_formats(root)[0]


def colmap_point_count(model_dir: Path) -> int:
    """Number of 3D points of a COLMAP model, from the header of points3D.bin or the lines of points3D.txt."""
    binary = model_dir / "points3D.bin"
    if binary.is_file():
        with open(binary, "rb") as f:
            head = f.read(8)
        return int.from_bytes(head, "little") if len(head) == 8 else 0
    text = model_dir / "points3D.txt"
    with open(text, errors="replace") as f:
        return sum(1 for line in f if line.strip() and not line.lstrip().startswith("#"))


def detect_formats(root: Path) -> list[str]:
    """Every capture format found in `root`, the one `format='auto'` uses first: Blender, instant-ngp, COLMAP,
    RGB-D in that order, except that a COLMAP model with sparse points goes before an instant-ngp transforms.json
    (its points give the Delaunay initialisation; fox ships both). FileNotFoundError when none fits."""
    from trisplat.data.colmap import find_model_dir
    from trisplat.data.rgbd import find_rgbd_layout

    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"{root}: capture folder does not exist")
    if root.is_file():
        if root.suffix == ".json":
            return ["ngp"]
        raise FileNotFoundError(f"{root}: expected a capture folder (or a transforms.json), got a file")
    found = []
    if (root / "transforms_train.json").is_file():
        found.append("blender")
    if (root / "transforms.json").is_file():
        found.append("ngp")
    model_dir = find_model_dir(root)
    if model_dir is not None:
        if "ngp" in found and colmap_point_count(model_dir) > 0:
            found.insert(found.index("ngp"), "colmap")
        else:
            found.append("colmap")
    if (root / "rgb.txt").is_file() or find_rgbd_layout(root) is not None:
        found.append("rgbd")
    if found:
        return found
    raise FileNotFoundError(
        f"{root}: no known capture format (looked for transforms_train.json, transforms.json, "
        f"sparse/0 or sparse/ with COLMAP cameras/images/points3D, color/ + depth/ with a trajectory)"
    )


def colmap_root(path: Path) -> Path | None:
    """The capture root when `path` is itself a COLMAP model folder (root/sparse/0 or root/sparse), else None."""
    if not (path / "cameras.bin").is_file() and not (path / "cameras.txt").is_file():
        return None
    if path.parent.name == "sparse":
        return path.parent.parent
    if path.name == "sparse":
        return path.parent
    return None


FORMAT_FILES = {"blender": "transforms_train.json", "ngp": "transforms.json", "colmap": "a COLMAP model",
                "rgbd": "an RGB-D layout"}


def read_capture(root: Path, opts: LoadOptions) -> RawCapture:
    raw = _read_capture(root, opts)
    if opts.format == "auto" and root.is_dir():
        found = detect_formats(root)
        if len(found) > 1:  # say what else is there, and how to pick it
            raw.warnings.append(
                f"{root} also holds {', '.join(f'{FORMAT_FILES[f]} ({f})' for f in found[1:])}; read as {found[0]}"
                + (" for its sparse points" if found[0] == "colmap" and "ngp" in found else "")
                + f"; --data-format {found[1]} picks the other")
    return raw


def _read_capture(root: Path, opts: LoadOptions) -> RawCapture:
    fmt = detect_format(root) if opts.format == "auto" else opts.format
    if fmt == "blender":
        from trisplat.data.transforms import read_blender

        return read_blender(root)
    if fmt == "ngp":
        from trisplat.data.transforms import read_ngp

        return read_ngp(root.parent, root) if root.is_file() else read_ngp(root)
    if fmt == "colmap":
        from trisplat.data.colmap import read_colmap

        return read_colmap(root, images=opts.images)
    from trisplat.data.rgbd import read_rgbd

    return read_rgbd(root, depth_scale=opts.depth_scale)


@dataclass
class _Prepared:
    """How to make one view's cached image: the original file, its camera, the target file and size."""

    view: RawView
    target: Path  # == view.image_path when nothing changes
    size: tuple[int, int]  # (width, height) of the target
    depth_target: Path | None


def _cache_key(view: RawView, downscale: int) -> str:
    st = view.image_path.stat()
    h = hashlib.sha1()
    h.update(repr((CACHE_VERSION, str(view.image_path.resolve()), st.st_size, st.st_mtime_ns)).encode())
    h.update(repr((view.camera.model, view.camera.width, view.camera.height, view.camera.params, downscale)).encode())
    return h.hexdigest()[:12]


def _cache_folder(root: Path, opts: LoadOptions) -> Path:
    ident = hashlib.sha1(str(root.resolve()).encode()).hexdigest()[:10]
    folder = opts.cache_root / "images" / f"{root.resolve().name}-{ident}" / f"x{opts.downscale}"
    try:
        folder.resolve().relative_to(root.resolve())
    except ValueError:
        return folder
    raise ValueError(f"cache_dir {opts.cache_root} lies inside the capture folder {root}: choose another one")


def make_image(p: _Prepared, downscale: int) -> None:
    """Undistort (if needed) and area-downscale one image into its cache file."""
    img = read_image(p.view.image_path)
    img = undistort_array(img, p.view.camera)
    if downscale > 1:
        mode = "RGBA" if img.shape[-1] == 4 else "RGB"  # Pillow resamples RGBA premultiplied
        img = np.asarray(Image.fromarray(img, mode).resize(p.size, Image.Resampling.BOX))
    if (img.shape[1], img.shape[0]) != p.size:
        raise ValueError(f"{p.view.image_path}: processed image is {img.shape[1]}x{img.shape[0]}, expected {p.size}")
    save_image_atomic(img, p.target)


def downscale_depth(raw: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Median of the valid (non-zero) depths of each block; blocks without depth stay 0. size = (W, H)."""
    H, W = raw.shape
    w, h = size
    if H % h == 0 and W % w == 0:
        fy, fx = H // h, W // w
        blocks = raw.reshape(h, fy, w, fx).transpose(0, 2, 1, 3).reshape(h, w, fy * fx).astype(np.float64)
        blocks[blocks <= 0] = np.nan
        with _warnings.catch_warnings():
            _warnings.simplefilter("ignore", RuntimeWarning)
            out = np.nanmedian(blocks, axis=2)
        return np.nan_to_num(out, nan=0.0)
    return np.asarray(Image.fromarray(raw.astype(np.float32), "F").resize(size, Image.Resampling.NEAREST))


def make_depth(p: _Prepared) -> None:
    from trisplat.data.rgbd import read_depth_raw

    raw = read_depth_raw(p.view.depth_path)
    small = downscale_depth(raw, p.size)
    p.depth_target.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.depth_target.with_name(f".{p.depth_target.name}.{os.getpid()}.tmp")
    Image.fromarray(np.clip(np.round(small), 0, 65535).astype(np.uint16)).save(tmp, format="PNG")
    os.replace(tmp, p.depth_target)


def _check_sizes(raw: RawCapture) -> None:
    """Every image: complete (not truncated), of the size its camera expects; a file in another format than its
    suffix says is warned about (raw.warnings)."""
    for v in raw.views:
        w, h, warning = check_image_file(v.image_path)
        if warning:
            raw.warnings.append(warning)
        if (w, h) != (v.camera.width, v.camera.height):
            raise ValueError(
                f"{v.image_path}: image is {w}x{h} but its camera ({v.camera.model}) expects "
                f"{v.camera.width}x{v.camera.height}"
            )


def _splits(raw: RawCapture, opts: LoadOptions) -> tuple[np.ndarray, np.ndarray]:
    n = len(raw.views)
    if raw.split is not None:
        labels = np.array(raw.split)
        return np.flatnonzero(labels == "train").astype(np.int64), np.flatnonzero(labels == "test").astype(np.int64)
    idx = np.arange(n, dtype=np.int64)
    if opts.test_every <= 0 or n < 2:
        return idx, idx[:0]
    test = idx % opts.test_every == 0
    return idx[~test], idx[test]


def load_dataset(path, downscale: int = 1, **options) -> SceneData:
    """Read a capture folder into a SceneData (format detected from the folder).

    Formats: COLMAP (sparse/0 or sparse, binary or text; images in <root>/images), Blender / NeRF-synthetic
    (transforms_train.json + transforms_test.json), instant-ngp (transforms.json; frames whose image is missing
    are skipped and counted in `warnings`), RGB-D (color/ + depth/ + Redwood *.log + Open3D camera.json, or TUM
    rgb.txt/depth.txt/groundtruth.txt).

    downscale: 1, 2, 4 or 8 (area filter, K scaled exactly). Options (trisplat.data.options.LoadOptions):
    background (RGB in [0,1], white), test_every (8), depth_scale (capture units per raw depth value),
    cache_dir, memory_budget_mb (1024), normalize ('auto' | 'cameras' | 'points' | 'none', rule in
    trisplat.data.normalize), images ('images', COLMAP image folder), prepare ('eager' | 'lazy').

    Distorted cameras are undistorted to pinhole once (pycolmap) and downscaled images are written once, both
    under the cache folder (never inside the capture); Camera.image_path names that file, or the original when
    nothing changed. Bad input raises ValueError / FileNotFoundError naming the file.
    """
    opts = LoadOptions.from_kwargs(downscale=downscale, **options)
    root = Path(path).expanduser()
    model_root = colmap_root(root)
    if model_root is not None:  # a path to sparse/0 means: this COLMAP model of that capture
        root = model_root
        opts = replace(opts, format="colmap")
    raw = read_capture(root, opts)
    if root.is_file():
        root = root.parent
    _check_sizes(raw)
    train, test = _splits(raw, opts)
    if len(train) == 0:
        raise ValueError(f"{root}: empty scene: no training images")

    points, colors = raw.points, raw.point_colors
    if raw.format == "rgbd" and points is None:
        from trisplat.data.rgbd import depth_points

        points, colors = depth_points(raw.views, train)
    centers = np.stack([-v.world_to_camera[:3, :3].T @ v.world_to_camera[:3, 3] for v in raw.views])
    hint = None if raw.object_bounds is None else raw.object_bounds.mean(0)
    N, rule = normalization(centers, points, opts.normalize, center=hint)
    s = float(N[0, 0])

    d = opts.downscale
    cache = _cache_folder(root, opts)
    cameras: list[Camera] = []
    jobs: list[_Prepared] = []
    for v in raw.views:
        K, w, h = pinhole_camera(v.camera)
        cam = Camera(
            world_to_camera=apply_to_world_to_camera(N, v.world_to_camera),
            K=K,
            width=w,
            height=h,
            image_path=v.image_path,
            name=v.name,
            depth_path=v.depth_path,
            depth_scale=v.depth_scale,
            extras={
                "source_model": v.camera.model,
                "source_size": (v.camera.width, v.camera.height),
                "source_image": str(v.image_path),
                "undistorted": v.camera.needs_undistortion,
            },
        )
        if d > 1:
            cam = cam.scaled(1.0 / d)
        target = v.image_path
        if v.camera.needs_undistortion or d > 1:
            target = cache / f"{Path(v.name).stem}-{_cache_key(v, d)}.png"
        depth_target = None
        if v.depth_path is not None and d > 1:
            depth_target = cache / "depth" / f"{Path(v.depth_path).stem}-{_cache_key(v, d)}.png"
        cam = replace(cam, image_path=target, depth_path=depth_target or v.depth_path)
        cameras.append(cam)
        jobs.append(_Prepared(v, target, (cam.width, cam.height), depth_target))

    def ensure(i: int) -> None:
        p = jobs[i]
        if p.target != p.view.image_path and not p.target.exists():
            make_image(p, d)
        if p.depth_target is not None and not p.depth_target.exists():
            make_depth(p)

    todo = [
        i
        for i, p in enumerate(jobs)
        if (p.target != p.view.image_path and not p.target.exists())
        or (p.depth_target is not None and not p.depth_target.exists())
    ]
    if opts.prepare == "eager" and todo:
        undist = any(jobs[i].view.camera.needs_undistortion for i in todo)
        what = " + ".join(w for w, on in (("undistorting", undist), (f"downscaling x{d}", d > 1)) if on)
        for i in progress_bar(todo, desc=f"{what} {len(todo)} images -> {cache}", unit="img", leave=False):
            ensure(i)

    background = opts.background

    def load_image(i: int) -> np.ndarray:
        ensure(i)
        cam = cameras[i]
        img = read_image(cam.image_path)
        if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
            raise ValueError(
                f"{cam.image_path}: image is {img.shape[1]}x{img.shape[0]}, camera is {cam.width}x{cam.height}"
            )
        return to_float_rgb(img, background)

    def load_alpha(i: int) -> np.ndarray | None:
        ensure(i)
        img = read_image(cameras[i].image_path)
        return img[..., 3].astype(np.float32) / 255.0 if img.ndim == 3 and img.shape[2] == 4 else None

    def load_depth(i: int) -> np.ndarray:
        from trisplat.data.rgbd import read_depth_raw

        ensure(i)
        cam = cameras[i]
        depth = read_depth_raw(cam.depth_path)
        if depth.shape != (cam.height, cam.width):
            raise ValueError(
                f"{cam.depth_path}: depth is {depth.shape[1]}x{depth.shape[0]}, camera is {cam.width}x{cam.height}"
            )
        return (depth * (cam.depth_scale * s)).astype(np.float32)

    budget = opts.memory_budget_mb * 2**20
    norm_points = norm_colors = None
    if points is not None and len(points):
        norm_points = apply_to_points(N, points).astype(np.float32)
        norm_colors = np.asarray(colors, dtype=np.float32)
    if raw.object_bounds is not None:
        bounds = apply_to_points(N, raw.object_bounds)
    elif norm_points is not None:
        bounds = robust_box(norm_points.astype(np.float64))
    else:
        c = apply_to_points(N, centers)
        bounds = np.stack([c.min(0), c.max(0)])
    warn = list(raw.warnings)
    if raw.format == "rgbd" and norm_points is not None:
        warn.append(f"points: {len(norm_points)} samples back-projected from depth (no SfM points in RGB-D captures)")
    used = opts.as_dict()
    used["normalize"] = rule  # the resolved rule: reloading with these options gives the same transform
    return SceneData(
        cameras=cameras,
        train_indices=train,
        test_indices=test,
        points=norm_points,
        point_colors=norm_colors,
        normalization=N,
        background=background,
        format=raw.format,
        root=root,
        warnings=warn,
        image_loader=LRUArrays(load_image, budget),
        bounds=bounds,
        options=used,
        depth_loader=LRUArrays(load_depth, budget) if raw.format == "rgbd" else None,
        alpha_loader=load_alpha,
    )
