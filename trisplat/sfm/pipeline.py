"""run_poses: photos or a video -> a COLMAP capture folder (images/, sparse/0) by structure from motion with pycolmap.

Stages (each with progress): frames (video only), input check, SIFT features, pair selection and matching with
geometric verification, global mapping (or incremental: PosesOptions.mapper), the registration check
(trisplat.sfm.verify: photos placed where their own matches disagree are registered again), undistortion to pinhole,
report. Layout of OUT:

  OUT/images/             undistorted images of the registered views (what `trisplat train` reads)
  OUT/sparse/0/           the PINHOLE COLMAP model of those images (cameras, images, points3D .bin)
  OUT/poses.json          the report (PosesReport.as_dict)
  OUT/distorted/          the work: database.db, the model before undistortion (sparse/0), video frames (images/)
"""
from __future__ import annotations

import json
import math
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from trisplat.sfm.inputs import (
    IMAGE_SUFFIXES,
    MIN_IMAGES,
    VIDEO_SUFFIXES,
    check_images,
    find_images,
    is_video,
    name_list,
)
from trisplat.sfm.pairs import exhaustive_pairs, loop_pairs, retrieval_similarity, sequential_pairs
from trisplat.sfm.verify import repair_registration

MATCHERS = ("auto", "exhaustive", "sequential")
CAMERA_MODES = ("single", "per-image")
MAPPERS = ("incremental", "global")
CAMERA_MODELS = ("auto", "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
# camera model 'auto': square pixels first (every phone and camera has them): RADIAL is OPENCV with fx = fy and no
# tangential terms (f, cx, cy, k1, k2). OPENCV's free fy was poorly constrained on orbits at one height (4.6x the truth
# on a synthetic arc; fx/fy 1.077 on bonsai), and its refusal fell back to a fresh SIMPLE_RADIAL mapping whose focal
# length on bonsai (829 px) disagreed with another self-calibration (~1188 px): two mappings, and the weaker model.
# SIMPLE_RADIAL (one radial term) is the fallback only when RADIAL registers too few images.
AUTO_FIRST, AUTO_FALLBACK = "RADIAL", "SIMPLE_RADIAL"
# part of the cache fingerprint: a capture posed by an older pipeline is posed again (3: the registration check)
POSES_VERSION = 3
REPORT = "poses.json"
WORK = "distorted"
FEW_FEATURES = 100  # images with fewer SIFT features than this are named in failure messages as a likely cause


@dataclass(frozen=True)
class PosesOptions:
    """Settings of `run_poses`.

    matcher: 'exhaustive' matches every pair (n (n-1)/2); 'sequential' matches each image with its `overlap`
        successors (plus successors at distances 2^k) and its `loop_neighbours` most similar images elsewhere in the
        sequence (retrieval with a vocabulary built from the capture's own descriptors); 'auto' = exhaustive up to
        `exhaustive_max` photos, sequential for more and for videos.
    camera_model: COLMAP model estimated (one camera shared by all images with camera_mode 'single'). 'auto' fits
        RADIAL (square pixels, as on every phone and camera: one focal length, principal point, k1, k2; OPENCV
        with fx = fy and no tangential terms) and maps again with SIMPLE_RADIAL (one radial term: COLMAP's
        default) from the same matches only when RADIAL registers fewer than `min_registered` of the images.
        OPENCV (free fy) is still available by name; its fy was poorly constrained on orbits at one height.
    max_image_size: SIFT runs on images downscaled to this longest side, pixels (the mapping and undistortion use
        full-size images).
    min_registered: fail (naming the images left out) when fewer than this fraction of the images register.
    video_rate: frames kept per second of video (the sharpest of each interval); max_frames caps their number.
    undistort: write undistorted pinhole images (True) or copy the originals with the distorted model (the
        trisplat loader then undistorts at load time).
    seed: RANSAC and mapper seed (runs are repeatable on one machine).
    mapper: 'global' (the default: COLMAP's global mapper, GLOMAP: all rotations, then all positions, then bundle
        adjustment; when it registers fewer than `min_registered` of the images, the incremental mapper maps the same
        matches again) or 'incremental' (COLMAP's incremental mapper, one image at a time). On bonsai's 168 photos
        the incremental mapper's multi-threaded result differed between two machines (f 827.7 px at 0.35 px, then
        727 px at 0.80 px with 10 mirror registrations); the global mapper, on the second machine's matches, found
        827.3 px at 0.40 px with 168 of 168 in half the time (docs/benchmarks.md).
    """

    matcher: str = "auto"
    exhaustive_max: int = 100
    overlap: int = 10
    loop_neighbours: int = 5
    camera_model: str = "auto"
    camera_mode: str = "single"
    max_image_size: int = 3200
    max_features: int = 8192
    min_registered: float = 0.5
    video_rate: float = 2.0
    max_frames: int = 300
    undistort: bool = True
    seed: int = 0
    force: bool = False
    verbose: bool = False
    mapper: str = "global"

    def __post_init__(self) -> None:
        if self.mapper not in MAPPERS:
            raise ValueError(f"mapper must be one of {MAPPERS}, got {self.mapper!r}")
        if self.matcher not in MATCHERS:
            raise ValueError(f"matcher must be one of {MATCHERS}, got {self.matcher!r}")
        if self.camera_mode not in CAMERA_MODES:
            raise ValueError(f"camera_mode must be one of {CAMERA_MODES}, got {self.camera_mode!r}")
        if self.camera_model not in CAMERA_MODELS:
            raise ValueError(f"camera_model must be one of {CAMERA_MODELS}, got {self.camera_model!r}")
        if not 0.0 <= self.min_registered <= 1.0:
            raise ValueError(f"min_registered must be a fraction in [0, 1], got {self.min_registered}")
        if self.overlap < 1 or self.loop_neighbours < 0 or self.exhaustive_max < 0:
            raise ValueError("overlap must be >= 1, loop_neighbours and exhaustive_max >= 0")
        if self.max_image_size < 64 or self.max_features < 64:
            raise ValueError("max_image_size and max_features must be >= 64")


@dataclass
class PosesReport:
    """What run_poses produced. Reprojection error in pixels of the original images; times in seconds."""

    source: str
    out: str
    n_input: int
    registered: list[str]
    unregistered: list[str]
    skipped: list[str]
    points: int
    mean_reprojection_error_px: float
    mean_track_length: float
    camera_model: str
    camera_params: list[float]
    image_size: list[int] | None
    focal_from_exif: bool
    matcher: str
    pairs: int
    verified_pairs: int
    models: int
    times: dict[str, float] = field(default_factory=dict)
    video: dict | None = None
    warnings: list[str] = field(default_factory=list)
    registration: dict | None = None  # the registration check (trisplat.sfm.verify.Repair.as_dict)

    @property
    def registered_fraction(self) -> float:
        return len(self.registered) / max(self.n_input, 1)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["registered_fraction"] = self.registered_fraction
        return d

    def summary(self) -> str:
        lines = [
            f"registered  {len(self.registered)} / {self.n_input} images ({100 * self.registered_fraction:.0f}%)",
            f"points      {self.points} (mean track length {self.mean_track_length:.2f})",
            f"reprojection error  {self.mean_reprojection_error_px:.3f} px (mean)",
            f"camera      {self.camera_model} {', '.join(f'{p:.4g}' for p in self.camera_params)}"
            f"{' (focal prior from EXIF)' if self.focal_from_exif else ''}",
            f"matching    {self.matcher}: {self.pairs} pairs, {self.verified_pairs} verified",
            "time        " + ", ".join(f"{k} {v:.1f} s" for k, v in self.times.items()),
        ]
        if self.unregistered:
            lines.append(f"not registered  {name_list(self.unregistered)}")
        lines += [f"warning     {w}" for w in self.warnings]
        lines.append(f"capture     {self.out} (images/, sparse/0; train it with: trisplat train {self.out} --out RUN)")
        return "\n".join(lines)


@contextmanager
def _quiet_colmap(verbose: bool):
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if verbose else 2  # 2: errors only; our own progress replaces COLMAP's log
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def _chunks(seq: list, size: int):
    for s in range(0, len(seq), size):
        yield seq[s : s + size]


def _bar(total: int, desc: str, unit: str, progress: bool):
    from trisplat.progress import progress_bar

    return progress_bar(total=total, desc=desc, unit=unit, disable=not progress, leave=True)


_OURS = ("images", "sparse", WORK, REPORT)


def _check_out(out: Path, source: Path, force: bool) -> None:
    """Refuse an output folder inside the input folder, or one holding anything but an earlier result (and that
    only with `force`)."""
    if out.resolve() == source.resolve() or (source.is_dir() and out.resolve().is_relative_to(source.resolve())):
        raise ValueError(f"--out {out} lies inside the input folder {source}: choose a folder elsewhere")
    if out.exists() and any(out.iterdir()):
        if not force:
            raise FileExistsError(f"{out} is not empty; pass --force to replace its images/, sparse/, {WORK}/ and "
                                  f"{REPORT}")
        others = [p.name for p in out.iterdir() if p.name not in _OURS]
        if others:
            raise FileExistsError(f"{out} holds files that are not from `trisplat poses` ({name_list(others)}); "
                                  f"choose an empty folder")


def _prepare_out(out: Path, source: Path, force: bool) -> None:
    _check_out(out, source, force)
    if out.exists():
        for name in _OURS:
            p = out / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    out.mkdir(parents=True, exist_ok=True)


def _extract(db: Path, image_dir: Path, names: list[str], opts: PosesOptions, progress: bool) -> dict:
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = AUTO_FIRST if opts.camera_model == "auto" else opts.camera_model
    mode = pycolmap.CameraMode.SINGLE if opts.camera_mode == "single" else pycolmap.CameraMode.PER_IMAGE
    ext = pycolmap.FeatureExtractionOptions()
    ext.max_image_size = opts.max_image_size
    ext.sift.max_num_features = opts.max_features
    pycolmap.Database.open(str(db)).close()  # create it
    # importing first creates the shared camera once (EXIF focal where present); extraction then fills keypoints
    pycolmap.import_images(str(db), str(image_dir), camera_mode=mode, image_names=names, options=reader)
    with _bar(len(names), "SIFT features", "img", progress) as bar:
        for chunk in _chunks(names, max(2, math.ceil(len(names) / 25))):
            pycolmap.extract_features(str(db), str(image_dir), image_names=chunk, camera_mode=mode,
                                      reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
            bar.update(len(chunk))
    with pycolmap.Database.open(str(db)) as d:
        images = {im.name: im.image_id for im in d.read_all_images()}
        counts = {name: int(d.num_keypoints_for_image(iid)) for name, iid in images.items()}
        exif = all(c.has_prior_focal_length for c in d.read_all_cameras())
    return {"ids": images, "features": counts, "exif": exif}


def _descriptors(db: Path, ids: list[int]) -> list[np.ndarray]:
    import pycolmap

    with pycolmap.Database.open(str(db)) as d:
        return [np.asarray(d.read_descriptors(i).data) for i in ids]


def _match(db: Path, work: Path, names: list[str], pairs: list[tuple[int, int]], seed: int, progress: bool) -> None:
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.random_seed = seed
    pair_file = work / "pairs.txt"
    with _bar(len(pairs), "matching", "pair", progress) as bar:
        for chunk in _chunks(pairs, 64):
            pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in chunk))
            pairing = pycolmap.ImportedPairingOptions()
            pairing.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(str(db), matching_options=matching, pairing_options=pairing,
                                       verification_options=verify, device=pycolmap.Device.cpu)
            bar.update(len(chunk))
    # every selected pair, as a record of the matching
    pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))


def _verified(db: Path, id_to_name: dict[int, str]) -> tuple[int, dict[str, int]]:
    """Number of verified pairs and, per image, how many verified pairs it belongs to."""
    import pycolmap

    per_image = {n: 0 for n in id_to_name.values()}
    with pycolmap.Database.open(str(db)) as d:
        pair_ids, inliers = d.read_two_view_geometry_num_inliers()
    n = 0
    for pid, k in zip(pair_ids, inliers):
        if k <= 0:
            continue
        a, b = pycolmap.pair_id_to_image_pair(pid)
        n += 1
        for i in (a, b):
            if i in id_to_name:
                per_image[id_to_name[i]] += 1
    return n, per_image


def _map(db: Path, image_dir: Path, work: Path, n_images: int, seed: int, progress: bool, mapper: str = "incremental"):
    """The reconstructions COLMAP's `mapper` ('incremental' or 'global', PosesOptions.mapper) makes of the matches."""
    import pycolmap

    tmp = work / "mapper"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        if mapper == "global":
            gopts = pycolmap.GlobalPipelineOptions()
            gopts.random_seed = seed
            return list(pycolmap.global_mapping(str(db), str(image_dir), str(tmp), options=gopts).values())
        opts = pycolmap.IncrementalPipelineOptions()
        opts.random_seed = seed
        opts.mapper.random_seed = seed
        opts.triangulation.random_seed = seed
        bar = _bar(n_images, "mapping", "img", progress)

        def on_pair():
            bar.update(2)

        def on_next():
            if bar.n < bar.total:
                bar.update(1)

        try:
            models = pycolmap.incremental_mapping(str(db), str(image_dir), str(tmp), options=opts,
                                                  initial_image_pair_callback=on_pair, next_image_callback=on_next)
        finally:
            bar.close()
        return list(models.values())
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _set_camera_model(db: Path, model: str) -> None:
    """Switch every camera of the database to `model`, from its initial focal length and principal point."""
    import pycolmap

    with pycolmap.Database.open(str(db)) as d:
        for cam in d.read_all_cameras():
            n_extra = {"SIMPLE_PINHOLE": 0, "SIMPLE_RADIAL": 1, "RADIAL": 2}[model]
            params = [cam.mean_focal_length(), cam.principal_point_x, cam.principal_point_y] + [0.0] * n_extra
            new = pycolmap.Camera(model=model, width=cam.width, height=cam.height, params=params,
                                  camera_id=cam.camera_id)
            new.has_prior_focal_length = cam.has_prior_focal_length
            d.update_camera(new)


def _undistort(model_dir: Path, image_dir: Path, names: list[str], out: Path, progress: bool) -> None:
    """pycolmap's undistorter into OUT/images and OUT/sparse/0 (run in a thread; progress from the files written)."""
    import pycolmap

    tmp = out / WORK / "undistorted"
    if tmp.exists():
        shutil.rmtree(tmp)
    error: list[BaseException] = []

    def work():
        try:
            pycolmap.undistort_images(str(tmp), str(model_dir), str(image_dir), image_names=names,
                                      output_type="COLMAP", jpeg_quality=95)
        except BaseException as exc:  # re-raised in the caller's thread
            error.append(exc)

    th = threading.Thread(target=work, daemon=True)
    th.start()
    with _bar(len(names), "undistorting", "img", progress) as bar:
        while th.is_alive():
            th.join(0.25)
            done = len(list((tmp / "images").glob("*"))) if (tmp / "images").is_dir() else 0
            bar.update(max(0, min(done, len(names)) - bar.n))
        bar.update(len(names) - bar.n)
    if error:
        raise RuntimeError(f"undistortion of {model_dir} failed: {error[0]}") from error[0]
    shutil.move(str(tmp / "images"), str(out / "images"))
    (out / "sparse").mkdir(exist_ok=True)
    shutil.move(str(tmp / "sparse"), str(out / "sparse" / "0"))
    shutil.rmtree(tmp, ignore_errors=True)


def _copy_distorted(model_dir: Path, image_dir: Path, names: list[str], out: Path) -> None:
    (out / "images").mkdir(parents=True)
    for n in names:
        shutil.copy2(image_dir / n, out / "images" / n)
    shutil.copytree(model_dir, out / "sparse" / "0")


def _failure(n_ok: int, names: list[str], registered: set[str], features: dict[str, int], pairs: dict[str, int],
             needed: int, source: Path, work: Path) -> ValueError:
    left = [n for n in names if n not in registered]
    detail = [f"{n} ({features.get(n, 0)} features, {pairs.get(n, 0)} verified pairs)" for n in left]
    few = [n for n in left if features.get(n, 0) < FEW_FEATURES]
    hint = (f"; {len(few)} of them have fewer than {FEW_FEATURES} features (blurred, dark or textureless?)"
            if few else "; they share too few matches with the rest (too little overlap between views?)")
    return ValueError(f"{source}: only {n_ok} of {len(names)} images registered (need at least {needed}); "
                      f"not registered: {name_list(detail)}{hint}. Features and matches are kept in {work}")


def run_poses(source: str | Path, out: str | Path, options: PosesOptions | None = None, progress: bool = True,
              log: Callable[[str], None] | None = None) -> PosesReport:
    """Estimate camera poses for a folder of photos or a video file and write a COLMAP capture to `out`.

    Raises ValueError naming the images concerned for bad input (fewer than 3 images, unreadable, blank, mixed
    sizes with camera_mode 'single') and when fewer than `options.min_registered` of the images register.
    `out` must be empty or hold an earlier `trisplat poses` result (replaced with options.force). Returns the
    report, also written to `out`/poses.json.
    """
    import pycolmap  # noqa: F401  (fail early if missing)

    opts = options or PosesOptions()
    say = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    source, out = Path(source), Path(out)
    if not source.exists():
        raise FileNotFoundError(f"{source}: no such folder or video file")
    video = is_video(source)
    if not video and not source.is_dir():
        raise ValueError(f"{source}: expected a folder of photos or a video file ({', '.join(VIDEO_SUFFIXES)})")
    if not video:  # photos are checked before anything is written
        _check_out(out, source, opts.force)
        t_check, cpu_check = time.perf_counter(), time.process_time()
        files = find_images(source)
        if not files:
            raise ValueError(f"{source}: no image files ({', '.join(IMAGE_SUFFIXES)}) directly in this folder "
                             f"(subfolders are not searched)")
        check = check_images(files, same_size=opts.camera_mode == "single", where=str(source))
        t_check, cpu_check = time.perf_counter() - t_check, time.process_time() - cpu_check
    _prepare_out(out, source, opts.force)
    work = out / WORK
    work.mkdir()
    times: dict[str, float] = {}
    warnings: list[str] = []
    video_info = None
    stage = "video frames" if video else "input"
    n_stages = 6 if video else 5
    k = 0

    cpu: dict[str, float] = {}  # CPU seconds of the whole process (all its threads) per stage
    cpu_at = time.process_time()

    def head(title: str) -> float:
        nonlocal k, cpu_at
        k += 1
        say(f"[{k}/{n_stages}] {title}")
        cpu_at = time.process_time()
        return time.perf_counter()

    def done(name: str, t: float) -> None:
        times[name] = time.perf_counter() - t
        cpu[name] = time.process_time() - cpu_at

    with _quiet_colmap(opts.verbose):
        if video:
            from trisplat.sfm.video import extract_frames

            t = head(f"frames: the sharpest of each 1/{opts.video_rate:g} s of {source.name}")
            sel = extract_frames(source, work / "images", rate=opts.video_rate, max_frames=opts.max_frames,
                                 progress=progress)
            image_dir = work / "images"
            files = sel.files
            video_info = {"fps": sel.fps, "rate": sel.rate, "frames_read": sel.frames_read,
                          "frames_kept": len(sel.files), "frame_indices": sel.frame_indices}
            say(f"      kept {len(files)} of {sel.frames_read} frames ({sel.rate:.3g} per second of video)")
            done(stage, t)
            t = head(f"checking {len(files)} frames")
            check = check_images(files, same_size=True, where=str(source))
        else:
            image_dir = source
            t = head(f"checked {len(files)} images") - t_check
            cpu_at -= cpu_check
        for w in check.warnings:
            say(f"      warning: {w}")
        warnings += check.warnings
        names = [p.name for p in check.images]
        done("input", t)

        first_model = AUTO_FIRST if opts.camera_model == "auto" else opts.camera_model
        t = head(f"SIFT features ({first_model}, {opts.camera_mode} camera)")
        db = work / "database.db"
        feats = _extract(db, image_dir, names, opts, progress)
        say("      focal: " + ("from EXIF" if feats["exif"] else
                                "no EXIF focal length; starting from 1.2 x the longest side, refined by bundle adjustment"))
        done("features", t)

        matcher = opts.matcher
        if matcher == "auto":
            matcher = "sequential" if video or len(names) > opts.exhaustive_max else "exhaustive"
        t = head(f"matching ({matcher})")
        if matcher == "exhaustive":
            pairs = exhaustive_pairs(len(names))
        else:
            pairs = set(sequential_pairs(len(names), opts.overlap))
            if opts.loop_neighbours and len(names) > opts.overlap + 1:
                sim = retrieval_similarity(_descriptors(db, [feats["ids"][n] for n in names]), seed=opts.seed)
                pairs |= set(loop_pairs(sim, opts.loop_neighbours, min_distance=opts.overlap + 1))
            pairs = sorted(pairs)
        _match(db, work, names, pairs, opts.seed, progress)
        id_to_name = {i: n for n, i in feats["ids"].items()}
        n_verified, per_image = _verified(db, id_to_name)
        say(f"      {n_verified} of {len(pairs)} pairs verified")
        done("matching", t)

        needed = max(MIN_IMAGES, math.ceil(opts.min_registered * len(names)))
        t = head(f"{opts.mapper} mapping")
        models = _map(db, image_dir, work, len(names), opts.seed, progress, opts.mapper)

        def map_again(models, first: str, then: str, again):
            """`models`, or again()'s models when `models` register fewer than `needed` images and again()'s more."""
            have = max((r.num_reg_images() for r in models), default=0)
            if have >= needed:
                return models
            note = f"{first} registered {have} of {len(names)} images (fewer than {needed}); mapped again with {then}"
            say(f"      {note}")
            warnings.append(note)
            other = again()
            return other if max((r.num_reg_images() for r in other), default=0) > have else models

        def fallback_camera():
            _set_camera_model(db, AUTO_FALLBACK)
            return _map(db, image_dir, work, len(names), opts.seed, progress, opts.mapper)

        if opts.camera_model == "auto":
            models = map_again(models, f"the {AUTO_FIRST} fit", AUTO_FALLBACK, fallback_camera)
        if opts.mapper == "global":
            models = map_again(models, "the global mapper", "the incremental mapper",
                               lambda: _map(db, image_dir, work, len(names), opts.seed, progress, "incremental"))
        done("mapping", t)
        if not models:
            raise _failure(0, names, set(), feats["features"], per_image, needed, source, work)
        best = max(models, key=lambda r: (r.num_reg_images(), r.num_points3D()))
        registered = {best.images[i].name for i in best.reg_image_ids()}
        elsewhere = {r.images[i].name for r in models if r is not best for i in r.reg_image_ids()} - registered
        if elsewhere:
            warnings.append(f"the images formed {len(models)} separate models; kept the largest "
                            f"({len(registered)} images); left out, in smaller models: {name_list(sorted(elsewhere))}")
        t = time.perf_counter()
        best, repair = repair_registration(db, image_dir, best, work, seed=opts.seed)
        done("registration check", t)
        if repair.flagged:
            note = (f"{len(repair.flagged)} image(s) were registered where their own matches disagree (a mirror "
                    f"position on repeated or symmetric content): {name_list(repair.flagged)}; "
                    + (f"registered again consistently: {name_list(repair.reregistered)}"
                       if repair.reregistered else "none registered again")
                    + (f"; left out of the capture: {name_list(repair.dropped)}" if repair.dropped else ""))
            say(f"      {note}")
            warnings.append(note)
        registered = {best.images[i].name for i in best.reg_image_ids()}
        if len(registered) < needed:
            raise _failure(len(registered), names, registered, feats["features"], per_image, needed, source, work)
        model_dir = work / "sparse" / "0"
        model_dir.mkdir(parents=True)
        best.write(str(model_dir))
        reg_names = [n for n in names if n in registered]
        unregistered = [n for n in names if n not in registered]
        if unregistered:
            warnings.append(f"{len(unregistered)} image(s) not registered (left out of the capture): "
                            f"{name_list(unregistered)}")

        t = head("undistorting to pinhole" if opts.undistort else "copying images (distorted model kept)")
        if opts.undistort:
            _undistort(model_dir, image_dir, reg_names, out, progress)
        else:
            _copy_distorted(model_dir, image_dir, reg_names, out)
        done("undistortion", t)
    # how many cores each stage kept busy (CPU time of all threads / wall time): COLMAP's stages use every core
    say(f"      {sum(times.values()) / 60:.1f} min on {os.cpu_count()} cores: "
        + ", ".join(f"{name} {sec:.0f} s ({cpu[name] / sec:.1f} cores busy)" for name, sec in times.items()
                    if sec >= 0.5))

    cam = next(iter(best.cameras.values()))
    report = PosesReport(
        source=str(source), out=str(out), n_input=len(files), registered=reg_names, unregistered=unregistered,
        skipped=[p.name for p in check.blank], points=int(best.num_points3D()),
        mean_reprojection_error_px=float(best.compute_mean_reprojection_error()),
        mean_track_length=float(best.compute_mean_track_length()), camera_model=cam.model.name,
        camera_params=[float(p) for p in cam.params], image_size=list(check.size) if check.size else None,
        focal_from_exif=bool(feats["exif"]), matcher=matcher, pairs=len(pairs), verified_pairs=n_verified,
        models=len(models), times=times, video=video_info, warnings=warnings, registration=repair.as_dict(),
    )
    (out / REPORT).write_text(json.dumps(report.as_dict(), indent=2))
    return report
