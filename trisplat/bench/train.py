"""`trisplat bench train`: equal-wall-time training; quality of the opaque mesh (and its geometry where known)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import tyro

from trisplat.commands.style import CLI_STYLE
from trisplat.bench.common import BenchTable

PROG = "trisplat bench train"

SCENES = {
    # name: (folder under the data root, or None for a scene the benchmark generates; loader/config options)
    "lego": ("lego", {"downscale": 1}),
    # fox through its COLMAP model: the sparse points give the Delaunay initialisation (transforms.json has none)
    "fox": ("fox", {"downscale": 4, "data_format": "colmap"}),
    # Spot (public domain) rendered from 64 + 16 views by trimesh's ray caster; its true mesh scores geometry
    "spot": (None, {"downscale": 1}),
    # 168 real photos of a room around a bonsai, no poses: posed by `trisplat poses` (cached; its time is the poses
    # report's), trained at half size (400x266, the resolution --minutes 30 picks), every 8th photo held out
    "bonsai": ("bonsai/images", {"downscale": 2}),
    # a room seen from inside (trisplat.synth.room), exact poses: walls, floor and ceiling beyond the cameras
    "room": (None, {"downscale": 1}),
}


@dataclass
class TrainBenchArgs:
    """Train each scene with each preset for the same wall time and score the opaque mesh (hard render) on the
    test split; scenes with a known surface (spot) also get Chamfer / F-score and mesh statistics."""

    scenes: list[str] = field(default_factory=lambda: ["lego", "fox"])
    presets: list[str] = field(default_factory=lambda: ["default"])
    minutes: float = 30.0
    data_root: Path = Path("../shared/data")
    out: Path = Path("bench_results")
    runs: Path = Path("bench_results/runs")
    """Where the benchmark's run directories (and generated scenes) go; existing runs are moved aside."""
    spot_size: int = 200
    """Image size of the generated Spot views."""
    output: str = "surface"
    """What the runs end with: 'surface' (one connected mesh, the default) or 'soup' (independent triangles)."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """Where the runs train (as `trisplat train --device`): cpu (the Numba kernels) or cuda (the numba-cuda kernels
    on the GPU; gpu extra). GPU results go to train_cuda.* and run folders named *_cuda."""
    texture_size: int | None = None
    """The runs' --texture-size (None: the preset's; 0: vertex colours in mesh.glb, which skips the texture fit and
    changes only the file PSNR column)."""


def _psnr_at_fractions(history: list[dict], fractions=(0.25, 0.5, 0.75)) -> list[str]:
    tests = [h for h in history if "test_psnr" in h]
    if not tests:
        return ["-"] * len(fractions)
    end = max(h["wall_s"] for h in history if "wall_s" in h)  # the first line, {"init": ...}, has no time
    out = []
    for f in fractions:
        before = [h for h in tests if h["wall_s"] <= f * end + 1e-9]
        out.append(f"{before[-1]['test_psnr']:.2f}@{before[-1]['wall_s'] / 60:.1f}m" if before else "-")
    return out


def spot_scene(args: TrainBenchArgs) -> Path:
    """The Spot capture (generated once): 64 train + 16 test views, surface samples as sparse points."""
    from trisplat.synth import spot_mesh, write_blender_scene

    out = args.runs / f"spot_scene_{args.spot_size}"
    if not (out / "synth.json").exists():
        mesh = spot_mesh(args.data_root / "meshes" / "spot_triangulated.obj")
        write_blender_scene(
            out, mesh, n_train=64, n_test=16, width=args.spot_size, height=args.spot_size, n_points=5000, progress=True
        )
    return out


def room_scene(args: TrainBenchArgs) -> Path:
    """The synthetic room (generated once): 96 views of 256x192 on a jittered ring, every 8th a test view."""
    from trisplat.synth.room import write_room_scene

    out = args.runs / "room_scene_256"
    if not (out / "synth.json").exists():
        write_room_scene(out, n_views=96, width=256, height=192, n_points=8000, progress=True)
    return out


def bench_data(name: str, folder: str | None, args: TrainBenchArgs) -> Path:
    """The capture a bench scene trains on: generated (spot, room), posed from photos (bonsai) or as stored."""
    if folder is None:
        return room_scene(args) if name == "room" else spot_scene(args)
    data = args.data_root / folder
    if not data.exists():
        raise FileNotFoundError(f"{data}: benchmark data missing (pass --data-root)")
    from trisplat.data.capture import is_plain_image_folder

    if is_plain_image_folder(data):
        from trisplat.sfm.cache import posed_capture

        return posed_capture(data)
    return data


def geometry_columns(run_dir: Path, gt_mesh: Path) -> list:
    """Chamfer (and its fraction of the GT diagonal), F-score at 1% of the diagonal and normal consistency of the
    run's mesh against the true surface (capture frame, like the ground truth)."""
    from trisplat.eval.geometry import compare_surfaces, load_surface

    g = compare_surfaces(load_surface(run_dir / "mesh.ply"), load_surface(gt_mesh))
    (run_dir / "geometry.json").write_text(json.dumps({"geometry": g.to_dict()}, indent=2))
    return [g.chamfer, g.chamfer_over_diagonal, g.fscore, g.normal_consistency]


def surface_columns(run_dir: Path, metrics: dict | None = None) -> list:
    """What a user opening mesh.ply sees: V/F, pieces, the largest piece's share of the faces, boundary and
    non-manifold edges, self-intersecting edges, mean valence (trisplat mesh-stats). With a far field, the connected
    surface's own statistics (metrics.json `mesh`): the far-field soup's shards are not pieces of it."""
    m = (metrics or {}).get("mesh") or {}
    if (metrics or {}).get("far_field_faces") and "vertex_face_ratio" in m:
        return [m["vertex_face_ratio"], m["connected_components"], 100 * m["largest_component_fraction"],
                m["boundary_edges"], m["non_manifold_edges"], m["self_intersecting_edges"], m["valence_mean"]]
    from trisplat.commands.mesh_stats import read_mesh
    from trisplat.mesh.stats import mesh_statistics

    v, f = read_mesh(run_dir / "mesh.ply")
    s = mesh_statistics(v, f)
    (run_dir / "mesh_stats.json").write_text(json.dumps(s.to_dict(), indent=2))
    return [s.vertex_face_ratio, s.connected_components, 100 * s.largest_component_fraction, s.boundary_edges,
            s.non_manifold_edges, s.self_intersecting_edges, s.valence_mean]


def main(argv: list[str]) -> int:
    args = tyro.cli(TrainBenchArgs, args=argv, description=TrainBenchArgs.__doc__, prog=PROG, config=CLI_STYLE)
    from trisplat.commands.train import make_train_args, run_training
    from trisplat.run import open_run

    geo = "spot" in args.scenes
    cols = [
        "scene",
        "preset",
        "budget min",
        "wall min",
        "steps",
        "faces",
        "vertices",
        "spp",
        "PSNR hard",
        "file PSNR",
        "SSIM",
        "LPIPS",
        "PSNR soft",
        "PSNR hard 1spp",
        "min opacity",
        "test PSNR @25/50/75% time",
        "V/F", "pieces", "largest %", "boundary edges", "non-manifold edges", "self-int. edges", "valence",
        "far-field faces", "coverage %", "health",
    ]
    if geo:
        cols += ["Chamfer", "Chamfer/diag", "F@1%", "normal consist."]
    from trisplat.render.device import device_name, resolve_device

    device = resolve_device(args.device)  # before any run starts
    table = BenchTable("train" if device.type == "cpu" else f"train_{device.type}", cols)
    for name in args.scenes:
        if name not in SCENES:
            raise ValueError(f"unknown bench scene {name!r}; choose from {sorted(SCENES)}")
        folder, opts = SCENES[name]
        data = bench_data(name, folder, args)
        for preset in args.presets:
            tag = "" if device.type == "cpu" else f"_{device.type}"
            tag += "" if args.output == "surface" else f"_{args.output}"
            run_dir = args.runs / f"{name}_{preset}_{args.minutes:g}min{tag}"
            targs = make_train_args(data, run_dir, preset, force=True, minutes=args.minutes, output=args.output,
                                    texture_size=args.texture_size, **opts)
            targs.device = device.type
            result = run_training(targs)
            m = result.metrics
            hist = open_run(run_dir).history()
            row = [
                name,
                preset,
                args.minutes,
                result.wall_s / 60,
                result.steps,
                m["faces"],
                m["vertices"],
                m.get("supersample", 1) ** 2,
                m.get("psnr"),
                m.get("file_psnr"),
                m.get("ssim"),
                m.get("lpips"),
                m.get("soft_psnr"),
                m.get("psnr_1spp", m.get("psnr") if m.get("supersample", 1) == 1 else None),
                m.get("min_vertex_opacity"),
                " ".join(_psnr_at_fractions(hist)),
                *surface_columns(run_dir, m),
                m.get("far_field_faces", 0),
                None if m.get("coverage") is None else 100 * m["coverage"],
                "ok" if (m.get("health") or {}).get("ok", True) else "; ".join(m["health"]["problems"]),
            ]
            if geo:
                row += geometry_columns(run_dir, data / "gt_mesh.ply") if name == "spot" else [None] * 4
            table.add(*row)
            print(json.dumps(m, indent=1))
    table.notes.append(
        "PSNR/SSIM/LPIPS (AlexNet v0.1) of the final opaque mesh rendered by the z-buffer (hard mode) on "
        "the test split with spp samples per pixel (anti-aliasing, the run's eval_supersample squared); soft = the "
        "splatting renderer at the final sigma, same samples; 1spp = the hard render with one sample at each pixel "
        "centre. file PSNR = mesh.glb read as the glTF specification defines it (unlit base colour texture, sRGB "
        "decoded and encoded as specified; `trisplat eval RUN --file mesh.glb`), same views and samples. "
        "Chamfer = mean of accuracy and completeness (DTU style) against the true surface, 200k area-uniform samples, seed 0."
    )
    table.notes.append(f"Training device: {device_name(device)} (renderer: "
                       f"{'the numba-cuda kernels' if device.type == 'cuda' else 'the Numba CPU kernels'}).")
    md = table.write(args.out, "trisplat bench train " + " ".join(argv))
    print(md.read_text())
    return 0
