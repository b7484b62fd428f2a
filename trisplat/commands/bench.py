"""`trisplat bench SUITE|all [options]`: one entry for the benchmarks (JSON + markdown in --out); SUITES lists them."""
from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

# subcommand -> (module with main(argv) -> int, what it measures)
SUITES: dict[str, tuple[str, str]] = {
    "render": ("trisplat.bench.render", "rasterizer forward/backward time and memory vs triangles and resolution"),
    "train": ("trisplat.bench.train", "training wall time and test PSNR/SSIM/LPIPS on reference scenes"),
    "mesh": ("trisplat.bench.mesh", "soup-to-mesh time, mesh statistics and z-buffer frames per second"),
    "losses": ("trisplat.bench.losses", "training step kernels (losses, SH colour): fused Numba vs their torch twins"),
    "poses": ("trisplat.bench.poses", "structure from motion on a capture's photos vs its own model (fox)"),
}
# run by name only, not by `all`: tens of minutes on the full sequence (slam), or tools outside the Python install
# (consumers: headless Chromium, Blender's bpy in its own environment)
LONG_SUITES: dict[str, tuple[str, str]] = {
    "consumers": ("trisplat.bench.consumers", "mesh.glb in real consumers (browser viewer: three.js GLTFLoader; "
                  "Blender: bpy + Cycles) vs the glTF spec render: PSNR (needs chromium; Blender: "
                  "scripts/ci_extras.sh --blender)"),
    "slam": ("trisplat.bench.slam", "trisplat slam vs Open3D odometry + TSDF on an RGB-D capture: ATE, time, mesh "
             "Chamfer (needs open3d-cpu; long: not part of 'all')"),
    "blocks": ("trisplat.bench.blocks", "partitioned training on local Ray (issue 28) vs one run on a synthetic "
               "street: PSNR, Chamfer, largest piece at equal CPU; peak memory per block for 2/4/8 objects (needs the "
               "cluster extra; long: tens of minutes)"),
    "texture": ("trisplat.bench.texture", "texturing a finished run (--run RUN): atlas, rows and solve seconds, "
                "peak memory; regulariser weights scored on held-out training views"),
    "step": ("trisplat.bench.step", "a run's training step stage by stage at 1..N threads: speed-up and serial fraction "
             "(RUN as its argument; its checkpoints soup.pt and last.pt)"),
    "walk": ("trisplat.bench.walk", "spheres dropped on a run's mesh in a physics engine (PyBullet): how many stand on "
             "the surface, where the others fell through (RUN as its argument)"),
    "switch-memory": ("trisplat.bench.switch_memory", "peak memory of the soup-to-surface switch on a synthetic "
                      "capture (default 300 photos of 4000x3000; long: tens of minutes)"),
    "gpu": ("trisplat.bench.gpu", "the CUDA backend on an NVIDIA GPU: parity with the reference, 100k/1M-face render "
            "timings, a lego training run (scripts/gpu_check.sh; needs a GPU, or --dry-run under numba's simulator)"),
}
DEFAULT_OUT = Path("bench_results")
INDEX_MD = "index.md"


def _usage() -> str:
    lines = ["usage: trisplat bench {render,train,mesh,losses,poses,consumers,slam,blocks,texture,step,walk,switch-memory,"
             "gpu,all} [options]   (trisplat bench SUITE --help for its options)",
             "", "Each suite writes <name>.json (with machine, versions, commit) and <name>.md into --out "
             f"(default {DEFAULT_OUT}/).", "", "suites:"]  # fmt: skip
    lines += [f"  {name:<9} {desc}" for name, (_, desc) in {**SUITES, **LONG_SUITES}.items()]
    lines.append(f"  {'all':<9} every suite in turn with the same options, except {', '.join(LONG_SUITES)} (long: run "
                 f"it by name); also writes --out/{INDEX_MD}")
    return "\n".join(lines)


def _load(name: str):
    """The suite's module, or None (with a message on stderr) when it is not part of this installation."""
    module = {**SUITES, **LONG_SUITES}[name][0]
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name is not None and (module == exc.name or module.startswith(exc.name + ".")):
            print(f"trisplat bench {name}: the {name} benchmark ({module}) is not available in this installation",
                  file=sys.stderr)  # fmt: skip
            return None
        raise


def _out_dir(argv: list[str]) -> Path:
    for k, a in enumerate(argv):
        if a == "--out" and k + 1 < len(argv):
            return Path(argv[k + 1])
        if a.startswith("--out="):
            return Path(a.split("=", 1)[1])
    return DEFAULT_OUT


def write_index(out_dir: Path, since: float) -> Path | None:
    """Concatenate the markdown tables written into out_dir since `since` (epoch s) into INDEX_MD, for docs to
    include; None when there are none."""
    tables = sorted(p for p in Path(out_dir).glob("*.md") if p.name != INDEX_MD and p.stat().st_mtime >= since)
    if not tables:
        return None
    index = Path(out_dir) / INDEX_MD
    index.write_text("\n\n".join(p.read_text().rstrip() for p in tables) + "\n")
    return index


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name == "all":
        if any(a in ("-h", "--help") for a in rest):
            print(_usage())
            return 0
        start = time.time() - 1.0  # mtime resolution
        status = 0
        for suite in SUITES:
            mod = _load(suite)
            if mod is None:
                status = status or 1
                continue
            print(f"== bench {suite}", file=sys.stderr)
            status = int(mod.main(list(rest)) or 0) or status
        index = write_index(_out_dir(rest), start)
        if index is not None:
            print(f"index: {index}")
        return status
    if name not in SUITES and name not in LONG_SUITES:
        print(f"trisplat bench: unknown suite {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    mod = _load(name)
    if mod is None:
        return 1
    return int(mod.main(rest) or 0)
