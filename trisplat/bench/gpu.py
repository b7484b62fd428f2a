"""`trisplat bench gpu`: the prepared check of the CUDA backend on a GPU machine (scripts/gpu_check.sh runs it):
parity with the reference, render timings, a lego training run; one gpu.json and one gpu.md.

Phases, in this order, inside one deadline (--deadline-s), each recorded even when a later one fails:
  facts     GPU, driver, versions; the first render's seconds (the kernels compile, cached on disk for the rest)
  timings   800x800 with 100k and 1M faces (2-20 px), forward, forward+backward and z-buffer, medians; the fixed cost
            of one launch sequence (one face); on a quiet GPU, before the lego run starts
  lego      `trisplat bench train --scenes lego --minutes M --device cuda` in a subprocess, scored as the CPU runs,
            given what is left of the deadline; while it runs:
  parity    the CUDA kernels against the dense float64 reference (on the GPU) on awkward scenes, forward and every
            gradient, with the CPU kernels' test tolerances (tests/render/test_render_numba.py); and against the
            Numba kernels on a medium scene (small scenes: they barely load the GPU)
  pytest    tests/render/test_render_cuda.py on the GPU, when a minute is left after lego
--dry-run runs every phase tiny under numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1, no GPU): the plumbing, not the
numbers.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from trisplat.commands.style import CLI_STYLE

# the CPU kernels' test tolerances (tests/render/test_render_numba.py): per pixel value, the share of pixels allowed
# beyond it (centres within rounding of an edge or threshold), gradients relative to their largest entry
IMG_ATOL = 2e-4
BOUNDARY_FRACTION = 0.01
GRAD_RTOL = 2e-3
GRAD_OUTLIER_FRACTION = 0.002  # large scenes: vertices whose position gradient may exceed GRAD_RTOL (alpha_min cut)
GRAD_OUTLIER_RTOL = 0.1
SIGMA = 0.7
TARGETS = {"fwd_bwd_ms_1M_800": 20.0, "lego_psnr_db": 27.0}  # issue 51, for an H100


@dataclass
class BenchGpuArgs:
    """The CUDA backend's check on a GPU machine: parity, timings, a lego run; writes gpu.json and gpu.md."""

    out: Path = Path("bench_results")
    """Folder for gpu.json / gpu.md (and the lego run's train_cuda.*)."""
    data_root: Path = Path("../shared/data")
    """Folder holding lego/ (as `trisplat bench train --data-root`)."""
    runs: Path = Path("/tmp/trisplat_gpu_runs")
    """Where the lego run folder goes."""
    minutes: float = 5.0
    """The lego run's --minutes."""
    texture_size: int = 0
    """The lego run's --texture-size (0: vertex colours; skips the texture fit, changes only the file PSNR)."""
    deadline_s: float = 480.0
    """Wall-clock budget of the whole check; the lego run gets what the earlier phases leave (minus a margin)."""
    repeats: int = 5
    """Timed runs per timing case (medians)."""
    commit: str = ""
    """The commit the files came from, recorded when the checkout has no git history (a copied working tree)."""
    dry_run: bool = False
    """Every phase tiny, under numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1; no GPU): checks the plumbing."""


def _awkward(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera-frame triangles [6,3,3] of the awkward kinds: huge (behind the rest), tiny, degenerate, behind the camera,
    crossing the near plane, off-screen."""
    def at(uv, z):
        uv, z = np.asarray(uv, float), np.asarray(z, float)
        return np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], 1)

    return np.stack([
        at([[-30, -20], [width + 40, -10], [width / 2, height + 40]], [11.0, 11.5, 12.0]),
        at([[10.2, 10.1], [11.1, 10.3], [10.5, 11.0]], [1.5, 1.5, 1.5]),
        at([[5, 5], [15, 10], [25, 15]], [3.0, 3.0, 3.0]),
        [[0.0, 0.0, -1.0], [1.0, 0.0, -1.2], [0.0, 1.0, -1.1]],
        [[-0.2, -0.2, -0.5], [0.3, -0.1, 1.5], [0.0, 0.3, 1.5]],
        at([[-30, 5], [-10, 8], [-20, 20]], [2.0, 2.0, 2.0]),
    ])


def parity_scene(n: int, width: int, height: int, size_px: tuple[float, float], seed: int):
    """bench.render.random_triangles plus one face of each awkward kind (_awkward): float64 torch tensors."""
    import torch

    from trisplat.bench.render import random_triangles

    pos, faces, col, op, w2c, K = random_triangles(n, width, height, size_px, seed=seed)
    extra = _awkward(K, width, height).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    pos = np.concatenate([pos, extra])
    faces = np.arange(len(pos), dtype=np.int32).reshape(-1, 3)
    col = np.concatenate([col, rng.random((len(extra), 3))])
    op = np.concatenate([op, 0.3 + 0.6 * rng.random(len(extra))])
    return tuple(torch.as_tensor(np.asarray(a, np.float64)) for a in (pos, col, op, w2c, K)), torch.as_tensor(faces)


def _render_with_grads(scene, faces, backend: str, device, width: int, height: int, opts: dict):
    """One render and the gradients of a fixed random linear loss on rgb, alpha, depth and normal (float64 inputs)."""
    import torch

    from trisplat.render import rasterize

    pos, col, op, w2c, K = (t.to(device) for t in scene)
    P = [pos.clone().requires_grad_(), col.clone().requires_grad_(), op.clone().requires_grad_()]
    out = rasterize(P[0], faces.to(device), P[1], P[2], SIGMA, w2c, K, width, height, backend=backend, **opts)
    g = torch.Generator().manual_seed(0)
    loss = sum((t * (torch.rand(t.shape, generator=g, dtype=t.dtype).to(device) - 0.3)).sum()
               for t in (out.rgb, out.alpha, out.depth, out.normal))
    loss.backward()
    return out, [p.grad.detach().cpu() for p in P]


def compare(ref, gref, out, gout, outliers: bool) -> dict:
    """Errors of (out, gout) against (ref, gref) and whether they pass the CPU kernels' test tolerances (outliers:
    allow GRAD_OUTLIER_FRACTION of the vertices a position gradient within GRAD_OUTLIER_RTOL instead)."""
    res = {"image_max_abs": 0.0, "image_bad_fraction": 0.0}
    for name in ("rgb", "alpha", "depth", "normal"):
        d = (getattr(ref, name).detach().cpu().double() - getattr(out, name).detach().cpu().double()).abs()
        bad = d > IMG_ATOL
        res["image_max_abs"] = max(res["image_max_abs"], float(d.max()))
        res["image_bad_fraction"] = max(res["image_bad_fraction"], float((bad.any(-1) if bad.ndim == 3 else bad)
                                                                          .float().mean()))
    res["max_weight_max_abs"] = float((ref.max_weight.cpu().double() - out.max_weight.cpu().double()).abs().max())
    res["face_id_mismatch_fraction"] = float((ref.face_id.cpu() != out.face_id.cpu()).float().mean())
    ok = (res["image_bad_fraction"] <= BOUNDARY_FRACTION and res["max_weight_max_abs"] <= IMG_ATOL
          and res["face_id_mismatch_fraction"] <= BOUNDARY_FRACTION)
    for name, a, b in zip(("positions", "colors", "opacities"), gref, gout):
        scale = float(a.abs().max())
        rel = float((a - b).abs().max()) / scale if scale > 0 else float("inf")
        res[f"grad_{name}_rel"] = rel
        if name == "positions" and outliers:
            per = (a - b).abs().amax(1) / scale
            res["grad_positions_outlier_fraction"] = float((per > GRAD_RTOL).float().mean())
            ok &= res["grad_positions_outlier_fraction"] <= GRAD_OUTLIER_FRACTION and rel <= GRAD_OUTLIER_RTOL
        else:
            ok &= rel <= GRAD_RTOL
    res["ok"] = bool(ok)
    return res


def parity(device, dry: bool) -> list[dict]:
    """The CUDA kernels against the float64 reference (on `device`) and, on a medium scene, the Numba kernels."""
    cases = ([(12, 24, 16, (3, 12), {"tile_size": 8})] if dry else
             [(300, 96, 64, (2, 20), {}), (300, 96, 64, (2, 20), {"perspective_correct": True}),
              (150, 96, 64, (15, 40), {"opacity_mode": "mean", "tile_size": 8}),
              (2000, 160, 120, (2, 20), {"tile_size": 32}), (300, 96, 64, (2, 20), {"supersample": 2})])
    rows = []
    for seed, (n, w, h, size, opts) in enumerate(cases):
        scene, faces = parity_scene(n, w, h, size, seed)
        ref, gref = _render_with_grads(scene, faces, "reference", device, w, h, opts)
        out, gout = _render_with_grads(scene, faces, "cuda", device, w, h, opts)
        rows.append({"against": "reference", "faces": int(faces.shape[0]), "size": f"{w}x{h}", "px": f"{size[0]}-{size[1]}",
                     "options": opts, **compare(ref, gref, out, gout, outliers=n > 1000)})
    if not dry:  # the Numba kernels render CPU tensors; the same scene on the GPU
        scene, faces = parity_scene(1500, 160, 120, (2, 20), 3)
        nb, gnb = _render_with_grads(scene, faces, "numba", "cpu", 160, 120, {})
        out, gout = _render_with_grads(scene, faces, "cuda", device, 160, 120, {})
        rows.append({"against": "numba", "faces": int(faces.shape[0]), "size": "160x120", "px": "2-20", "options": {},
                     **compare(nb, gnb, out, gout, outliers=True)})
    return rows


def timings(device, dry: bool, repeats: int) -> list[dict]:
    """Forward, forward+backward and z-buffer medians (bench.render._run_case), GPU peak memory per case."""
    import torch

    from trisplat.bench.render import _run_case

    cases = [(32, 32, 1, 5, 10), (32, 32, 60, 2, 20)] if dry else [
        (800, 800, 1, 100, 120), (800, 800, 100_000, 2, 20), (800, 800, 1_000_000, 2, 20)]
    rows = []
    for w, h, n, lo, hi in cases:
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        row = _run_case(w, h, n, lo, hi, False, 1 if dry else repeats, 0.5, backend="cuda", device=device.type)
        if device.type == "cuda":
            row["gpu_peak_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
        rows.append(row)
    return rows


def _first_render_s(device) -> float:
    """Seconds of the first soft render with its backward and of the first z-buffer render (kernel compilation)."""
    scene, faces = parity_scene(20, 32, 32, (3, 12), 0)
    t0 = time.perf_counter()
    _render_with_grads(scene, faces, "cuda", device, 32, 32, {})
    from trisplat.render import rasterize_hard

    pos, col, _, w2c, K = (t.to(device) for t in scene)
    rasterize_hard(pos, faces.to(device), col, w2c, K, 32, 32, backend="cuda")
    return time.perf_counter() - t0


@dataclass
class LegoRun:
    """The lego bench running in its own process (started before the parity phase, which runs beside it)."""

    proc: subprocess.Popen
    command: str
    log: Path
    started: float


def start_lego(args: BenchGpuArgs, device) -> LegoRun:
    """Start `trisplat bench train --scenes lego` on `device` in a subprocess (output to OUT/train/lego.log)."""
    out = Path(args.out) / "train"
    out.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "trisplat", "bench", "train", "--scenes", "lego", "--minutes", f"{args.minutes:g}",
           "--device", device.type, "--data-root", str(args.data_root), "--out", str(out), "--runs", str(args.runs),
           "--texture-size", str(args.texture_size)]
    log = out / "lego.log"
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
    return LegoRun(proc, " ".join(cmd[1:]), log, time.perf_counter())


def finish_lego(run: LegoRun, args: BenchGpuArgs, device, budget_s: float) -> dict:
    """Wait up to budget_s for the lego run (then stop it); its train_*.json row, metrics.json's scores and, stopped
    or not, its history (steps, test PSNRs, the switch)."""
    res: dict = {"command": run.command, "budget_s": round(budget_s, 1)}
    try:
        res["returncode"] = run.proc.wait(timeout=max(budget_s, 1.0))
    except subprocess.TimeoutExpired:
        run.proc.kill()
        run.proc.wait()
        res["returncode"], res["timed_out"] = None, True
    res["wall_s"] = round(time.perf_counter() - run.started, 1)
    res["log_tail"] = run.log.read_text(errors="replace")[-3000:] if run.log.exists() else ""
    out = Path(args.out) / "train"
    table = out / (f"train_{device.type}.json" if device.type != "cpu" else "train.json")
    if table.exists() and res.get("returncode") == 0:
        t = json.loads(table.read_text())
        res["row"] = dict(zip(t["columns"], t["rows"][0])) if t["rows"] else None
    folder = Path(args.runs) / f"lego_default_{args.minutes:g}min{'_' + device.type if device.type != 'cpu' else ''}"
    if (folder / "history.jsonl").exists():
        hist = [json.loads(line) for line in (folder / "history.jsonl").read_text().splitlines() if line.strip()]
        tests = [h for h in hist if "test_psnr" in h]
        steps = [h for h in hist if "step" in h and "loss" in h]
        res["history"] = {"steps": steps[-1]["step"] if steps else 0,
                          "train_wall_s": steps[-1]["wall_s"] if steps else 0,
                          "test_psnr": [(h["step"], round(h["test_psnr"], 3)) for h in tests],
                          "switch": [h for h in hist if "switch" in h or "switch_failed" in h]}
    if (folder / "metrics.json").exists():
        m = json.loads((folder / "metrics.json").read_text())
        res["metrics"] = {k: m.get(k) for k in ("psnr", "psnr_1spp", "ssim", "soft_psnr", "file_psnr", "faces",
                                                 "connected", "switch_failure", "switch_s", "test_views", "supersample")}
    return res


def pytest_phase(budget_s: float) -> dict:
    """tests/render/test_render_cuda.py on this machine (its GPU), within budget_s."""
    tests = Path(__file__).resolve().parents[2] / "tests" / "render" / "test_render_cuda.py"
    if not tests.exists():
        return {"skipped": f"{tests} is not in this checkout"}
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(tests)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=max(budget_s, 1.0))
    except subprocess.TimeoutExpired:
        return {"timed_out": True, "budget_s": round(budget_s, 1)}
    return {"returncode": proc.returncode, "summary": proc.stdout.strip().splitlines()[-1:] if proc.stdout else [],
            "tail": proc.stdout[-2500:] if proc.returncode else ""}


def _facts(args: BenchGpuArgs, device) -> dict:
    import numba
    import torch

    from trisplat.bench.common import machine_info

    info = machine_info()
    if info.get("commit") == "unknown" and args.commit:
        info["commit"] = args.commit
    facts = {"machine": info, "device": str(device), "simulated": bool(numba.config.ENABLE_CUDASIM)}
    try:
        from importlib import metadata

        facts["numba_cuda"] = metadata.version("numba-cuda")
    except Exception:  # noqa: BLE001 - a missing distribution is recorded as such
        facts["numba_cuda"] = None
    if device.type == "cuda":
        p = torch.cuda.get_device_properties(device)
        facts.update(gpu=p.name, gpu_memory_gib=round(p.total_memory / 2**30, 1), multiprocessors=p.multi_processor_count,
                     capability=f"{p.major}.{p.minor}", torch_cuda=torch.version.cuda)
        try:
            facts["nvidia_smi"] = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,clocks.max.sm",
                                                  "--format=csv,noheader"], capture_output=True, text=True,
                                                 timeout=20).stdout.strip()
        except (OSError, subprocess.TimeoutExpired):
            facts["nvidia_smi"] = None
    return facts


def _phase(report: dict, name: str, fn):
    """Run one phase into report[name] (its error and traceback instead when it fails) and time it."""
    t0 = time.perf_counter()
    try:
        report[name] = fn()
    except Exception as exc:  # noqa: BLE001 - a failed phase is recorded; the next phases still run
        report[name] = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()[-4000:]}
    report.setdefault("phase_s", {})[name] = round(time.perf_counter() - t0, 1)


def verdict(report: dict) -> dict:
    """The issue's targets against what this run measured (None where a phase did not get that far)."""
    par = report.get("parity")
    rows = report.get("timings")
    big = [r for r in rows if r.get("faces") == 1_000_000] if isinstance(rows, list) else []
    lego_run = report.get("lego") or {}
    psnr = ((lego_run.get("metrics") or {}).get("psnr")) if isinstance(lego_run, dict) else None
    return {
        "parity_ok": all(r["ok"] for r in par) if isinstance(par, list) and par else None,
        "fwd_bwd_ms_1M_800": big[0]["fwd_bwd_ms"] if big else None,
        "fwd_bwd_1M_800_met": (big[0]["fwd_bwd_ms"] <= TARGETS["fwd_bwd_ms_1M_800"]) if big else None,
        "lego_psnr_db": psnr,
        "lego_met": (psnr >= TARGETS["lego_psnr_db"]) if psnr is not None else None,
        "targets": TARGETS,
    }


def markdown(report: dict) -> str:
    """gpu.md: the facts, the parity and timing tables, the lego run and the verdict."""
    f = report.get("facts", {})
    lines = [f"### gpu\n\n`{report['command']}` on {f.get('gpu', f.get('device'))} (capability {f.get('capability')}, "
             f"{f.get('nvidia_smi')}), torch {f.get('machine', {}).get('torch')} CUDA {f.get('torch_cuda')}, numba "
             f"{f.get('machine', {}).get('numba')}, numba-cuda {f.get('numba_cuda')}, commit "
             f"{f.get('machine', {}).get('commit')}, {f.get('machine', {}).get('date')}"
             f"{'; SIMULATOR (dry run): no number here is a GPU measurement' if f.get('simulated') else ''}\n",
             f"Phases (s): {report.get('phase_s')}; first render with backward and z-buffer (compiles the kernels): "
             f"{report.get('first_render_s')} s\n", "| against | faces | size | px | options | image max abs | bad px "
             "frac | max weight abs | face_id frac | grad pos rel | grad col rel | grad op rel | ok |", "|" + "---|" * 13]
    par = report.get("parity")
    if isinstance(par, list):
        for r in par:
            lines.append(f"| {r['against']} | {r['faces']} | {r['size']} | {r['px']} | {r['options'] or '-'} | "
                         f"{r['image_max_abs']:.2e} | {r['image_bad_fraction']:.4f} | {r['max_weight_max_abs']:.2e} | "
                         f"{r['face_id_mismatch_fraction']:.4f} | {r['grad_positions_rel']:.2e} | "
                         f"{r['grad_colors_rel']:.2e} | {r['grad_opacities_rel']:.2e} | {r['ok']} |")
    else:
        lines.append(f"\nparity: {par}")
    lines += ["", "| size | faces | tri px | pairs | visible | fwd ms | fwd+bwd ms | hard ms | GPU peak MB |",
              "|" + "---|" * 9]
    rows = report.get("timings")
    if isinstance(rows, list):
        lines += [f"| {r['size']} | {r['faces']} | {r['px']} | {r['pairs']} | {r['visible']} | {r['fwd_ms']:.3g} | "
                  f"{r['fwd_bwd_ms']:.3g} | {r['hard_ms']:.3g} | {r.get('gpu_peak_mb', float('nan')):.0f} |"
                  for r in rows]
    else:
        lines.append(f"\ntimings: {rows}")
    lego_run = report.get("lego") or {}
    lines += ["", f"lego: `{lego_run.get('command')}`: return code {lego_run.get('returncode')}, "
              f"{lego_run.get('wall_s')} s of {lego_run.get('budget_s')} s; metrics {lego_run.get('metrics')}; "
              f"history {(lego_run.get('history') or {}).get('test_psnr')}; steps "
              f"{(lego_run.get('history') or {}).get('steps')}",
              "", f"pytest (tests/render/test_render_cuda.py on this machine): {report.get('pytest')}",
              "", f"Verdict: {report.get('verdict')}"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(BenchGpuArgs, args=argv, prog="trisplat bench gpu", description=__doc__, config=CLI_STYLE)
    t_start = time.perf_counter()
    import numba
    import torch

    if args.dry_run:
        if not numba.config.ENABLE_CUDASIM:
            print("trisplat bench gpu --dry-run: set NUMBA_ENABLE_CUDASIM=1 (numba's CUDA simulator) before starting",
                  file=sys.stderr)
            return 2
        device = torch.device("cpu")
    else:
        from trisplat.render.device import resolve_device

        try:
            device = resolve_device("cuda")
        except ValueError as exc:
            print(f"trisplat bench gpu: {exc}", file=sys.stderr)
            return 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"command": "trisplat bench gpu " + " ".join(argv or [])}

    def save():
        report["verdict"] = verdict(report)
        report["wall_s"] = round(time.perf_counter() - t_start, 1)
        (out / "gpu.json").write_text(json.dumps(report, indent=2, default=str))
        (out / "gpu.md").write_text(markdown(report))

    def left() -> float:
        return args.deadline_s - (time.perf_counter() - t_start)

    _phase(report, "facts", lambda: _facts(args, device))
    _phase(report, "first_render_s", lambda: round(_first_render_s(device), 2))
    _phase(report, "timings", lambda: timings(device, args.dry_run, args.repeats))  # a quiet GPU: before lego
    save()
    if args.dry_run:  # the plumbing of the lego phase, on a tiny generated "lego" trained on the CPU
        from trisplat.synth import demo_mesh, write_blender_scene

        fake = Path(args.data_root) / "lego"
        if fake.exists() and not (fake / "synth.json").exists():
            print(f"trisplat bench gpu --dry-run: {fake} holds a real capture; the dry run writes a generated stand-in "
                  "there: give it another --data-root", file=sys.stderr)
            return 2
        write_blender_scene(fake, demo_mesh(), n_train=4, n_test=2, width=24, height=24, samples_per_pixel=1,
                            n_points=0)
    lego_run = start_lego(args, torch.device("cpu") if args.dry_run else device)
    # beside the lego run: the parity checks' small scenes (the compiled kernels are cached on disk by then)
    _phase(report, "parity", lambda: parity(device, args.dry_run))
    save()
    _phase(report, "lego", lambda: finish_lego(lego_run, args, torch.device("cpu") if args.dry_run else device,
                                               left() - 15.0))
    save()
    if left() > 60.0 and not args.dry_run:
        _phase(report, "pytest", lambda: pytest_phase(left() - 10.0))
    else:
        report["pytest"] = {"skipped": "dry run" if args.dry_run else f"{left():.0f} s left of the deadline"}
    save()
    print((out / "gpu.md").read_text())
    return 0 if (report["verdict"]["parity_ok"] is not False) else 1


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
