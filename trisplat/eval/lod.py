"""Level of detail, scored as files: export the run's surface decimated to several face counts (each with a texture
re-fitted to the photos), score every GLB as a glTF viewer shows it, and show PSNR against face count."""
from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from trisplat.io.atomic import atomic_write_text

LOD_METRICS = "lod.json"
LOD_PLOT = "psnr_vs_faces.png"


@dataclass
class LodPoint:
    """One exported level: the face count asked for and got, its texture side, file size and scores."""

    faces_requested: int | None  # None: the run's own mesh.glb (every face)
    faces: int
    texture_size: int
    glb_bytes: int
    psnr: float
    ssim: float
    lpips: float | None
    seconds: float  # export (decimation + texture fit) and scoring
    file: str
    views: int = 0  # test views scored (all of the split unless max_views)


def evaluate_lod(run_dir: str | Path, faces: Sequence[int], texture_size: int | None = None, split: str = "test",
                 out_dir: str | Path | None = None, supersample: int | None = None, max_views: int | None = None,
                 include_full: bool = True, show_progress: bool = True) -> list[LodPoint]:
    """Export RUN's surface at each face count in `faces` (GLB, texture of side `texture_size`, default the run's
    own `texture_size`) into out_dir/faces_<N>/mesh.glb, score each as a glTF viewer shows it (eval.file_scores)
    and write out_dir/lod.json and out_dir/psnr_vs_faces.png (default out_dir: RUN/eval_<split>_lod). With
    include_full, the run's own mesh.glb (all faces) is the first point. The model's report (RUN/eval_<split>/
    report.html), when present, gets a 'Level of detail' section. Returns the points, most faces first."""
    from trisplat.eval.file_scores import evaluate_file
    from trisplat.io.export_run import export_run
    from trisplat.run import open_run

    run = open_run(run_dir)
    counts = sorted({int(n) for n in faces}, reverse=True)
    if not counts and not include_full:
        raise ValueError("level of detail: give at least one face count")
    bad = [n for n in counts if n < 1]
    if bad:
        raise ValueError(f"level of detail: face counts must be at least 1, got {bad}")
    size = int(run.config.get("texture_size", 0) if texture_size is None else texture_size)
    if size < 0:
        raise ValueError(f"level of detail: texture size must be >= 0, got {size}")
    out = Path(out_dir) if out_dir is not None else run.path / f"eval_{split}_lod"
    out.mkdir(parents=True, exist_ok=True)
    data = run.load_scene_data()
    points: list[LodPoint] = []
    levels: list[tuple[int | None, Path]] = []
    if include_full and (run.path / "mesh.glb").is_file():
        levels.append((None, run.path / "mesh.glb"))
    levels += [(n, out / f"faces_{n}" / "mesh.glb") for n in counts]
    for n, glb in levels:
        t0 = time.perf_counter()
        if n is not None:
            if show_progress:
                print(f"level of detail: {n} faces, texture {size}", flush=True)
            export_run(run.path, formats=("glb",), out_dir=glb.parent, faces=n, texture_size=size)
        m = evaluate_file(run.path, glb, split, out_dir=glb.parent / "eval", supersample=supersample,
                          max_views=max_views, report=False, show_progress=show_progress, data=data)
        tex = size if n is not None else (int(run.config.get("texture_size", 0)) if m.extra.get("textured") else 0)
        points.append(LodPoint(faces_requested=n, faces=int(m.extra["faces"]), texture_size=int(tex),
                               glb_bytes=glb.stat().st_size, psnr=float(m.psnr), ssim=float(m.ssim),
                               lpips=None if m.lpips is None else float(m.lpips),
                               seconds=round(time.perf_counter() - t0, 2), file=str(glb), views=len(m.views)))
    atomic_write_text(out / LOD_METRICS, json.dumps({"split": split, "levels": [asdict(p) for p in points]}, indent=2))
    plot = plot_lod(points, out / LOD_PLOT)
    page = run.path / f"eval_{split}" / "report.html"
    if page.is_file():
        add_lod_section(page, points, plot)
    return points


def plot_lod(points: Sequence[LodPoint], path: Path) -> Path | None:
    """PSNR against face count (log scale) as a PNG; None when there is nothing to plot."""
    if not points:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = sorted(points, key=lambda p: p.faces)
    fig, ax = plt.subplots(figsize=(6, 3.6), constrained_layout=True)
    ax.plot([p.faces for p in pts], [p.psnr for p in pts], "o-", color="C0")
    for p in pts:
        ax.annotate(f"{p.faces / 1000:.0f}k" if p.faces >= 1000 else str(p.faces), (p.faces, p.psnr),
                    textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("faces of the exported GLB")
    ax.set_ylabel("PSNR of the file (dB)")
    ax.grid(alpha=0.3, which="both")
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def add_lod_section(page: str | Path, points: Sequence[LodPoint], plot: Path | None) -> Path:
    """Insert (or replace) a 'Level of detail' section in an existing report.html: one row per exported level
    (faces, texture, file size, scores) and the PSNR-against-faces plot."""
    import html
    import os

    from trisplat.eval.report import _fmt, insert_section

    page = Path(page)
    views = sorted({p.views for p in points})
    rows = [f"<div id='lod'><h2>Level of detail (files, glTF spec render, {'/'.join(map(str, views))} views)</h2>"
            "<table id='lod-scores'><tr>"
            "<th>faces</th><th>texture</th><th>GLB (MB)</th><th>PSNR (dB)</th><th>SSIM</th><th>LPIPS</th></tr>"]
    for p in points:
        what = "all (mesh.glb)" if p.faces_requested is None else f"{p.faces} (asked {p.faces_requested})"
        rows.append(f"<tr><td class='name'>{html.escape(what)}</td><td>{p.texture_size or 'vertex colours'}</td>"
                    f"<td>{p.glb_bytes / 1e6:.1f}</td><td>{_fmt(p.psnr, 2)}</td><td>{_fmt(p.ssim, 4)}</td>"
                    f"<td>{_fmt(p.lpips, 4)}</td></tr>")
    rows.append("</table>")
    if plot is not None:
        rel = os.path.relpath(plot, page.parent)
        rows.append(f"<img src='{html.escape(rel)}' alt='PSNR against face count'>")
    rows.append("</div>")
    section = "\n".join(rows)
    text = page.read_text()
    start = text.find("<div id='lod'>")
    if start >= 0:  # a second `eval --lod` replaces the first one's section
        end = text.find("</div>", start) + len("</div>")
        atomic_write_text(page, text[:start] + section + text[end:])
        return page
    return insert_section(page, section, text)
