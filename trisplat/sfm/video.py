"""Frames from a video for SfM: one frame per interval of 1/rate seconds, the sharpest of each (imageio + ffmpeg)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def sharpness(frame: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (higher = sharper; motion blur lowers it). frame: uint8 [H,W,3]."""
    g = frame[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    lap = g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var())


@dataclass(frozen=True)
class FrameSelection:
    """What extract_frames wrote: files (in time order), the source frame index and time (s) of each, the rate used."""

    files: list[Path]
    frame_indices: list[int]
    times: list[float]
    fps: float
    rate: float
    frames_read: int


def _open(video: Path):
    try:
        import imageio.v2 as iio
        import imageio_ffmpeg  # noqa: F401  (the ffmpeg binary comes with this wheel)
    except ImportError as exc:
        raise ImportError(f"reading videos needs imageio and imageio-ffmpeg: pip install imageio imageio-ffmpeg "
                          f"({exc})") from None
    try:
        return iio.get_reader(str(video), format="ffmpeg")
    except Exception as exc:
        raise ValueError(f"{video}: cannot read the video ({type(exc).__name__}: {exc})") from None


def extract_frames(video: Path, out_dir: Path, rate: float = 2.0, max_frames: int = 300, progress: bool = True,
                   jpeg_quality: int = 95) -> FrameSelection:
    """Write the sharpest frame of each 1/`rate`-second interval of `video` to `out_dir`/frame_<index>.jpg.

    rate: frames kept per second of video; lowered when the video's duration times it exceeds `max_frames`.
    The sharpness measure is the variance of the Laplacian (see `sharpness`). Frames are named after their index
    in the video, so names sort in time order.
    """
    from PIL import Image
    from trisplat.progress import progress_bar

    video = Path(video)
    if not video.is_file():
        raise FileNotFoundError(f"{video}: video file does not exist")
    if not rate > 0:
        raise ValueError(f"frame rate must be > 0 frames per second, got {rate}")
    reader = _open(video)
    meta = reader.get_meta_data()
    fps = float(meta.get("fps") or 0.0)
    if not fps > 0:
        raise ValueError(f"{video}: the video reports no frame rate")
    duration = float(meta.get("duration") or 0.0)
    if duration > 0 and duration * rate > max_frames:
        rate = max_frames / duration
    n_total = int(round(duration * fps)) if duration > 0 else None
    out_dir.mkdir(parents=True, exist_ok=True)
    files, indices, times = [], [], []
    best: tuple[float, int, np.ndarray] | None = None
    current = None
    read = 0

    def flush():
        if best is None:
            return
        _, idx, frame = best
        path = out_dir / f"frame_{idx:06d}.jpg"
        Image.fromarray(np.ascontiguousarray(frame[..., :3])).save(path, quality=jpeg_quality)
        files.append(path)
        indices.append(idx)
        times.append(idx / fps)

    bar = progress_bar(total=n_total, desc="reading video", unit="frame", disable=not progress)
    try:
        for i, frame in enumerate(reader):
            read += 1
            bar.update(1)
            interval = math.floor(i / fps * rate + 1e-9)
            if interval != current:
                flush()
                best, current = None, interval
            s = sharpness(frame)
            if best is None or s > best[0]:
                best = (s, i, np.asarray(frame))
        flush()
    except Exception as exc:
        if read == 0:
            raise ValueError(f"{video}: cannot decode frames ({type(exc).__name__}: {exc})") from None
        # a truncated tail: keep what was read
        flush()
    finally:
        bar.close()
        reader.close()
    if read == 0:
        raise ValueError(f"{video}: the video holds no frames")
    return FrameSelection(files, indices, times, fps, rate, read)
