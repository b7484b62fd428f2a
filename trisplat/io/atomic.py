"""Atomic file writes: a temporary file beside the target, flushed to disk, then renamed over it.

A reader (or a run killed mid-write) sees either the old file or the complete new one, never half a file.
"""
from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def _temporary_name(path: Path) -> Path:
    """A hidden sibling of `path`, unique per process and thread, keeping the suffix (writers that pick a format
    by suffix still see the right one)."""
    return path.with_name(f".{path.stem}.{os.getpid()}.{threading.get_ident()}.partial{path.suffix}")


@contextmanager
def atomic_target(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write to; on success it is fsynced and renamed to `path`, on an exception it is
    removed and `path` is left as it was."""
    path = Path(path)
    tmp = _temporary_name(path)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` atomically; returns `path`."""
    path = Path(path)
    with atomic_target(path) as tmp:
        tmp.write_bytes(data)
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write `text` (UTF-8) to `path` atomically; returns `path`."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def refuse_to_overwrite(paths, force: bool, hint: str = "") -> None:
    """The one overwrite rule of every command: raise FileExistsError naming the files of `paths` that exist,
    unless `force`. Call it before any work, so a refusal costs nothing and changes nothing."""
    existing = [Path(p) for p in paths if Path(p).exists()]
    if existing and not force:
        names = ", ".join(str(p) for p in existing[:5]) + (f" (and {len(existing) - 5} more)" if len(existing) > 5
                                                          else "")
        raise FileExistsError(f"would overwrite {names}; pass --force to replace {'it' if len(existing) == 1 else 'them'}"
                              + (f", or {hint}" if hint else ""))
