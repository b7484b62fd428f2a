"""Image files: header checks, decoding to RGB(A), compositing over a background, a memory-bounded LRU."""
from __future__ import annotations

import os
import threading
from collections import OrderedDict
from pathlib import Path
from collections.abc import Callable

import numpy as np
from PIL import Image, UnidentifiedImageError


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header; missing or unreadable files raise with the file named."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file does not exist")
    try:
        with Image.open(path) as im:
            return im.size
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"{path}: unreadable image ({exc})") from None


# what a complete file of each format ends with (trailing bytes after it are tolerated only if they are padding)
_FILE_ENDS = {"JPEG": b"\xff\xd9", "PNG": b"IEND\xaeB`\x82"}
_SUFFIX_FORMATS = {".jpg": "JPEG", ".jpeg": "JPEG", ".png": "PNG"}


def check_image_file(path: Path) -> tuple[int, int, str | None]:
    """(width, height, warning or None) from the file header, after two cheap checks of the whole file: a JPEG or
    PNG must end with its end marker (a truncated file is refused now, not half-way through training), and a file
    whose content is another format than its suffix says (a JPEG renamed .png: no alpha channel) gets a warning."""
    path = Path(path)
    w, h = image_size(path)
    with Image.open(path) as im:
        fmt = im.format
    end = _FILE_ENDS.get(fmt)
    if end is not None:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - 4096))
            tail = f.read().rstrip(b"\x00\r\n\t ")
        if not tail.endswith(end):
            raise ValueError(f"{path}: truncated or damaged {fmt} file (it does not end with the {fmt} end marker); "
                             "re-export it or remove it from the capture")
    expected = _SUFFIX_FORMATS.get(path.suffix.lower())
    warning = None
    if expected is not None and fmt is not None and fmt != expected:
        warning = (f"{path}: a {fmt} file named {path.suffix}" + (" (it has no alpha channel)" if expected == "PNG"
                                                                  and fmt == "JPEG" else ""))
    return w, h, warning


def read_image(path: Path) -> np.ndarray:
    """Decode to uint8 [H,W,3] (RGB) or [H,W,4] (RGBA, straight alpha); 16-bit greyscale is scaled to 8 bits."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file does not exist")
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                a = np.asarray(im, dtype=np.float64)
                a = np.clip(a / 257.0 + 0.5, 0, 255).astype(np.uint8)
                return np.repeat(a[..., None], 3, axis=2)
            has_alpha = im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info)
            return np.asarray(im.convert("RGBA" if has_alpha else "RGB"))
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"{path}: unreadable image ({exc})") from None


def has_alpha_channel(path: Path) -> bool:
    with Image.open(path) as im:
        return im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info)


def to_float_rgb(img: np.ndarray, background: tuple[float, float, float]) -> np.ndarray:
    """uint8 RGB(A) -> float32 [H,W,3] in [0,1], straight alpha composited over `background`."""
    rgb = img[..., :3].astype(np.float32) / 255.0
    if img.shape[-1] == 4:
        a = img[..., 3:4].astype(np.float32) / 255.0
        rgb = rgb * a + np.asarray(background, dtype=np.float32) * (1.0 - a)
    return rgb


def save_image_atomic(img: np.ndarray, path: Path) -> None:
    """Write a PNG via a temporary file + rename, so a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    Image.fromarray(img).save(tmp, format="PNG", compress_level=1)
    os.replace(tmp, path)


class LRUArrays:
    """index -> numpy array, computed on demand, least recently used dropped beyond `budget_bytes`.

    The most recent array is always kept, even if it alone exceeds the budget. Thread-safe. Returned arrays
    are read-only (they are shared between callers).
    """

    def __init__(self, compute: Callable[[int], np.ndarray], budget_bytes: float):
        self.compute = compute
        self.budget_bytes = float(budget_bytes)
        self._items: OrderedDict[int, np.ndarray] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)

    def __call__(self, index: int) -> np.ndarray:
        index = int(index)
        with self._lock:
            if index in self._items:
                self._items.move_to_end(index)
                return self._items[index]
        arr = self.compute(index)
        arr.flags.writeable = False
        with self._lock:
            if index not in self._items:
                self._items[index] = arr
                self._bytes += arr.nbytes
            while self._bytes > self.budget_bytes and len(self._items) > 1:
                _, old = self._items.popitem(last=False)
                self._bytes -= old.nbytes
        return arr
