"""The evaluation report: typed per-view/split metrics, metrics.json, and one self-contained HTML page per split.

`write_report` is a pure function of its inputs: it writes report.html plus the pictures it shows (ground truth,
render, error map per view; training curves) as files next to it, and nothing else.
"""
from __future__ import annotations

import html
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from trisplat.io.atomic import atomic_write_text

REPORT_HTML = "report.html"
METRICS_JSON = "metrics.json"
IMAGES_DIR = "images"
ERROR_MAP_MAX = 0.25  # mean absolute RGB error (fraction of full range) shown at the top of the error colour map
ERROR_MAP_CMAP = "inferno"


@dataclass
class ViewMetrics:
    """Scores of one rendered view against its ground truth. psnr in dB (+inf if identical); lpips None if unknown."""

    index: int
    name: str
    psnr: float
    ssim: float
    lpips: float | None = None
    psnr_exposure_matched: float | None = None  # runs with per-photo colour corrections (trisplat.train.exposure)


@dataclass
class SplitMetrics:
    """Scores of a split: per-view values and their means (LPIPS-AlexNet v0.1; None when the weights were missing)."""

    split: str
    mode: str
    views: list[ViewMetrics]
    lpips_note: str | None = None
    render_seconds: float | None = None  # total wall time spent rendering the split
    extra: dict = field(default_factory=dict)

    @property
    def psnr(self) -> float:
        """Mean of the per-view PSNRs (dB), as papers report it (not the PSNR of the mean MSE)."""
        return _mean([v.psnr for v in self.views])

    @property
    def ssim(self) -> float:
        return _mean([v.ssim for v in self.views])

    @property
    def lpips(self) -> float | None:
        vals = [v.lpips for v in self.views]
        return None if not vals or any(x is None for x in vals) else _mean(vals)

    def to_dict(self) -> dict:
        return {
            "split": self.split,
            "mode": self.mode,
            "num_views": len(self.views),
            "psnr": self.psnr,
            "ssim": self.ssim,
            "lpips": self.lpips,
            "lpips_net": "alex-v0.1",
            "lpips_note": self.lpips_note,
            "render_seconds": self.render_seconds,
            **self.extra,
            "views": [asdict(v) for v in self.views],
        }

    @staticmethod
    def from_dict(d: dict) -> SplitMetrics:
        views = [ViewMetrics(**{k: _from_json_float(v) for k, v in view.items()}) for view in d["views"]]
        known = {"split", "mode", "num_views", "psnr", "ssim", "lpips", "lpips_net", "lpips_note", "render_seconds",
                 "views"}  # fmt: skip
        return SplitMetrics(split=d["split"], mode=d["mode"], views=views, lpips_note=d.get("lpips_note"),
                            render_seconds=d.get("render_seconds"),
                            extra={k: v for k, v in d.items() if k not in known})  # fmt: skip


@dataclass
class ViewImages:
    """The pictures of one view shown in the report: ground truth and render, float [H,W,3] in [0,1]; optionally
    `shaded`, the bare surface from the same camera (grey, headlight-lit: see eval.views.render_shaded)."""

    name: str
    gt: np.ndarray
    render: np.ndarray
    shaded: np.ndarray | None = None


def _mean(vals: Sequence[float]) -> float:
    return float(np.mean(vals)) if len(vals) else math.nan


def _from_json_float(v):
    return float(v) if isinstance(v, str) and v in ("inf", "-inf", "nan") else v


def json_safe(x):
    """Replace non-finite floats (PSNR of identical images is +inf) by the strings "inf"/"-inf"/"nan" (valid JSON)."""
    if isinstance(x, float) and not math.isfinite(x):
        return "inf" if x > 0 else ("-inf" if x < 0 else "nan")
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    return x


def write_metrics(out_dir: str | Path, metrics: SplitMetrics) -> Path:
    """Write metrics.json (means and per view; non-finite values as strings) into out_dir; returns its path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = out / METRICS_JSON
    atomic_write_text(p, json.dumps(json_safe(metrics.to_dict()), indent=2))
    return p


def error_map(gt: np.ndarray, render: np.ndarray, vmax: float = ERROR_MAP_MAX) -> np.ndarray:
    """Colour-mapped mean absolute error [H,W,3] uint8: black = 0, bright yellow >= vmax (fraction of range)."""
    from matplotlib import colormaps

    err = np.abs(np.asarray(gt, np.float64) - np.asarray(render, np.float64)).mean(axis=-1)
    rgba = colormaps[ERROR_MAP_CMAP](np.clip(err / vmax, 0.0, 1.0))
    return (rgba[..., :3] * 255.0 + 0.5).astype(np.uint8)


def _to_uint8(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img, dtype=np.float64)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"report images must be [H,W,3], got shape {a.shape}")
    return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _save_png(arr: np.ndarray, path: Path) -> None:
    from PIL import Image

    Image.fromarray(arr).save(path)


def write_png(img, path: Path) -> None:
    """Save a float RGB image [H,W,3] in [0,1] (numpy or torch) as an 8-bit PNG (clipped, rounded)."""
    if hasattr(img, "detach"):
        img = img.detach().cpu().numpy()
    _save_png(_to_uint8(img), Path(path))


def _fmt(v, digits: int) -> str:
    if v is None:
        return "-"
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    return f"{v:.{digits}f}"


def _num_attr(v) -> str:
    """The exact value as an HTML attribute, so tests and scripts can read numbers back without rounding."""
    if v is None:
        return "null"
    return repr(float(v)) if math.isfinite(float(v)) else json_safe(float(v))


def plot_history(history: Sequence[dict], path: Path, final_psnr: float | None = None) -> Path | None:
    """Training curves (test PSNR and face count against step and wall time) as one PNG; None if nothing to plot.

    final_psnr: this evaluation's mean PSNR, drawn as a star at the last logged step / wall time.
    """
    rows = [h for h in history if "step" in h]
    test = [h for h in rows if h.get("test_psnr") is not None and math.isfinite(float(h["test_psnr"]))]
    train = [h for h in rows if h.get("psnr") is not None and math.isfinite(float(h["psnr"]))]
    faces = [h for h in rows if h.get("faces") is not None]
    if not (test or train or faces):
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(10, 6.5), constrained_layout=True)
    for col, (key, label) in enumerate((("step", "step"), ("wall_s", "wall time (s)"))):
        ax = axes[0, col]
        if train:
            ax.plot([h.get(key, math.nan) for h in train], [h["psnr"] for h in train], color="0.7", lw=1,
                    label="train view PSNR")  # fmt: skip
        if test:
            ax.plot([h.get(key, math.nan) for h in test], [h["test_psnr"] for h in test], "o-", color="C0", ms=3,
                    label="test PSNR")  # fmt: skip
        if final_psnr is not None and math.isfinite(final_psnr) and rows:
            ax.plot([rows[-1].get(key, math.nan)], [final_psnr], "*", color="C3", ms=12, label="this evaluation")
        ax.set_xlabel(label)
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)
        ax = axes[1, col]
        if faces:
            ax.plot([h.get(key, math.nan) for h in faces], [h["faces"] for h in faces], color="C1")
        _mark_events(axes[:, col], rows, key)
        ax.set_xlabel(label)
        ax.set_ylabel("faces")
        ax.grid(alpha=0.3)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _mark_events(axes, rows: Sequence[dict], key: str) -> None:
    """Vertical lines where the run switched to a connected surface (green), collapsed (red) and rolled back
    (orange, dashed), so a face count or PSNR that falls can be read against what the run did."""
    last = {}
    for h in rows:  # rows without the x key (the rollback's) take the position of the record before them
        if key in h:
            last[key] = h[key]
        x = h.get(key, last.get(key))
        if x is None:
            continue
        style = (dict(color="C2", ls="-", label="switch to a surface") if "switch" in h else
                 dict(color="C3", ls="-", label="collapse") if "collapse" in h else
                 dict(color="C1", ls="--", label="rolled back") if "recovery" in h else None)
        if style is None:
            continue
        for ax in axes:
            ax.axvline(x, lw=1, alpha=0.8, **style)


def _stats_dict(mesh_stats) -> dict | None:
    if mesh_stats is None:
        return None
    if hasattr(mesh_stats, "to_dict"):
        return dict(mesh_stats.to_dict())
    if isinstance(mesh_stats, dict):
        return dict(mesh_stats)
    raise ValueError(f"mesh_stats must be a dict or have to_dict(), got {type(mesh_stats).__name__}")


_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}
th{background:#f3f3f3}td.name{text-align:left}tr.mean td{font-weight:bold;background:#fafafa}
div.view{display:flex;flex-wrap:wrap;gap:6px;align-items:flex-start;margin:.6em 0 1.4em}div.view figure{margin:0}
div.view img{max-width:24vw;image-rendering:pixelated;border:1px solid #ddd}figcaption{font-size:.8em;color:#555}
pre{background:#f7f7f7;padding:.6em;overflow:auto;max-height:30em}.note{color:#a40}
"""


def write_report(
    out_dir: str | Path,
    metrics: SplitMetrics,
    images: Sequence[ViewImages] = (),
    history: Sequence[dict] = (),
    mesh_stats=None,
    config: dict | None = None,
    title: str = "trisplat evaluation",
) -> Path:
    """Write out_dir/report.html (+ out_dir/images/*.png) and return the page's path.

    metrics: the split's scores (the table lists every view; means first). images: the views to show as
    ground truth | render | error map (names must match views in `metrics`). history: records of the run's
    history.jsonl (step, wall_s, psnr, test_psnr, faces) for the curves. mesh_stats: a dict or an object with
    to_dict() (e.g. trisplat.mesh.stats.mesh_statistics(...)), or None. config: the run's config, shown verbatim.
    """
    out = Path(out_dir)
    img_dir = out / IMAGES_DIR
    img_dir.mkdir(parents=True, exist_ok=True)
    by_name = {v.name: v for v in metrics.views}
    e = html.escape
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{e(title)}</title>"
             f"<style>{_CSS}</style></head><body>", f"<h1>{e(title)}</h1>"]  # fmt: skip
    parts.append(f"<p>split <b>{e(metrics.split)}</b>, {e(metrics.mode)} rendering, {len(metrics.views)} views; "
                 "LPIPS is AlexNet v0.1 on inputs scaled to [-1,1]; SSIM uses an 11x11 Gaussian window "
                 "(sigma 1.5 px); PSNR is the mean of per-view PSNRs.</p>")  # fmt: skip
    if metrics.lpips_note:
        parts.append(f"<p class='note'>LPIPS not computed: {e(metrics.lpips_note)}</p>")

    # --- metrics table
    parts.append("<h2>Metrics</h2><table id='metrics'><tr><th>view</th><th>PSNR (dB)</th><th>SSIM</th>"
                 "<th>LPIPS</th></tr>")  # fmt: skip

    def row(cls: str, name: str, p, s, lp) -> str:
        return (f"<tr class='{cls}' data-name='{e(name)}'><td class='name'>{e(name)}</td>"
                f"<td class='psnr' data-value='{_num_attr(p)}'>{_fmt(p, 2)}</td>"
                f"<td class='ssim' data-value='{_num_attr(s)}'>{_fmt(s, 4)}</td>"
                f"<td class='lpips' data-value='{_num_attr(lp)}'>{_fmt(lp, 4)}</td></tr>")  # fmt: skip

    parts.append(row("mean", "mean", metrics.psnr, metrics.ssim, metrics.lpips))
    parts += [row("view", v.name, v.psnr, v.ssim, v.lpips) for v in metrics.views]
    parts.append("</table>")
    if metrics.extra:
        parts.append("<table id='run-summary'>")
        for k, v in metrics.extra.items():
            parts.append(f"<tr><th>{e(str(k))}</th><td>{e(_fmt(v, 4) if isinstance(v, float) else str(v))}</td></tr>")
        parts.append("</table>")
    if metrics.render_seconds is not None and metrics.views:
        parts.append(f"<p>rendering: {metrics.render_seconds:.2f} s for {len(metrics.views)} views "
                     f"({metrics.render_seconds / len(metrics.views) * 1e3:.0f} ms per view)</p>")  # fmt: skip

    # --- training curves
    curves = plot_history(history, img_dir / "training_curves.png", final_psnr=metrics.psnr)
    if curves is not None:
        parts.append(f"<h2>Training</h2><img id='curves' src='{IMAGES_DIR}/{curves.name}' alt='training curves'>")

    # --- mesh statistics
    stats = _stats_dict(mesh_stats)
    if stats is not None:
        parts.append("<h2>Mesh</h2><table id='mesh-stats'>")
        for k, v in stats.items():
            parts.append(f"<tr><th>{e(str(k))}</th><td>{e(_fmt(v, 4) if isinstance(v, float) else str(v))}</td></tr>")
        parts.append("</table>")

    # --- views
    if images:
        shaded = sum(vi.shaded is not None for vi in images)
        parts.append("<h2>Views</h2><p>ground truth | render | "
                     + ("surface (the mesh without its colours: grey, lit from the camera; " f"{shaded} views) | "
                        if shaded else "")
                     + f"mean absolute error (black 0, yellow &ge; {ERROR_MAP_MAX:g}); {len(images)} of "
                     f"{len(metrics.views)} views shown.</p>")  # fmt: skip
    for k, vi in enumerate(images):
        if vi.name not in by_name:
            raise ValueError(f"report image {vi.name!r} has no metrics entry (views: {list(by_name)[:5]}...)")
        gt, rd = _to_uint8(vi.gt), _to_uint8(vi.render)
        if gt.shape != rd.shape:
            raise ValueError(f"view {vi.name!r}: ground truth {gt.shape} and render {rd.shape} differ in shape")
        stem = f"{k:03d}"
        files = {"gt": f"{stem}_gt.png", "render": f"{stem}_render.png", "error": f"{stem}_error.png"}
        _save_png(gt, img_dir / files["gt"])
        _save_png(rd, img_dir / files["render"])
        _save_png(error_map(vi.gt, vi.render), img_dir / files["error"])
        shown = [("ground truth", "gt"), ("render", "render"), ("error", "error")]
        if vi.shaded is not None:
            sh = _to_uint8(vi.shaded)
            if sh.shape != rd.shape:
                raise ValueError(f"view {vi.name!r}: shaded {sh.shape} and render {rd.shape} differ in shape")
            files["shaded"] = f"{stem}_shaded.png"
            _save_png(sh, img_dir / files["shaded"])
            shown.insert(2, ("surface", "shaded"))
        v = by_name[vi.name]
        caption = f"PSNR {_fmt(v.psnr, 2)} dB, SSIM {_fmt(v.ssim, 4)}, LPIPS {_fmt(v.lpips, 4)}"
        parts.append(f"<h3>{e(vi.name)}</h3><div class='view' data-name='{e(vi.name)}'>")
        for label, key in shown:
            parts.append(f"<figure><img src='{IMAGES_DIR}/{files[key]}' alt='{label}'>"
                         f"<figcaption>{label}{' - ' + caption if key == 'render' else ''}</figcaption></figure>")
        parts.append("</div>")

    # --- config
    if config is not None:
        parts.append(f"<h2>Config</h2><pre id='config'>{e(json.dumps(json_safe(config), indent=2, default=str))}</pre>")
    parts.append("</body></html>")
    page = out / REPORT_HTML
    atomic_write_text(page, "\n".join(parts))
    return page


def add_file_scores(page: str | Path, model: SplitMetrics, file: SplitMetrics, file_report: str | None = None) -> Path:
    """Insert a table 'What you get' into an existing report.html: the model's scores beside those of the exported
    file rendered as its format's specification defines it (trisplat.eval.file_scores), with a link to the file's
    own report. Returns the page."""
    page = Path(page)
    e = html.escape
    rows = [("model (" + e(model.mode) + " render)", model), (e(str(file.extra.get("file", "file"))) +
                                                            " (glTF spec render)", file)]
    table = ["<h2>What you get</h2><table id='file-scores'><tr><th>rendered</th><th>PSNR (dB)</th><th>SSIM</th>"
             "<th>LPIPS</th></tr>"]
    for name, m in rows:
        table.append(f"<tr><td class='name'>{name}</td><td>{_fmt(m.psnr, 2)}</td><td>{_fmt(m.ssim, 4)}</td>"
                     f"<td>{_fmt(m.lpips, 4)}</td></tr>")
    table.append("</table>")
    if file_report:
        table.append(f"<p><a href='{e(file_report)}'>the file's own report</a> (its renders beside the photos)</p>")
    return insert_section(page, "\n".join(table))


def insert_section(page: str | Path, section: str, text: str | None = None) -> Path:
    """Write report.html `page` with `section` (HTML) inserted before its per-view metrics table (at the end of the
    body when it has none). text: the page's HTML to insert into, when the caller already edited it."""
    page = Path(page)
    text = page.read_text() if text is None else text
    marker = "<h2>Metrics</h2>"
    text = text.replace(marker, section + marker, 1) if marker in text else text.replace("</body>", section + "</body>")
    atomic_write_text(page, text)
    return page
