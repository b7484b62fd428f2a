"""Keep freed memory in the process: large arrays allocated and freed every training step cost page faults.

glibc returns every block larger than its mmap threshold (128 KiB, rising to at most 32 MiB) to the system when it is
freed, so the next step's arrays of the same size (a render's per-face tables, the gradients, torch's temporaries:
tens of MiB each) come back as fresh pages, zeroed by the kernel one fault at a time, and faults from several threads
queue on the process's memory map. On the 2-core machine a training step of bonsai's 414k-face surface spent about a
tenth of its time there, and the normal-smoothness term ran slower on two threads than on one (76.8 ms against 20.9;
12.7 ms on two once freed memory is kept; docs/benchmarks.md, issue 50). `keep_freed_memory()` raises glibc's mmap
threshold to 1 GiB and its trim threshold to 2 GiB (mallopt), so freed blocks stay in the heap and are reused: the
process's resident size stays near its peak instead of shrinking between steps. Nothing changes where the C
library is not glibc. TRISPLAT_KEEP_FREED_MEMORY=0 turns it off.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 1 << 30
TRIM_THRESHOLD = (1 << 31) - 1

_done: bool | None = None


def keep_freed_memory() -> bool:
    """Make glibc keep freed memory for reuse (see the module docstring); True when it took effect. Idempotent."""
    global _done
    if _done is not None:
        return _done
    _done = False
    if os.environ.get("TRISPLAT_KEEP_FREED_MEMORY", "1") == "0":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (macOS, musl, Windows)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    _done = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _done
