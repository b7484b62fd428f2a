"""Stage timing of a training step, for `trisplat bench step`: named wall-clock sums, switched off by default.

Code marks its stages with `with stage("render_forward"):`; while `recording()` is active the seconds are summed per
name (stages may nest: an inner stage's time is also inside its outer one's), otherwise a stage costs one attribute
read. Not thread-safe across Python threads (the step runs in one; the kernels' own threads are inside a stage).
"""
from __future__ import annotations

import time
from contextlib import contextmanager

_TIMES: dict[str, float] | None = None
_CLOCK = time.perf_counter


class stage:
    """Context manager adding the wall time of its block to `name` while recording."""

    __slots__ = ("name", "t0")

    def __init__(self, name: str):
        self.name = name

    def __enter__(self):
        if _TIMES is not None:
            self.t0 = _CLOCK()
        return self

    def __exit__(self, *exc):
        if _TIMES is not None:
            _TIMES[self.name] = _TIMES.get(self.name, 0.0) + _CLOCK() - self.t0
        return False


@contextmanager
def recording(clock=time.perf_counter):
    """Record the stages inside the block; yields the dict of seconds per stage name (filled as it goes). clock:
    wall time by default; time.thread_time gives the CPU time of the calling thread, which at one thread (numba's
    and torch's work run in it) is the stage's work, less stretched by other jobs on a shared machine."""
    global _TIMES, _CLOCK
    outer, outer_clock, _TIMES, _CLOCK = _TIMES, _CLOCK, {}, clock
    try:
        yield _TIMES
    finally:
        _TIMES, _CLOCK = outer, outer_clock
