"""Progress bars that suit where the output goes: tqdm's redrawn bar on a terminal, plain lines in a log.

Redirected to a file (a log, `nohup`, CI), a tqdm bar writes a carriage return and a new bar several times a second:
a 15-minute training left 1.6 MB of them in its log. `progress_bar` gives tqdm's bar when the stream is a terminal
and otherwise a `LogLines` bar: one complete line each time another LOG_STEP_PERCENT of the total is done (and at
least one every LOG_HEARTBEAT_S while it runs, so a slow phase still shows it is alive), the last one at the end.
"""
from __future__ import annotations

import math
import sys
import time

from tqdm import tqdm

LOG_STEP_PERCENT = 5.0  # a line per this much progress when the output is not a terminal
LOG_HEARTBEAT_S = 60.0  # ... and at least one line this often while something runs (also when the total is unknown)


def is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class LogLines(tqdm):
    """A tqdm whose display is a plain line ending in a newline, written only when the progress crossed the next
    `step_percent` (or `heartbeat_s` passed since the last line), and once at the end; never a carriage return.
    Everything else (update, set_postfix, write, the formatting of the line) is tqdm's."""

    def __init__(self, *args, step_percent: float = LOG_STEP_PERCENT, heartbeat_s: float = LOG_HEARTBEAT_S, **kwargs):
        self._step = float(step_percent) / 100.0
        self._heartbeat = float(heartbeat_s)
        self._next_fraction = 0.0  # the first display (at creation) writes a line
        self._last_line_t = -math.inf
        self._last_line_n = None
        kwargs["dynamic_ncols"] = False  # no terminal to measure
        super().__init__(*args, **kwargs)

    def _write_line(self) -> None:
        line = self.__str__().strip()
        if line:
            self.fp.write(line + "\n")
            self.fp.flush()
        self._last_line_n = self.n
        self._last_line_t = time.monotonic()
        fraction = self.n / self.total if self.total else 0.0
        self._next_fraction = (math.floor(fraction / self._step + 1e-9) + 1) * self._step if self._step > 0 else 0.0

    def display(self, msg=None, pos=None):
        if msg is not None:  # tqdm clearing or overwriting its line: a log has nothing to clear
            return False
        fraction = self.n / self.total if self.total else None
        due = (time.monotonic() - self._last_line_t >= self._heartbeat
               or (fraction is not None and fraction >= self._next_fraction - 1e-9))
        if due:
            self._write_line()
        return True

    def clear(self, nolock=False):  # tqdm.write clears bars before printing: a log line stays
        pass

    def moveto(self, n):  # nested bars' cursor moves: a log has no cursor
        pass

    def close(self):
        if not self.disable and self.n and self.n != self._last_line_n:  # the final state, also for leave=False
            self._write_line()
        self.leave = False  # tqdm's close would redraw and add a newline
        super().close()


def progress_bar(iterable=None, *, file=None, **kwargs) -> tqdm:
    """tqdm(iterable, **kwargs) on a terminal; a LogLines bar (plain lines every few percent) when `file` (default:
    sys.stderr, tqdm's own default) is not one."""
    stream = sys.stderr if file is None else file
    cls = tqdm if is_terminal(stream) else LogLines
    return cls(iterable, file=stream, **kwargs)
