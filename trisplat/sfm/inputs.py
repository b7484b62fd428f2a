"""The images SfM starts from: a folder's photos (checked: count, readable, sizes, blank) or a video's suffix test."""
from __future__ import annotations

import re
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
MIN_IMAGES = 3  # incremental SfM needs an initial pair plus at least one registration
BLANK_STD = 2.0 / 255.0  # grey-level standard deviation below which an image is uniform (no features)
LIST_NAMES = 12  # at most this many file names in one error message


def natural_key(name: str):
    """Sort key putting frame_2 before frame_10."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def is_video(path: Path) -> bool:
    return Path(path).is_file() and Path(path).suffix.lower() in VIDEO_SUFFIXES


def find_images(folder: Path) -> list[Path]:
    """Image files directly in `folder` (not its subfolders), in natural name order (frame_2 before frame_10)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: not a folder")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
             and not p.name.startswith(".")]
    return sorted(files, key=lambda p: natural_key(p.name))


def name_list(names, limit: int = LIST_NAMES) -> str:
    names = [str(n) for n in names]
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


@dataclass(frozen=True)
class ImageCheck:
    """What the input check found: usable images, blank ones (skipped) and the common size (None when mixed)."""

    images: list[Path]
    blank: list[Path]
    size: tuple[int, int] | None
    warnings: list[str]


def grey_std(path: Path, max_side: int = 256) -> float:
    """Standard deviation of the grey levels in [0,1] of a thumbnail of the image (raises naming an unreadable file)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.draft("L", (max_side, max_side))  # JPEG: decode at a reduced size
            g = im.convert("L")
            g.thumbnail((max_side, max_side))
            return float(np.asarray(g, dtype=np.float32).std() / 255.0)
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"{path}: unreadable image ({exc})") from None


def check_images(files: list[Path], same_size: bool = True, where: str = "") -> ImageCheck:
    """Validate SfM input images; raise ValueError naming the offending files.

    - fewer than MIN_IMAGES images -> error naming them;
    - unreadable files -> error naming them;
    - blank images (uniform colour, e.g. all black) are skipped with a warning, or an error when fewer than
      MIN_IMAGES usable ones remain;
    - with `same_size`, images of different sizes -> error listing each size with its files.
    """
    from PIL import Image, UnidentifiedImageError

    where = where or (str(files[0].parent) if files else "the input")
    if len(files) < MIN_IMAGES:
        found = f": {name_list(p.name for p in files)}" if files else ""
        raise ValueError(f"{where}: structure from motion needs at least {MIN_IMAGES} images, found {len(files)}{found}")
    sizes: dict[tuple[int, int], list[Path]] = defaultdict(list)
    bad = []
    for p in files:
        try:
            with Image.open(p) as im:
                sizes[im.size].append(p)
        except (UnidentifiedImageError, OSError) as exc:
            bad.append(f"{p.name} ({exc})")
    if bad:
        raise ValueError(f"{where}: unreadable image(s): {name_list(bad)}")
    if same_size and len(sizes) > 1:
        groups = sorted(sizes.items(), key=lambda kv: -len(kv[1]))
        parts = [f"{w}x{h}: {name_list([p.name for p in ps], 6)}" for (w, h), ps in groups]
        raise ValueError(f"{where}: the images have {len(sizes)} different sizes ({'; '.join(parts)}); "
                         f"one camera is assumed: remove or resize the odd ones, or pass --camera-mode per-image")
    blank = [p for p in files if grey_std(p) < BLANK_STD]
    usable = [p for p in files if p not in set(blank)]
    warnings = []
    if blank:
        msg = f"{len(blank)} blank image(s) (uniform colour, nothing to match): {name_list(p.name for p in blank)}"
        if len(usable) < MIN_IMAGES:
            raise ValueError(f"{where}: {msg}; only {len(usable)} usable image(s) left, "
                             f"structure from motion needs at least {MIN_IMAGES}")
        warnings.append(f"skipped {msg}")
    size = next(iter(sizes)) if len(sizes) == 1 else None
    return ImageCheck(usable, blank, size, warnings)
