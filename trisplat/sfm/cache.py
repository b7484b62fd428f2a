"""Poses for `trisplat train PHOTOS`: run `poses` once into a cache folder (never inside the user's folder), reuse it."""
from __future__ import annotations

import hashlib
import json
import sys
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

from trisplat.sfm.inputs import find_images, is_video
from trisplat.sfm.pipeline import POSES_VERSION, REPORT, WORK, PosesOptions, run_poses

FINGERPRINT = "source.json"  # in OUT/distorted: what the cached capture was computed from


def default_poses_cache() -> Path:
    """$XDG_CACHE_HOME/trisplat/poses (or ~/.cache/trisplat/poses)."""
    from trisplat.data.options import default_cache_dir

    return default_cache_dir() / "poses"


def _sha1(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha1").hexdigest()


def fingerprint(source: Path, options: PosesOptions) -> dict:
    """The input files (name, size, SHA-1 of the bytes) and the settings: a cached capture is reused while equal.
    The bytes, not the modification times: photos copied, synced or unpacked again keep their poses (a re-provisioned
    copy of bonsai's 168 photos, same bytes, new times, ran 20 minutes of structure from motion again and got other
    poses). Hashing costs about 10 ms per MB."""
    source = Path(source).resolve()
    files = [source] if is_video(source) else find_images(source)
    opts = asdict(replace(options, force=False, verbose=False))
    return {"pipeline": POSES_VERSION, "source": str(source),
            "files": [[p.name, p.stat().st_size, _sha1(p)] for p in files],
            "options": opts}


def cache_folder(source: Path, cache_root: Path | None = None) -> Path:
    """CACHE/<name>-<hash of the absolute path>: one capture per photo folder or video (outside it)."""
    source = Path(source).resolve()
    root = Path(cache_root) if cache_root is not None else default_poses_cache()
    folder = root / f"{source.stem}-{hashlib.sha1(str(source).encode()).hexdigest()[:10]}"
    if folder.resolve().is_relative_to(source) if source.is_dir() else False:
        raise ValueError(f"the poses cache {root} lies inside the photo folder {source}: set XDG_CACHE_HOME elsewhere")
    return folder


def posed_capture(source: Path, options: PosesOptions | None = None, cache_root: Path | None = None,
                  progress: bool = True, log: Callable[[str], None] | None = None) -> Path:
    """A COLMAP capture of the photos (or video) `source`: the cached one when its fingerprint still matches,
    else `run_poses` into the cache folder first. Returns the capture folder."""
    from filelock import FileLock, Timeout  # torch's own dependency

    say = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    opts = options or PosesOptions()
    out = cache_folder(source, cache_root)
    out.parent.mkdir(parents=True, exist_ok=True)
    # two runs on the same photos at once: the second waits for the first's poses instead of running structure from
    # motion into the same folder beside it (where each would delete the other's files)
    lock = FileLock(str(out) + ".lock")
    try:
        lock.acquire(timeout=0)
    except Timeout:
        say(f"another trisplat run is computing the poses of {source} into {out}: waiting for it to finish "
            f"(lock {lock.lock_file})")
        lock.acquire()
    try:
        return _posed_capture_locked(source, opts, out, progress, log, say)
    finally:
        lock.release()


def _posed_capture_locked(source: Path, opts: PosesOptions, out: Path, progress: bool,
                          log: Callable[[str], None] | None, say: Callable[[str], None]) -> Path:
    want = fingerprint(source, opts)
    stamp = out / WORK / FINGERPRINT
    if (out / REPORT).is_file() and stamp.is_file():
        try:
            same = json.loads(stamp.read_text()) == json.loads(json.dumps(want))
        except ValueError:
            same = False
        if same:
            say(f"{source} has no poses: using the capture `trisplat poses` made of it earlier, {out}")
            return out
    say(f"{source} has no poses: running `trisplat poses` first, into {out} (reused while the photos are unchanged)")
    report = run_poses(source, out, replace(opts, force=True), progress=progress, log=log)
    stamp.write_text(json.dumps(want, indent=1))
    say(f"poses: {len(report.registered)} of {report.n_input} images registered, {report.points} points, mean "
        f"reprojection error {report.mean_reprojection_error_px:.2f} px (report: {out / REPORT})")
    return out
