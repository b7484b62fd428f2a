"""Image files: header checks, decoding to RGB(A), compositing over a background, a memory-bounded LRU."""
from __future__ import annotations

import mmap
import os
import re
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


_SUFFIX_FORMATS = {".jpg": "JPEG", ".jpeg": "JPEG", ".png": "PNG"}
# a JPEG marker inside entropy-coded data: 0xFF followed by a code that is not a stuffed zero, a restart marker
# (RST0-7: part of the scan) or a fill byte
_JPEG_MARKER = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
_JPEG_STANDALONE = set(range(0xD0, 0xD8)) | {0x01}  # markers without a length field (TEM, RSTn)


def _jpeg_end(mm) -> int | None:
    """Offset just past the End Of Image marker that closes the first image of a JPEG file, or None if the file
    ends before it (truncated).

    The marker segments are walked by their lengths (so an EXIF thumbnail's own end marker inside APP1 is skipped)
    and each scan's entropy-coded data is searched for the next marker; the file's last bytes are not looked at,
    so a trailer after the end marker (a Pixel motion photo's MP4, Samsung's SEFH block, an MPF second image) is
    no damage. This reads the file once and decodes nothing: milliseconds for a 12-megapixel photo."""
    n = len(mm)
    if mm[:2] != b"\xff\xd8":
        return None
    pos = 2
    while True:
        if pos < n and mm[pos] != 0xFF:  # stray bytes between segments: skipped, as libjpeg (and so PIL) does
            m = _JPEG_MARKER.search(mm, pos)
            if m is None:
                return None
            pos = m.start()
        while pos + 1 < n and mm[pos + 1] == 0xFF:  # fill bytes before a marker
            pos += 1
        if pos + 2 > n:
            return None
        code = mm[pos + 1]
        if code == 0xD9:  # EOI
            return pos + 2
        if code in _JPEG_STANDALONE:
            pos += 2
            continue
        if pos + 4 > n:
            return None
        end = pos + 2 + int.from_bytes(mm[pos + 2:pos + 4], "big")
        if end > n:
            return None
        pos = end
        if code == 0xDA:  # SOS: the entropy-coded data follows, up to the next marker
            m = _JPEG_MARKER.search(mm, pos)
            if m is None:
                return None
            pos = m.start()


def _png_end(f) -> int | None:
    """Offset just past the IEND chunk of a PNG file, or None if the file ends before it (truncated): the chunks
    are walked by their lengths (seeks, no decoding), so bytes after IEND are no damage."""
    f.seek(0, os.SEEK_END)
    n = f.tell()
    pos = 8
    while pos + 12 <= n:
        f.seek(pos)
        head = f.read(8)
        length = int.from_bytes(head[:4], "big")
        pos += 12 + length
        if head[4:8] == b"IEND":
            return pos if pos <= n else None
    return None


def check_image_file(path: Path) -> tuple[int, int, str | None]:
    """(width, height, warning or None) from the file header, after two cheap checks of the whole file: a JPEG or
    PNG must be complete (a truncated file is refused now, not half-way through training), and a file whose content
    is another format than its suffix says (a JPEG renamed .png: no alpha channel) gets a warning.

    Complete means the image's own end marker is present where the file's structure puts it (a JPEG's EOI after its
    last scan, a PNG's IEND chunk), found by walking the file's segments, not by its last bytes: phone cameras append
    trailers after the end marker (motion photos' videos, vendor metadata) and such photos decode, so they load
    silently. No pixel is decoded (a decode costs ~0.1 s per 12-megapixel photo, this check milliseconds)."""
    path = Path(path)
    w, h = image_size(path)
    with Image.open(path) as im:
        fmt = im.format
    if fmt in ("JPEG", "PNG"):
        with open(path, "rb") as f:
            if fmt == "JPEG":
                with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                    end = _jpeg_end(mm)
            else:
                end = _png_end(f)
        if end is None:
            marker = "end of image marker (FFD9) after its scan data" if fmt == "JPEG" else "IEND chunk"
            raise ValueError(f"{path}: truncated or damaged {fmt} file (the file ends before its {marker}); "
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
