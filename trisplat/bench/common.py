"""Shared benchmark plumbing: machine facts, timing medians, peak memory, JSON + markdown output."""
from __future__ import annotations

import json
import os
import platform
import resource
import statistics
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable


def machine_info() -> dict:
    """Cores, CPU model, thread counts, versions and the git commit, recorded with every result."""
    import numba
    import numpy
    import torch

    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    code = code_version()
    return {**_more_machine_info(code), **{
        "cpu": cpu,
        "cores": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "numba_threading_layer": threading_layer(),
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numba": numba.__version__,
        "numpy": numpy.__version__,
        "commit": code["commit"] or "unknown",
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }}


def threading_layer() -> str:
    """The threading layer numba's parallel kernels run on (tbb, omp or workqueue), or what it is configured to
    choose before the first parallel kernel has run."""
    import numba

    try:
        return numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet
        return f"not chosen yet (configured: {numba.config.THREADING_LAYER})"


def code_version() -> dict:
    """{"trisplat": version (or None when not installed), "commit": the git commit of the source tree (or None
    outside a checkout), "dirty": whether tracked files differ from it (or None)}. Runs record it in metrics.json."""
    from importlib import metadata

    here = Path(__file__).resolve().parent
    try:
        version = metadata.version("trisplat")
    except metadata.PackageNotFoundError:
        version = None
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=here,
                                timeout=10).stdout.strip() or None
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                                text=True, cwd=here, timeout=10)
        dirty = bool(status.stdout.strip()) if commit and status.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        commit, dirty = None, None
    return {"trisplat": version, "commit": commit, "dirty": dirty}


def _more_machine_info(code: dict) -> dict:
    """OS, total memory (GiB), trisplat's version and whether tracked files differ from the commit (`code`:
    code_version())."""
    mem_gib = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                mem_gib = round(int(line.split()[1]) / 2**20, 1)
                break
    except (OSError, ValueError):
        pass
    return {"os": platform.platform(), "memory_gib": mem_gib, "trisplat": code["trisplat"] or "unknown",
            "commit_dirty": code["dirty"]}


def median_ms(fn: Callable[[], object], repeats: int = 5, warmup: int = 1) -> float:
    """Median wall time of fn() in milliseconds after `warmup` untimed calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@dataclass
class BenchTable:
    """Rows of one benchmark; written as JSON (with machine facts) and as a markdown table."""

    name: str
    columns: list[str]
    rows: list[list] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    started: dict = field(default_factory=lambda: machine_info())
    """machine facts when the benchmark began: its commit is the code that ran (HEAD may move during a long run)"""

    def add(self, *values) -> None:
        if len(values) != len(self.columns):
            raise ValueError(f"row has {len(values)} values for {len(self.columns)} columns")
        self.rows.append(list(values))

    def markdown(self) -> str:
        def fmt(v):
            if isinstance(v, float):
                return f"{v:.3g}" if abs(v) < 1e5 else f"{v:.3e}"
            return "-" if v is None else str(v)

        out = ["| " + " | ".join(self.columns) + " |", "|" + "---|" * len(self.columns)]
        out += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in self.rows]
        out += [f"\n{n}" for n in self.notes]
        return "\n".join(out)

    def write(self, out_dir: Path, command: str) -> Path:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        info = machine_info()
        if (self.started.get("commit"), self.started.get("commit_dirty")) != (info["commit"], info.get("commit_dirty")):
            info["commit_at_end"], info["commit_dirty_at_end"] = info["commit"], info.get("commit_dirty")
        info["commit"], info["commit_dirty"] = self.started.get("commit", "unknown"), self.started.get("commit_dirty")
        info["started"] = self.started.get("date")
        payload = {"name": self.name, "command": command, "machine": info, "columns": self.columns,
                   "rows": self.rows, "notes": self.notes}
        (out_dir / f"{self.name}.json").write_text(json.dumps(payload, indent=2))
        header = (f"### {self.name}\n\n`{command}` on {info['cpu']} ({info['cores']} cores, numba threads "
                  f"{info['numba_threads']}, torch threads {info['torch_threads']}), commit {info['commit']}"
                  f"{' (with uncommitted changes)' if info.get('commit_dirty') else ''}, "
                  f"{info['started']} to {info['date']}"
                  f"{'; HEAD moved to ' + info['commit_at_end'] + ' during the run' if 'commit_at_end' in info else ''}\n\n")
        md = out_dir / f"{self.name}.md"
        md.write_text(header + self.markdown() + "\n")
        return md
