"""`trisplat train PHOTOS`: a plain photo folder is posed first into a cache folder outside it, then reused."""
from __future__ import annotations

import hashlib
import json
import os
import shutil

from trisplat.data.capture import is_plain_image_folder
from trisplat.sfm.cache import FINGERPRINT, cache_folder, fingerprint, posed_capture
from trisplat.sfm.pipeline import REPORT, WORK, PosesOptions


def test_plain_image_folder_detection(tmp_path, synthetic_frames, synthetic_capture):
    folder, _ = synthetic_frames
    _, capture = synthetic_capture
    assert is_plain_image_folder(folder)
    assert not is_plain_image_folder(capture)  # it has sparse/0
    assert not is_plain_image_folder(capture / "images" / "frame_000.png")  # a file
    (tmp_path / "transforms.json").write_text("{}")
    (tmp_path / "a.png").write_bytes((folder / "frame_000.png").read_bytes())
    assert not is_plain_image_folder(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert not is_plain_image_folder(empty)


def test_train_on_photos_poses_into_the_cache_once(tmp_path, monkeypatch, synthetic_frames):
    from trisplat.commands.train import make_train_args, pose_plain_photos

    folder, cams = synthetic_frames
    before = sorted(p.name for p in folder.iterdir())
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    messages: list[str] = []
    args = make_train_args(folder, tmp_path / "run", preset="fast")
    posed = pose_plain_photos(args)
    capture = posed.data
    assert capture == cache_folder(folder) and capture.is_relative_to(tmp_path / "xdg" / "trisplat" / "poses")
    assert (capture / "sparse" / "0").is_dir() and (capture / REPORT).is_file()
    assert json.loads((capture / REPORT).read_text())["registered_fraction"] == 1.0
    assert sorted(p.name for p in folder.iterdir()) == before  # nothing written into the photos' folder
    # a second run reuses the cached capture (and says so) instead of running SfM again
    stamp = (capture / REPORT).stat().st_mtime_ns
    assert posed_capture(folder, log=messages.append, progress=False) == capture
    assert "earlier" in messages[0] and (capture / REPORT).stat().st_mtime_ns == stamp
    # resuming maps the photos to the same capture without running anything
    resumed = pose_plain_photos(make_train_args(folder, tmp_path / "run", preset="fast", resume=True))
    assert resumed.data == capture
    # the fingerprint that decides reuse lists every photo with its size and the hash of its bytes
    fp = json.loads((capture / WORK / FINGERPRINT).read_text())
    assert [f[0] for f in fp["files"]] == [f"{c.name}.png" for c in cams]
    assert fp["files"][0][1] == (folder / "frame_000.png").stat().st_size
    assert fp["files"][0][2] == hashlib.sha1((folder / "frame_000.png").read_bytes()).hexdigest()
    # photos touched (copied, synced again: same bytes, new times) keep their poses ...
    for p in folder.iterdir():
        os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 10**9))
    messages.clear()
    assert posed_capture(folder, log=messages.append, progress=False) == capture
    assert "earlier" in messages[0] and (capture / REPORT).stat().st_mtime_ns == stamp
    # ... and a photo whose bytes changed (same size) does not (in a copy: the photos are a shared fixture)
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)
    want = fingerprint(copy, PosesOptions())
    frame = copy / "frame_000.png"
    data = bytearray(frame.read_bytes())
    data[-20] ^= 0xFF
    frame.write_bytes(bytes(data))
    got = fingerprint(copy, PosesOptions())
    assert got != want and got["files"][1:] == want["files"][1:] and got["files"][0][1] == want["files"][0][1]


def _photos(folder):
    import numpy as np
    from PIL import Image

    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        Image.fromarray(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(folder / f"p{i}.jpg")
    return folder


def test_train_on_photos_checks_out_and_device_before_structure_from_motion(tmp_path, monkeypatch, capsys):
    """A bad --device, an --out that holds files (no --force), or --resume of nothing fail at once: the structure
    from motion that would pose the photos first (minutes) is never started."""
    import torch

    import trisplat.sfm.cache
    from trisplat.cli import main

    def no_sfm(*a, **k):
        raise AssertionError("structure from motion was started before the cheap checks")

    monkeypatch.setattr(trisplat.sfm.cache, "posed_capture", no_sfm)
    monkeypatch.setattr(trisplat.sfm.cache, "cache_folder", no_sfm)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    photos = _photos(tmp_path / "photos")
    assert is_plain_image_folder(photos)

    assert main(["train", str(photos), "--out", str(tmp_path / "new"), "--device", "cuda", "--preset", "fast"]) == 1
    assert "device 'cuda'" in capsys.readouterr().err and not (tmp_path / "new").exists()

    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    assert main(["train", str(photos), "--out", str(busy), "--preset", "fast"]) == 1
    assert f"{busy} already holds files; pass --force" in capsys.readouterr().err
    assert sorted(p.name for p in busy.iterdir()) == ["notes.txt"]

    assert main(["train", str(photos), "--out", str(tmp_path / "none"), "--resume"]) == 1
    assert "nothing to resume" in capsys.readouterr().err

    for bad, said in ((["--downscale", "3"], "downscale must be one of"), (["--steps", "0"], "--steps must be at least 1"),
                      (["--minutes", "0"], "--minutes must be > 0")):
        assert main(["train", str(photos), "--out", str(tmp_path / "new"), *bad]) == 1
        assert said in capsys.readouterr().err
    assert not (tmp_path / "new").exists() and not (tmp_path / "xdg").exists()


def test_two_runs_on_the_same_photos_pose_them_once(tmp_path, monkeypatch):
    """A second run started while the first is still posing the photos waits for it and reuses its capture; it does
    not run structure from motion into the same cache folder beside it."""
    import threading
    import time

    import trisplat.sfm.cache as cache

    photos = _photos(tmp_path / "photos")
    calls: list[float] = []

    class Report:
        registered, n_input, points, mean_reprojection_error_px = [0, 1, 2], 3, 10, 0.5

    def slow_poses(source, out, options, progress=True, log=None):
        calls.append(time.monotonic())
        (out / WORK).mkdir(parents=True, exist_ok=True)
        time.sleep(0.5)
        (out / REPORT).write_text("{}")
        return Report()

    monkeypatch.setattr(cache, "run_poses", slow_poses)
    logs: list[list[str]] = [[], []]
    results: list = [None, None]

    def run(i):
        results[i] = cache.posed_capture(photos, cache_root=tmp_path / "cache", progress=False, log=logs[i].append)

    first = threading.Thread(target=run, args=(0,))
    first.start()
    time.sleep(0.1)
    run(1)
    first.join()
    assert len(calls) == 1
    assert results[0] == results[1] == cache_folder(photos, tmp_path / "cache")
    assert "waiting" in logs[1][0] and "earlier" in logs[1][-1]
