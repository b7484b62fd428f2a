"""docs/results.md and the README's results table are generated from bench JSON files (trisplat.bench.results): the
committed page and table match the committed JSON, every number comes from a file, the newest row of a scene wins in
the README, and a finished run is recorded in the same layout."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from trisplat.bench import results as R

REPO = Path(__file__).resolve().parents[1]


def test_committed_page_and_readme_match_the_committed_results():
    """`python scripts/make_results.py --check`: nothing typed by hand, nothing left out after a new JSON."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "make_results.py"), "--check"], cwd=REPO, env=env,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    readme = (REPO / "README.md").read_text()
    assert readme.index(R.README_START) < readme.index(R.README_END)
    for row in R.scene_rows(R.load_results(REPO / "docs" / "results")):  # the README shows every scene's newest row
        assert f"| {row.scene} | {row.input} |" in readme


MACHINE = {"cpu": "AMD EPYC 7B13 Processor", "cores": 2, "numba_threads": 2, "torch_threads": 2, "memory_gib": 23.5,
           "python": "3.11.7", "torch": "2.13.0+cpu", "numba": "0.68.1", "commit": "abc1234", "commit_dirty": False}


def _write(folder: Path, name: str, command: str, columns, rows, date: str, notes=()) -> Path:
    p = folder / f"{name}.json"
    p.write_text(json.dumps({"name": name, "command": command, "machine": {**MACHINE, "date": date},
                             "columns": columns, "rows": rows, "notes": list(notes)}))
    return p


@pytest.fixture
def folder(tmp_path):
    res = tmp_path / "results"
    res.mkdir()
    train_cols = ["scene", "preset", "budget min", "wall min", "steps", "faces", "PSNR hard", "file PSNR", "SSIM",
                  "pieces"]
    _write(res, "train", "trisplat bench train --scenes lego fox", train_cols,
           [["lego", "default", 30.0, 30.2, 9000, 274803, 27.44, 25.99, 0.941, 1],
            ["fox", "default", 30.0, 30.1, 8000, 120000, 23.33, 23.61, 0.70, 3]], "2026-11-20 10:00",
           notes=["a note | with a bar"])
    _write(res, "run_lego", "trisplat train lego --out runs/lego --minutes 10", R.RUN_COLUMNS,
           [["lego", "100 views", "default", 10.0, 10.0, 3000, 100000, 50000, 26.1, 25.2, 0.9, None, 1, 100.0, None,
             100.0, "ok"]], "2026-11-25 08:00")
    from trisplat.bench.slam import COLUMNS

    slam_rows = [[None] * len(COLUMNS), [None] * len(COLUMNS)]
    for row, method, psnr in ((slam_rows[0], "trisplat", 21.5), (slam_rows[1], "open3d", 19.0)):
        row[COLUMNS.index("method")], row[COLUMNS.index("held-out PSNR")] = method, psnr
        row[COLUMNS.index("frames")], row[COLUMNS.index("wall s")] = 400, 240.0
        row[COLUMNS.index("held-out PSNR of mesh.ply")], row[COLUMNS.index("mesh faces")] = 20.25, 512000
    _write(res, "slam", "trisplat bench slam --capture ../shared/data/icl_rgbd --out x", COLUMNS, slam_rows,
           "2026-11-26 09:00")
    return res


def test_page_and_readme_table_come_from_the_files(folder, tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"# x\n\nbefore\n{R.README_START}\nold table\n{R.README_END}\nafter\n")
    page = tmp_path / "docs" / "results.md"
    page.parent.mkdir()
    assert R.build(folder, page, readme) == [page, readme]
    text, md = readme.read_text(), page.read_text()
    assert text.startswith("# x\n\nbefore\n") and text.endswith(f"{R.README_END}\nafter\n") and "old table" not in text
    table = text[text.index(R.README_START):text.index(R.README_END)]
    # the newest lego row (a run record, 25 Nov) wins over the bench's (20 Nov); fox from the bench; slam's trisplat row
    assert "| lego | 100 views | 10.0 | 26.10 / 25.20 | 100,000 | 1 | AMD EPYC 7B13, 2 cores |" in table
    assert "| fox | instant-ngp fox: 50 photos with COLMAP poses, 1080x1920 | 30.1 | 23.33 / 23.61 | 120,000 | 3 |" in table
    assert "| icl_rgbd | RGB-D frames without poses, 400 frames | 4.0 | 21.50 / 20.25 | 512,000 | - |" in table
    assert "27.44" not in table and "19.00" not in table and "docs/results.md#run_lego" in table
    # the page: every scene row, then each file's own section with its command, machine and notes
    assert md.count("| lego |") == 4 and "| 27.44 / 25.99 |" in md  # scene table (2 rows), run_lego's, train's
    for name, command in (("train", "trisplat bench train --scenes lego fox"), ("slam", "trisplat bench slam")):
        assert f"\n## {name}\n" in md and f"`{command}" in md
    assert "AMD EPYC 7B13, 2 cores (23.5 GiB, numba threads 2, torch threads 2), commit abc1234" in md
    assert "\na note | with a bar\n" in md
    assert "without a result here yet: spot, bonsai, room" in md  # lego and fox have results
    assert R.build(folder, page, readme, check=True) == []  # regenerating changes nothing
    data = json.loads((folder / "train.json").read_text())
    data["rows"][1][6] = 23.5
    (folder / "train.json").write_text(json.dumps(data))
    assert R.build(folder, page, readme, check=True) == [page, readme] and "23.33" in readme.read_text()
    R.build(folder, page, readme)
    assert "| 23.50 / 23.61 |" in readme.read_text()


def test_a_file_that_is_no_bench_result_is_named(tmp_path):
    (tmp_path / "other.json").write_text('{"psnr": 1}')
    with pytest.raises(ValueError, match="other.json: not a bench result"):
        R.load_results(tmp_path)
    with pytest.raises(ValueError, match="markers"):
        R.replace_block("no markers here", "table")


def test_record_run_writes_a_runs_scores_as_a_bench_table(tmp_path):
    run = tmp_path / "bonsai_c1"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"minutes": 30.0, "data": "x"}))
    (run / "metrics.json").write_text(json.dumps({
        "psnr": 24.44, "file_psnr": 22.55, "ssim": 0.735, "lpips": None, "faces": 414337, "vertices": 208644,
        "wall_s": 1800.0, "steps": 17044, "mesh": {"connected_components": 2, "largest_component_fraction": 0.98},
        "surface_pixels": 0.9989, "coverage": 1.0, "test_views": 21, "supersample": 2,
        "health": {"ok": False, "problems": ["holes"]}}))
    path = R.record_run(run, "bonsai", "168 photos", "trisplat train bonsai --out r --minutes 30 --preset fast",
                        tmp_path / "out", commit="a0203fb", note="the default layout")
    d = json.loads(path.read_text())
    assert path.name == "run_bonsai.json" and d["name"] == "run_bonsai" and d["columns"] == R.RUN_COLUMNS
    row = dict(zip(d["columns"], d["rows"][0]))
    assert row == {"scene": "bonsai", "input": "168 photos", "preset": "fast", "budget min": 30.0, "wall min": 30.0,
                   "steps": 17044, "faces": 414337, "vertices": 208644, "PSNR hard": 24.44, "file PSNR": 22.55,
                   "SSIM": 0.735, "LPIPS": None, "pieces": 2, "largest %": 98.0, "surface pixels %": 99.89,
                   "coverage %": 100.0, "health": "holes"}
    assert d["machine"]["commit"] == "a0203fb" and "numba_threads" not in d["machine"]  # not the run's threads
    assert "21 test views at 2x2" in d["notes"][0] and d["notes"][1] == "the default layout"
    (s,) = R.scene_rows(R.load_results(path.parent))
    assert (s.scene, s.minutes, s.psnr, s.file_psnr, s.faces, s.pieces) == ("bonsai", 30.0, 24.44, 22.55, 414337, 2)


def test_machine_label():
    assert R.machine_label({"cpu": "Intel(R) Xeon(R) CPU @ 2.80GHz", "cores": 2}) == "Intel Xeon, 2 cores"
    assert R.machine_label({"cpu": "AMD EPYC 7B13 64-Core Processor", "cores": 16, "gpu": "NVIDIA H100"}) == \
        "NVIDIA H100 + AMD EPYC 7B13, 16 cores"
