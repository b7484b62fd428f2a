"""`trisplat bench consumers`: does a real consumer show RUN/mesh.glb as trisplat's glTF spec renderer does?

For one test camera of a run, three pictures of the same file: trisplat.eval.spec_render (the reference), the
browser viewer (three.js GLTFLoader in headless Chromium, `?testcam=K`) and Blender (bpy: the glTF importer, Cycles
on the CPU, 'Standard' view transform, box pixel filter). PSNR of each consumer against the spec render.

Blender runs in its own interpreter: bpy 5.0 requires numpy < 2 while trisplat's environment has numpy 2, so bpy
lives in a separate virtual environment (`TRISPLAT_BPY_PYTHON`, default `.cache/bpy-venv/bin/python` of the
repository; `bash scripts/ci_extras.sh --blender` makes it). Without a run (`--run`), a tiny one is built: a
coloured sphere capture (trisplat.synth.blender), its model, and a textured mesh.glb fitted to its photos.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from trisplat.bench.common import BenchTable
from trisplat.commands.style import CLI_STYLE

VIEWER_BACKGROUND = (0x20 / 255, 0x24 / 255, 0x28 / 255)  # viewer.js BACKGROUND, sRGB
BPY_PYTHON_ENV = "TRISPLAT_BPY_PYTHON"
DEFAULT_BPY_PYTHON = Path(__file__).resolve().parents[2] / ".cache" / "bpy-venv" / "bin" / "python"


# ---- a tiny run ---------------------------------------------------------------------------------------------
def make_tiny_textured_run(root: str | Path, width: int = 400, height: int = 300, texture_size: int = 512,
                           n_train: int = 8, n_test: int = 2) -> Path:
    """A run folder as `trisplat train` leaves it (config, state, model.ply) plus a textured mesh.glb fitted to its
    training photos, around a ray-cast capture of a sphere with a colour gradient and stripes. Seconds."""
    import trimesh

    from trisplat.data import load_dataset
    from trisplat.io import export_run, save_model_ply
    from trisplat.scene.model import TriangleScene
    from trisplat.synth.blender import write_blender_scene

    root = Path(root)
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.6)
    v = mesh.vertices / 0.6
    stripes = 0.5 + 0.5 * np.sign(np.sin(9.0 * np.arctan2(v[:, 1], v[:, 0])))
    rgb = np.clip(np.c_[0.5 + 0.45 * v[:, 0], 0.25 + 0.6 * stripes, 0.5 - 0.45 * v[:, 2]], 0, 1)
    mesh.visual.vertex_colors = np.c_[np.round(rgb * 255), np.full(len(rgb), 255)].astype(np.uint8)
    capture = write_blender_scene(root / "capture", mesh, n_train=n_train, n_test=n_test, width=width, height=height,
                                  samples_per_pixel=2, n_points=0)
    data = load_dataset(capture, cache_dir=str(root / "cache"))
    N = np.asarray(data.normalization)
    verts = mesh.vertices @ N[:3, :3].T + N[:3, 3]
    scene = TriangleScene.from_rgb(verts.astype(np.float32), mesh.faces, (mesh.visual.vertex_colors[:, :3] / 255.0)
                                   .astype(np.float32), opacity=0.9999)
    run = root / "run"
    run.mkdir(parents=True, exist_ok=True)
    (run / "config.json").write_text(json.dumps({"data": str(capture), "data_options": {"cache_dir": str(root / "cache")},
                                                 "sigma_end": 1e-4, "steps": 1}))
    (run / "state.json").write_text(json.dumps({"finished": True, "step": 1, "total_steps": 1}))
    save_model_ply(run / "model.ply", scene, N)
    export_run(run, formats=("glb",), texture_size=texture_size)
    return run


# ---- the reference and the camera in the file's frame ---------------------------------------------------------
@dataclass
class ConsumerView:
    """One test camera of a run: OpenCV world_to_camera in the run's normalised frame and in the GLB's own frame
    (rigid, the file's units), intrinsics and size."""

    index: int
    w2c_normalized: np.ndarray
    w2c_file: np.ndarray
    K: np.ndarray
    width: int
    height: int
    background: tuple


def camera_view(run_dir: str | Path, k: int = 0, glb: str = "mesh.glb", shift_px: tuple[float, float] = (0.0, 0.0),
              data=None) -> ConsumerView:
    """Test camera k of the run; shift_px moves its principal point (pixels) to exercise off-centre projections."""
    from trisplat.eval.file_scores import file_to_normalized
    from trisplat.run import open_run

    run = open_run(run_dir)
    data = run.load_scene_data() if data is None else data
    cam = data.cameras[int(data.test_indices[k])]
    T = file_to_normalized(run, data, Path(run_dir) / glb)
    M = cam.world_to_camera @ T  # file -> camera, up to the normalisation's uniform scale
    scale = float(np.cbrt(np.linalg.det(M[:3, :3])))
    w2c_file = np.eye(4)
    w2c_file[:3] = M[:3] / scale
    K = cam.K.copy()
    K[0, 2] += shift_px[0]
    K[1, 2] += shift_px[1]
    return ConsumerView(int(data.test_indices[k]), cam.world_to_camera, w2c_file, K, cam.width, cam.height,
                    tuple(float(c) for c in data.background))


def spec_render(run_dir: str | Path, view: ConsumerView, background, supersample: int, glb: str = "mesh.glb",
                data=None) -> np.ndarray:
    """float32 [H,W,3] sRGB: trisplat's glTF specification render of the run's GLB from `view`."""
    from trisplat.eval.file_scores import file_to_normalized
    from trisplat.eval.spec_render import prepare_asset, render_asset
    from trisplat.io.gltf import read_glb
    from trisplat.run import open_run

    run = open_run(run_dir)
    data = run.load_scene_data() if data is None else data
    asset = prepare_asset(read_glb(Path(run_dir) / glb), file_to_normalized(run, data, Path(run_dir) / glb))
    return render_asset(asset, view.w2c_normalized, view.K, view.width, view.height, background, supersample,
                        float(run.config.get("near", 0.01)))


def psnr_u8(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two images in [0,1] (any dtype scaled to [0,1] first)."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


# ---- the browser viewer ------------------------------------------------------------------------------------
def viewer_render(run_dir: str | Path, k: int = 0, min_window: int = 400) -> tuple[np.ndarray, list[dict], str]:
    """(float32 [H,W,3] sRGB screenshot, page reports, Chromium stderr) of the viewer at test camera k. The window
    is the camera's image size times the smallest integer m that makes both sides >= min_window (headless Chromium
    has a minimum window size); for m > 1 each m x m block is averaged in linear light back to one pixel."""
    from trisplat.io.colour import linear_to_srgb, srgb_to_linear
    from trisplat.viewer.data import viewer_data_from_run
    from trisplat.viewer.headless import screenshot

    data = viewer_data_from_run(run_dir)
    cam = data.test_cameras[k]
    m = max(1, -(-min_window // min(cam.width, cam.height)))
    W, H = cam.width * m, cam.height * m
    image, reports, stderr = screenshot(data, f"clean=1&frusta=0&testcam={k}", (W, H))
    # the canvas when the page was ready, or after the window's last resize (headless windows may open small and
    # grow)
    sized = [r for r in reports if r.get("kind") in ("ready", "layout")]
    if not sized or sized[-1].get("canvas") != [W, H] or image.shape[:2] != (H, W):
        raise RuntimeError(f"the viewer's canvas is not the camera's {cam.width}x{cam.height} image times {m}: "
                           f"{sized}, screenshot {image.shape}; stderr: {stderr[-1500:]}")
    out = image.astype(np.float32) / 255.0
    if m > 1:
        out = linear_to_srgb(srgb_to_linear(out).reshape(cam.height, m, cam.width, m, 3).mean(axis=(1, 3)))
    return out.astype(np.float32), reports, stderr


# ---- Blender ------------------------------------------------------------------------------------------------
BLENDER_SCRIPT = r'''
import json, logging, sys, warnings
args = json.loads(open(sys.argv[1]).read())
records = []
class Keep(logging.Handler):
    def emit(self, r):
        if r.levelno >= logging.WARNING:
            records.append(f"{r.levelname}: {r.getMessage()}")
logging.getLogger().addHandler(Keep())
import bpy
import mathutils
bpy.ops.wm.read_factory_settings(use_empty=True)
import addon_utils
if not addon_utils.check("io_scene_gltf2")[1]:
    addon_utils.enable("io_scene_gltf2", default_set=True)
print("TRISPLAT_IMPORT_BEGIN", flush=True)
print("TRISPLAT_IMPORT_BEGIN", file=sys.stderr, flush=True)
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    result = bpy.ops.import_scene.gltf(filepath=args["glb"])
records += [f"python warning: {w.message}" for w in caught]
print("TRISPLAT_IMPORT_END", flush=True)
print("TRISPLAT_IMPORT_END", file=sys.stderr, flush=True)
import_records = list(records)
scene = bpy.context.scene
meshes = [o for o in scene.objects if o.type == "MESH"]
materials = sorted({s.material.name for o in meshes for s in o.material_slots if s.material})
nodes = sorted({n.bl_idname for o in meshes for s in o.material_slots if s.material and s.material.node_tree
                for n in s.material.node_tree.nodes})
W, H = args["width"], args["height"]
K = args["K"]
cam_data = bpy.data.cameras.new("trisplat_test_view")
size = max(W, H)
cam_data.sensor_fit = "HORIZONTAL" if W >= H else "VERTICAL"
cam_data.sensor_width = cam_data.sensor_height = 36.0
cam_data.lens = (K[0][0] if W >= H else K[1][1]) * 36.0 / size
cam_data.shift_x = (W / 2 - K[0][2]) / size   # OpenCV principal point -> Blender lens shift (units of the fit side)
cam_data.shift_y = (K[1][2] - H / 2) / size
cam_data.clip_start, cam_data.clip_end = args["clip"]
cam = bpy.data.objects.new("trisplat_test_view", cam_data)
scene.collection.objects.link(cam)
# glTF (Y-up) -> Blender (Z-up), as the importer converts: (x, y, z) -> (x, -z, y); OpenCV camera -> Blender camera
yup_to_zup = mathutils.Matrix(((1, 0, 0, 0), (0, 0, -1, 0), (0, 1, 0, 0), (0, 0, 0, 1)))
c2w_cv = mathutils.Matrix(args["c2w_file"])
cam.matrix_world = yup_to_zup @ c2w_cv @ mathutils.Matrix.Diagonal((1, -1, -1, 1))
scene.camera = cam
r = scene.render
r.engine = "CYCLES"
r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
r.pixel_aspect_x = r.pixel_aspect_y = 1.0
r.dither_intensity = 0.0
r.film_transparent = False
r.threads_mode, r.threads = "FIXED", args["threads"]
c = scene.cycles
c.device = "CPU"
c.samples = args["samples"]
c.use_adaptive_sampling = False
c.use_denoising = False
c.pixel_filter_type = "BOX"  # a box over the pixel: the average of the pixel's area, as the spec render's samples
c.filter_width = 1.0
c.seed = 0
c.max_bounces = 0
scene.view_settings.view_transform = "Standard"  # no AgX / Filmic tone mapping: linear -> sRGB only
scene.view_settings.look = "None"
scene.view_settings.exposure = 0.0
scene.view_settings.gamma = 1.0
scene.display_settings.display_device = "sRGB"
world = bpy.data.worlds.new("trisplat_background")
if world.node_tree is None:  # Blender < 5: worlds without nodes by default
    world.use_nodes = True
bg = world.node_tree.nodes["Background"]
bg.inputs["Color"].default_value = (*args["background_linear"], 1.0)
bg.inputs["Strength"].default_value = 1.0
scene.world = world
r.image_settings.file_format = "PNG"
r.image_settings.color_mode = "RGB"
r.image_settings.color_depth = "16"
r.filepath = args["out_png"]
bpy.ops.render.render(write_still=True)
json.dump({"result": sorted(result), "warnings": import_records, "other_warnings": records[len(import_records):],
           "meshes": len(meshes), "materials": materials,
           "shader_nodes": nodes, "blender": bpy.app.version_string}, open(args["out_json"], "w"))
'''


def bpy_python() -> Path | None:
    """The interpreter that has bpy: $TRISPLAT_BPY_PYTHON, else the repository's .cache/bpy-venv; None if absent."""
    p = Path(os.environ.get(BPY_PYTHON_ENV, DEFAULT_BPY_PYTHON))
    return p if p.is_file() else None


def blender_render(glb: str | Path, view: ConsumerView, background, samples: int = 64, threads: int = 1,
                   python: str | Path | None = None, timeout_s: float = 300.0) -> tuple[np.ndarray, dict]:
    """(float32 [H,W,3] sRGB, report) of `glb` imported into an empty Blender (factory settings) and rendered with
    Cycles on the CPU from `view`. report: importer result, `import_warnings` (see importer_warnings), meshes,
    materials, shader nodes, Blender version, `seconds`, `output` (the tail of Blender's stdout + stderr)."""
    from PIL import Image

    from trisplat.io.colour import srgb_to_linear

    python = Path(python) if python is not None else bpy_python()
    if python is None:
        raise FileNotFoundError(f"no Python with bpy: set {BPY_PYTHON_ENV} or run `bash scripts/ci_extras.sh --blender` "
                                f"(makes {DEFAULT_BPY_PYTHON})")
    c2w = np.linalg.inv(view.w2c_file)
    depth = float(np.linalg.norm(c2w[:3, 3]))
    with tempfile.TemporaryDirectory(prefix="trisplat-bpy-") as tmp:
        tmp = Path(tmp)
        args = {"glb": str(Path(glb).resolve()), "width": view.width, "height": view.height, "K": view.K.tolist(),
                "c2w_file": c2w.tolist(), "clip": [1e-3 * depth, 1e3 * depth], "samples": samples, "threads": threads,
                "background_linear": srgb_to_linear(np.asarray(background, np.float64)).tolist(),
                "out_png": str(tmp / "render.png"), "out_json": str(tmp / "report.json")}
        (tmp / "args.json").write_text(json.dumps(args))
        (tmp / "render.py").write_text(BLENDER_SCRIPT)
        proc = subprocess.run([str(python), str(tmp / "render.py"), str(tmp / "args.json")], capture_output=True,
                              text=True, timeout=timeout_s, cwd=tmp)
        output = proc.stdout + proc.stderr
        if proc.returncode != 0 or not (tmp / "render.png").is_file():
            raise RuntimeError(f"Blender failed (rc {proc.returncode}): {output[-3000:]}")
        report = json.loads((tmp / "report.json").read_text())
        report["import_warnings"] = importer_warnings(report, proc.stdout, proc.stderr)
        report["output"] = output[-3000:]
        image = np.asarray(Image.open(tmp / "render.png"))
    image = image.astype(np.float32) / (65535.0 if image.dtype == np.uint16 else 255.0)
    return image[..., :3], report


def importer_warnings(report: dict, stdout: str, stderr: str) -> list[str]:
    """What the glTF importer warned about while it ran: its logging records >= WARNING, Python warnings, and the
    lines it printed (stdout or stderr, between the script's import markers) that name a warning or an error."""
    lines = []
    for text in (stdout, stderr):
        inside = text.split("TRISPLAT_IMPORT_BEGIN", 1)[-1].split("TRISPLAT_IMPORT_END", 1)[0]
        lines += [ln.strip() for ln in inside.splitlines() if "warn" in ln.lower() or "error" in ln.lower()]
    return list(report.get("warnings", [])) + lines


# ---- the benchmark ------------------------------------------------------------------------------------------
@dataclass
class ConsumersArgs:
    """PSNR of the browser viewer's and Blender's pictures of a run's mesh.glb against the glTF spec render."""

    run: Path | None = None
    """a finished run with mesh.glb (default: build a tiny textured one in a temporary folder)"""
    view: int = 0
    """test camera index"""
    supersample: int = 4
    """spec render samples per pixel side"""
    samples: int = 64
    """Cycles samples per pixel"""
    shift: tuple[float, float] = (6.0, -4.0)
    """principal point offset (pixels) applied to the Blender and spec renders, to test the lens shift"""
    out: Path = Path("bench_results")
    """folder for consumers.json and consumers.md"""


def main(argv: list[str]) -> int:
    args = tyro.cli(ConsumersArgs, args=argv, prog="trisplat bench consumers", description=__doc__, config=CLI_STYLE)
    table = BenchTable("consumers", ["consumer", "what", "PSNR vs spec (dB)", "seconds", "notes"])
    with tempfile.TemporaryDirectory(prefix="trisplat-consumers-") as tmp:
        t0 = time.perf_counter()
        run = args.run if args.run is not None else make_tiny_textured_run(tmp)
        print(f"run: {run} ({'given' if args.run else f'built in {time.perf_counter() - t0:.1f} s'})")
        view = camera_view(run, args.view)
        ref_viewer = spec_render(run, view, VIEWER_BACKGROUND, args.supersample)
        try:
            t0 = time.perf_counter()
            shot, reports, _ = viewer_render(run, args.view)
            dt = time.perf_counter() - t0
            errors = [r for r in reports if r.get("kind") == "error"]
            p = psnr_u8(shot, ref_viewer)
            table.add("browser viewer", "three.js 0.187 GLTFLoader, headless Chromium (SwiftShader WebGL), MSAA",
                      round(p, 2), round(dt, 1), f"{len(errors)} page errors")
            print(f"viewer vs spec: {p:.2f} dB ({dt:.1f} s)")
        except (FileNotFoundError, RuntimeError) as exc:
            table.add("browser viewer", "three.js GLTFLoader, headless Chromium", None, None, f"not run: {exc}"[:200])
            print(f"viewer: not run: {exc}", file=sys.stderr)
        shifted = camera_view(run, args.view, shift_px=args.shift)
        ref = spec_render(run, shifted, shifted.background, args.supersample)
        try:
            t0 = time.perf_counter()
            img, report = blender_render(Path(run) / "mesh.glb", shifted, shifted.background, args.samples)
            dt = time.perf_counter() - t0
            warns = report["import_warnings"]
            p = psnr_u8(img, ref)
            table.add(f"Blender {report['blender']} (bpy)", f"glTF importer, Cycles CPU {args.samples} spp, box filter, "
                      "Standard view", round(p, 2), round(dt, 1),
                      f"{len(warns)} importer warnings; principal point shifted {args.shift} px")
            print(f"Blender vs spec: {p:.2f} dB ({dt:.1f} s); importer warnings: {warns}; nodes: {report['shader_nodes']}")
        except (FileNotFoundError, RuntimeError) as exc:
            table.add("Blender (bpy)", "glTF importer, Cycles CPU", None, None, f"not run: {exc}"[:200])
            print(f"Blender: not run: {exc}", file=sys.stderr)
    table.notes.append(f"test camera {args.view} ({view.width}x{view.height}); the reference is "
                       f"trisplat.eval.spec_render at {args.supersample}x{args.supersample} samples per pixel")
    md = table.write(args.out, "trisplat bench consumers " + " ".join(argv))
    print(md.read_text())
    return 0
