"""`trisplat bench`: dispatch to the suites, a clear message for a missing one, `all` and its markdown index."""
from __future__ import annotations

import json
import sys
import types

import pytest

from trisplat.bench.common import BenchTable
from trisplat.cli import main as cli_main
from trisplat.commands import bench


def _fake_suite(name: str, calls: list):
    """A suite module whose main(argv) records its argv and writes a one-row table into --out."""

    def main(argv):
        calls.append((name, list(argv)))
        out = argv[argv.index("--out") + 1] if "--out" in argv else "bench_results"
        t = BenchTable(f"{name}_bench", ["case", "ms"])
        t.add(name, 1.5)
        t.write(out, f"trisplat bench {name}")
        return 0

    mod = types.ModuleType(f"trisplat.bench.{name}")
    mod.main = main
    return mod


@pytest.fixture
def fake_suites(monkeypatch):
    calls: list = []
    for name in bench.SUITES:
        monkeypatch.setitem(sys.modules, f"trisplat.bench.{name}", _fake_suite(name, calls))
    return calls


def test_dispatch_passes_arguments(fake_suites, tmp_path):
    assert cli_main(["bench", "render", "--out", str(tmp_path), "--quick"]) == 0
    assert fake_suites == [("render", ["--out", str(tmp_path), "--quick"])]
    payload = json.loads((tmp_path / "render_bench.json").read_text())
    assert payload["rows"] == [["render", 1.5]] and payload["machine"]["cores"] >= 1


def test_all_runs_every_suite_and_writes_an_index(fake_suites, tmp_path):
    assert bench.main(["all", "--out", str(tmp_path)]) == 0
    assert [c[0] for c in fake_suites] == list(bench.SUITES)
    index = (tmp_path / bench.INDEX_MD).read_text()
    for name in bench.SUITES:
        assert f"### {name}_bench" in index and f"| {name} | 1.5 |" in index


def test_missing_suite_says_so(monkeypatch, capsys):
    monkeypatch.setitem(bench.SUITES, "render", ("trisplat.bench.no_such_suite", "x"))
    assert bench.main(["render"]) == 1
    assert "the render benchmark (trisplat.bench.no_such_suite) is not available" in capsys.readouterr().err


def test_broken_suite_is_not_reported_as_missing(monkeypatch, tmp_path):
    # a suite that exists but fails to import one of *its* dependencies must surface that error, not hide it
    pkg = tmp_path / "brokenbench_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "suite.py").write_text("import some_module_that_does_not_exist_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(bench.SUITES, "mesh", ("brokenbench_pkg.suite", "x"))
    with pytest.raises(ModuleNotFoundError, match="some_module_that_does_not_exist_xyz"):
        bench.main(["mesh"])


def test_usage_and_unknown_suite(capsys):
    assert bench.main([]) == 0
    usage = capsys.readouterr().out
    assert all(name in usage for name in ("render", "train", "mesh", "all"))
    assert bench.main(["fast"]) == 2
    assert "unknown suite 'fast'" in capsys.readouterr().err


def test_machine_info_records_commit_and_dirtiness(tmp_path, monkeypatch):
    import subprocess
    from pathlib import Path

    from trisplat.bench import common

    info = common.machine_info()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          cwd=Path(bench.__file__).parent)
    if head.returncode != 0:
        pytest.skip("not inside a git checkout")
    assert info["commit"] == head.stdout.strip()
    assert isinstance(info["commit_dirty"], bool)  # the shared checkout changes under us: no equality test here
    assert info["cores"] >= 1 and info["cpu"] and info["torch"].startswith("2.")
    for dirty in (True, False):
        monkeypatch.setattr(common, "machine_info", lambda d=dirty: {**info, "commit_dirty": d})
        t = BenchTable("x", ["a"])
        t.add(1)
        md = t.write(tmp_path, "cmd").read_text()
        assert f"commit {info['commit']}" in md
        assert ("uncommitted changes" in md) is dirty
        assert json.loads((tmp_path / "x.json").read_text())["machine"]["commit_dirty"] is dirty


def test_table_records_the_commit_the_benchmark_started_on(tmp_path, monkeypatch):
    """A 30-minute bench outlives commits made meanwhile: the table names the code that ran, and the move."""
    from trisplat.bench import common

    info = common.machine_info()
    monkeypatch.setattr(common, "machine_info", lambda: {**info, "commit": "aaaaaaa", "commit_dirty": False})
    t = BenchTable("x", ["a"])
    t.add(1)
    monkeypatch.setattr(common, "machine_info", lambda: {**info, "commit": "bbbbbbb", "commit_dirty": False})
    md = t.write(tmp_path, "cmd").read_text()
    assert "commit aaaaaaa" in md and "HEAD moved to bbbbbbb during the run" in md
    saved = json.loads((tmp_path / "x.json").read_text())["machine"]
    assert saved["commit"] == "aaaaaaa" and saved["commit_at_end"] == "bbbbbbb"


def test_train_table_reads_psnr_against_time_from_a_real_history(tmp_path):
    """The curve column of `bench train`: the last test PSNR at or before 25/50/75% of the run's time, from a
    history.jsonl as the trainer writes it (its first line records the initialisation and has no time)."""
    from trisplat.bench.train import _psnr_at_fractions

    history = [{"init": "hull: 4000 faces"}, {"step": 10, "wall_s": 10.0, "loss": 0.2},
               {"step": 20, "wall_s": 20.0, "test_psnr": 21.0}, {"step": 50, "wall_s": 50.0, "test_psnr": 24.5},
               {"step": 100, "wall_s": 100.0, "loss": 0.1}]
    assert _psnr_at_fractions(history) == ["21.00@0.3m", "24.50@0.8m", "24.50@0.8m"]
    assert _psnr_at_fractions(history[:2]) == ["-", "-", "-"]
