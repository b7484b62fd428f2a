"""Regenerate docs/results.md and the README's results table from the JSON files in docs/results/ (trisplat.bench.results).

    python scripts/make_results.py            # write docs/results.md and the table between the README's markers
    python scripts/make_results.py --check    # exit 1, naming them, when they are out of date (a test runs this)
    python scripts/make_results.py record RUN --scene bonsai --input "168 photos, no poses" \\
        --command "trisplat train ../shared/data/bonsai/images --out RUN --minutes 30" [--commit abc1234]

`record` adds a finished `trisplat train` run (its metrics.json) as docs/results/run_SCENE.json; a bench writes its own
JSON there with `trisplat bench SUITE ... --out docs/results`. Then run this script again.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "docs" / "results"
PAGE = REPO / "docs" / "results.md"
README = REPO / "README.md"


def main(argv: list[str] | None = None) -> int:
    from trisplat.bench.results import build, record_run

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["record"]:
        ap = argparse.ArgumentParser(prog="python scripts/make_results.py record",
                                     description="a finished run's metrics.json -> docs/results/run_SCENE.json")
        ap.add_argument("run", type=Path)
        ap.add_argument("--scene", required=True, help="the scene's name in the tables (one file per scene)")
        ap.add_argument("--input", required=True, help="what the run was given, e.g. '168 photos, no poses'")
        ap.add_argument("--command", required=True, help="the command that made the run")
        ap.add_argument("--commit", help="the commit the run was trained with (a run folder does not record it)")
        ap.add_argument("--note", help="a sentence for the results page (e.g. what else ran on the machine)")
        ap.add_argument("--preset", help="the run's preset (default: the command's --preset, else 'default')")
        ap.add_argument("--out", type=Path, default=RESULTS)
        a = ap.parse_args(argv[1:])
        print(record_run(a.run, a.scene, a.input, a.command, a.out, commit=a.commit, note=a.note, preset=a.preset))
        return 0
    ap = argparse.ArgumentParser(prog="python scripts/make_results.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 when a file is out of date")
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--page", type=Path, default=PAGE)
    ap.add_argument("--readme", type=Path, default=README)
    a = ap.parse_args(argv)
    changed = build(a.results, a.page, a.readme, check=a.check)
    for p in changed:
        print(f"{p}: {'out of date (run python scripts/make_results.py)' if a.check else 'written'}")
    return 1 if a.check and changed else 0


if __name__ == "__main__":
    sys.exit(main())
