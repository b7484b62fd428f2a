"""Regenerate the pictures of the README and docs/guide.md from finished run folders (trisplat.eval.pictures).

    python scripts/make_doc_pictures.py demo=trisplat_demo/run bonsai=runs/bonsai:6 room=runs/room --out docs/pictures

Each NAME=RUN[:VIEW] writes docs/pictures/NAME_file.jpg (the run's mesh file as a viewer shows it) and NAME_shaded.jpg
(the bare geometry) from test view VIEW (default 0) of a `trisplat train` run, or from tracked frame VIEW (default: the
middle one) of a `trisplat slam` run; NAME_photo.jpg too when the capture is one of the project's synthetic scenes.
The pictures committed under docs/pictures/ and the runs they came from are listed in docs/pictures/pictures.json.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def parse_source(text: str) -> tuple[str, Path, int | None]:
    """NAME=RUN[:VIEW] -> (name, run folder, view or None)."""
    name, sep, rest = text.partition("=")
    if not sep or not name or not rest:
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=RUN or NAME=RUN:VIEW")
    run, _, view = rest.rpartition(":") if rest.rpartition(":")[2].isdigit() else (rest, "", "")
    return name, Path(run), int(view) if view else None


def main(argv: list[str] | None = None) -> int:
    from trisplat.eval.pictures import WIDTH, run_pictures, slam_pictures, write_index

    ap = argparse.ArgumentParser(prog="python scripts/make_doc_pictures.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("sources", nargs="+", type=parse_source, metavar="NAME=RUN[:VIEW]")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "pictures")
    ap.add_argument("--width", type=int, default=WIDTH, help="pixels across each picture")
    args = ap.parse_args(argv)
    written = []
    for name, run, view in args.sources:
        slam = (run / "trajectory.txt").is_file()
        pics = (slam_pictures(run, name, args.out, view, args.width) if slam
                else run_pictures(run, name, args.out, 0 if view is None else view, args.width))
        for p in pics:
            print(f"{args.out / p.file}: {p.width}x{p.height}, {p.bytes / 1024:.0f} KB ({p.view} of {run})")
        written += pics
    write_index(args.out, written)
    total = sum(p.stat().st_size for p in args.out.glob("*.jpg"))
    print(f"{args.out}: {total / 1024:.0f} KB of pictures in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
