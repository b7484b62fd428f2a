"""`trisplat bench render`: soft (forward, forward+backward) and hard renderer timings, pairs, peak memory."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import tyro

from trisplat.commands.style import CLI_STYLE

REFERENCE_MAX_FACES = 100_000  # the dense reference is run only up to this many faces ...
REFERENCE_MAX_PIXELS = 256 * 256  # ... and this image size (it needs GBs and minutes beyond)
GEN_CHUNK = 100_000  # triangles generated per chunk


@dataclass
class BenchRenderConfig:
    """Benchmark the triangle-splatting renderer on random triangle soups (camera at the origin)."""

    out: Path = Path("bench_results")
    """Folder for render.json / render.md."""
    repeats: int = 5
    """Timed runs per case (the median is reported)."""
    quick: bool = False
    """Only the small cases (for a smoke run)."""
    sigma: float = 0.5
    """Window sharpness used for the soft renders."""
    reference: bool = True
    """Also time the dense PyTorch reference where it fits (100k faces at 256x256 takes about a minute)."""
    backend: Literal["numba", "cuda"] = "numba"
    """Renderer timed (soft and hard): numba (CPU kernels) or cuda (numba-cuda kernels on the GPU; gpu extra and a
    CUDA build of torch). Results go to render.json/.md for numba, render_cuda.json/.md for cuda."""
    case: str = ""
    """Internal: run a single case 'W,H,F,lo,hi,ref' and print JSON (used to isolate peak memory per case)."""


def random_triangles(n: int, width: int, height: int, size_px: tuple[float, float], seed: int = 0):
    """n independent triangles with random screen positions (centres on the image), screen sizes uniform in size_px
    (pixels, circumradius-like scale), depths 2-10, random colours and opacities 0.3-0.9.

    Returns numpy positions float32 [3n,3], faces int32 [n,3], colors [3n,3], opacities [3n], world_to_camera, K.
    """
    rng = np.random.default_rng(seed)
    f = 0.8 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    pos = np.empty((n, 3, 3), np.float32)
    for a in range(0, n, GEN_CHUNK):  # in chunks, so that the generator's temporaries stay small
        m = min(n, a + GEN_CHUNK) - a
        c = rng.uniform([0, 0], [width, height], size=(m, 2))
        s = rng.uniform(size_px[0], size_px[1], size=m)
        ang = rng.uniform(0, 2 * np.pi, size=(m, 1)) + np.array([0, 2.1, 4.2]) + rng.normal(0, 0.25, size=(m, 3))
        z = rng.uniform(2, 10, size=(m, 1)) * (1 + rng.normal(0, 0.02, size=(m, 3)))
        u = c[:, None, 0] + (s[:, None] / 2) * np.cos(ang)
        v = c[:, None, 1] + (s[:, None] / 2) * np.sin(ang)
        pos[a:a + m, :, 0] = (u - K[0, 2]) / f * z
        pos[a:a + m, :, 1] = (v - K[1, 2]) / f * z
        pos[a:a + m, :, 2] = z
    pos = pos.reshape(-1, 3)
    faces = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    colors = rng.random((3 * n, 3), dtype=np.float32)
    opac = (0.3 + 0.6 * rng.random(3 * n, dtype=np.float32)).astype(np.float32)
    return pos, faces, colors, opac, np.eye(4), K


def _current_rss_mb() -> float:
    """Resident set size of this process now, MiB (Linux)."""
    try:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError):
        return float("nan")


def _run_case(width: int, height: int, n: int, lo: float, hi: float, with_ref: bool, repeats: int, sigma: float,
              backend: str = "numba", device: str = "cpu"):
    import torch

    from trisplat.bench.common import median_ms, peak_rss_mb
    from trisplat.render import rasterize, rasterize_hard

    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)  # time finished work, not launches
    pos, faces, col, op, w2c, K = random_triangles(n, width, height, (lo, hi))
    if dev.type != "cpu":
        pos, faces, col, op = (torch.from_numpy(a).to(dev) for a in (pos, faces, col, op))
        w2c, K = torch.as_tensor(w2c, device=dev), torch.as_tensor(K, device=dev)
    P = torch.as_tensor(pos).requires_grad_()
    C = torch.as_tensor(col).requires_grad_()
    O = torch.as_tensor(op).requires_grad_()
    g = torch.rand(height, width, 3, device=dev)
    main_backend = backend

    def fwd(backend=main_backend):
        with torch.no_grad():
            out = rasterize(P, faces, C, O, sigma, w2c, K, width, height, backend=backend)
        sync()
        return out

    def fwd_bwd(backend=main_backend):
        out = rasterize(P, faces, C, O, sigma, w2c, K, width, height, backend=backend)
        ((out.rgb * g).sum() + out.alpha.sum() + out.depth.sum() + out.normal.sum()).backward()
        P.grad = C.grad = O.grad = None
        sync()
        return out

    row = {"size": f"{width}x{height}", "faces": n, "px": f"{lo:g}-{hi:g}", "base_rss_mb": _current_rss_mb()}
    out = fwd()
    row.update(pairs=out.pairs_evaluated, visible=out.faces_visible)
    del out
    row["fwd_ms"] = median_ms(fwd, repeats=repeats)
    row["fwd_bwd_ms"] = median_ms(fwd_bwd, repeats=repeats)
    row["peak_rss_mb"] = peak_rss_mb()  # the soft renderer's peak, before the hard mode runs in this process
    hard = lambda: (rasterize_hard(pos, faces, col, w2c, K, width, height, backend=backend), sync())  # noqa: E731
    row["hard_ms"] = median_ms(hard, repeats=repeats)
    row["hard_fps"] = 1000.0 / row["hard_ms"]
    row["hard_peak_rss_mb"] = peak_rss_mb()
    if with_ref:
        row["ref_fwd_bwd_ms"] = median_ms(lambda: fwd_bwd("reference"), repeats=1, warmup=0)
        row["ref_peak_rss_mb"] = peak_rss_mb()
    return row


CASES = [  # width, height, faces, min px, max px
    (256, 256, 20_000, 2, 20), (256, 256, 100_000, 2, 20), (256, 256, 20_000, 35, 45),
    (800, 800, 20_000, 2, 20), (800, 800, 100_000, 2, 20), (800, 800, 1_000_000, 2, 20), (800, 800, 20_000, 35, 45),
]


def main(argv: list[str] | None = None) -> int:
    cfg = tyro.cli(BenchRenderConfig, args=argv, prog="trisplat bench render", description=__doc__, config=CLI_STYLE)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if cfg.case:
        w, h, n, lo, hi, ref = cfg.case.split(",")
        from trisplat.render.device import resolve_device

        device = resolve_device("cuda" if cfg.backend == "cuda" else "cpu").type
        row = _run_case(int(w), int(h), int(n), float(lo), float(hi), ref == "1", cfg.repeats, cfg.sigma, cfg.backend,
                        device)
        print("RESULT " + json.dumps(row))
        return 0
    from trisplat.progress import progress_bar

    from trisplat.bench.common import BenchTable

    cols = ["image", "faces", "tri px", "pairs evaluated", "fwd ms", "fwd+bwd ms", "peak RSS MB", "RSS before MB",
            "ref fwd+bwd ms",
            "ref peak RSS MB", "speed-up vs ref", "hard ms", "hard FPS", "peak RSS with hard MB"]
    table = BenchTable("render" if cfg.backend == "numba" else f"render_{cfg.backend}", cols)
    cases = CASES[:3] if cfg.quick else CASES
    if cfg.backend == "cuda":
        from trisplat.render.device import device_name, resolve_device

        try:
            dev = resolve_device("cuda")
        except ValueError as exc:
            print(f"trisplat bench render: {exc}", file=sys.stderr)
            return 1
        table.notes.append(f"Backend cuda (numba-cuda kernels) on device {device_name(dev)}; the dense reference "
                           "runs on the same device. 'pairs evaluated' counts, for cuda, the (pixel, face) pairs of "
                           "each tile's list whose pixel lies in the face's pixel box while the pixel is not yet "
                           "opaque (a thread per pixel tests every face of its tile).")
    else:
        dev = None
    for w, h, n, lo, hi in progress_bar(cases, desc="bench render"):
        ref = cfg.reference and n <= REFERENCE_MAX_FACES and w * h <= REFERENCE_MAX_PIXELS
        cmd = [sys.executable, "-m", "trisplat.bench.render", "--case", f"{w},{h},{n},{lo},{hi},{int(ref)}",
               "--repeats", str(cfg.repeats), "--sigma", str(cfg.sigma), "--backend", cfg.backend]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
        if proc.returncode != 0 or not lines:
            table.add(f"{w}x{h}", n, f"{lo}-{hi}", *(["failed"] + [None] * 10))
            print(proc.stderr[-2000:], file=sys.stderr)
            continue
        r = json.loads(lines[-1][7:])
        ref_ms = r.get("ref_fwd_bwd_ms")
        table.add(r["size"], n, r["px"], r["pairs"], r["fwd_ms"], r["fwd_bwd_ms"], r["peak_rss_mb"], r["base_rss_mb"],
                  ref_ms,
                  r.get("ref_peak_rss_mb"), ref_ms / r["fwd_bwd_ms"] if ref_ms else None, r["hard_ms"], r["hard_fps"],
                  r["hard_peak_rss_mb"])
    table.notes.append("Medians over --repeats runs after one warm-up. Each case runs in its own process, so peak RSS "
                       "is per case; it includes the Python/torch/numba baseline and the scene arrays, shown as "
                       "'RSS before' (measured before the first render); 'peak RSS' is taken after the soft renders, "
                       "'peak RSS with hard' after the hard renders too. The dense reference is timed once. "
                       "fwd+bwd = render + a loss on rgb, alpha, depth and normal + backward to positions, colours "
                       "and opacities. 'pairs evaluated' = (pixel, face) window evaluations of the Numba kernel. "
                       "Hard = z-buffer render (rasterize_hard). On a shared machine the numbers are noisy.")
    md = table.write(cfg.out, "trisplat bench render " + " ".join(argv or []))
    print(md.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
