"""The Python API for notebooks and scripts: train a capture, read a run back, render it, load its mesh, export it, SLAM.

    import trisplat.api as ts
    run = ts.train("path/to/capture", "runs/scene", minutes=10)   # -> TrainedRun (what `trisplat train` runs)
    image = run.render(0)                                         # test view 0: float32 [H,W,3] in [0,1]
    mesh = run.mesh()                                             # trimesh.Trimesh, the capture's frame and units
    run.export("exported/")                                       # mesh.ply / .obj / .glb
    room = ts.slam("path/to/rgbd", "runs/room")                   # -> SlamRun (what `trisplat slam` runs)

The `trisplat train`, `trisplat slam` and `trisplat export` commands call `train_from_args`, `slam_from_args` and
`export`, so a notebook and the command line run the same code. (The functions live in `trisplat.api`, not at the top
of the package: `trisplat.train` and `trisplat.slam` are the subpackages that do the work.)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:  # imported where used: `import trisplat.api` stays cheap
    import trimesh

    from trisplat.cameras import Camera
    from trisplat.commands.slam import SlamArgs
    from trisplat.commands.train import TrainArgs
    from trisplat.data.types import SceneData
    from trisplat.scene.model import TriangleScene

RenderMode = Literal["hard", "soft", "file", "shaded"]
"""hard: the opaque mesh (z-buffer, the model's view-dependent colour; what `psnr` scores); soft: the training
renderer at the run's final sigma; file: RUN/mesh.glb as a glTF viewer shows it (what `file_psnr` scores); shaded:
the bare geometry, grey and lit by a light at the camera (trisplat.eval.views.render_shaded)."""


def _read_metrics(path: Path) -> dict:
    import json

    from trisplat import run as layout

    p = Path(path) / layout.METRICS
    return json.loads(p.read_text()) if p.is_file() else {}


@dataclass
class TrainedRun:
    """A run folder written by `trisplat train` (or `train`), read back: its scores, renders, mesh and exports.
    Cameras, photos and renders are in the run's normalised frame (docs/conventions.md); meshes and exports in the
    capture's own frame and units."""

    path: Path
    metrics: dict = field(default_factory=dict)
    """RUN/metrics.json ({} while the run has not finished)"""
    wall_s: float | None = None
    """seconds the training took in this call (None for a run opened from disk: metrics['wall_s'] has it)"""
    _data: SceneData | None = field(default=None, init=False, repr=False)
    _model: TriangleScene | None = field(default=None, init=False, repr=False)
    _asset: object = field(default=None, init=False, repr=False)

    @property
    def psnr(self) -> float | None:
        """Test PSNR (dB) of the model, rendered opaque (`render(mode='hard')`)."""
        return self.metrics.get("psnr")

    @property
    def file_psnr(self) -> float | None:
        """Test PSNR (dB) of RUN/mesh.glb as a glTF viewer shows it (`render(mode='file')`)."""
        return self.metrics.get("file_psnr")

    @property
    def faces(self) -> int | None:
        return self.metrics.get("faces")

    def data(self) -> SceneData:
        """The capture, loaded as the run trained on it (cached)."""
        if self._data is None:
            from trisplat.run import open_run

            self._data = open_run(self.path).load_scene_data()
        return self._data

    def model(self) -> TriangleScene:
        """The trained triangles (normalised frame; model.ply, or the last checkpoint of an unfinished run)."""
        if self._model is None:
            from trisplat.run import open_run

            self._model = open_run(self.path).load_model()[0]
        return self._model

    def cameras(self, split: Literal["test", "train", "all"] = "test") -> list[Camera]:
        data = self.data()
        idx = {"test": data.test_indices, "train": data.train_indices, "all": range(len(data.cameras))}[split]
        return [data.cameras[int(i)] for i in idx]

    def _camera(self, view: int | Camera, split: str) -> Camera:
        if isinstance(view, (int, np.integer)):
            cams = self.cameras(split)  # type: ignore[arg-type]
            if not -len(cams) <= int(view) < len(cams):
                raise IndexError(f"{self.path}: view {view} of the {split} split, which has {len(cams)} views")
            return cams[int(view)]
        return view

    def photo(self, view: int = 0, split: Literal["test", "train", "all"] = "test") -> np.ndarray:
        """The photo of a view of `split` (float32 [H,W,3], composited over the run's background)."""
        data = self.data()
        idx = {"test": data.test_indices, "train": data.train_indices, "all": range(len(data.cameras))}[split]
        return np.asarray(data.load_image(int(list(idx)[view])), dtype=np.float32)

    def render(self, view: int | Camera = 0, split: Literal["test", "train", "all"] = "test",
               mode: RenderMode = "hard", supersample: int | None = None, background=None) -> np.ndarray:
        """float32 [H,W,3] in [0,1]: view `view` of `split` (an index) or any Camera in the normalised frame.
        supersample: samples per pixel side (default: the run's eval_supersample, as its scores); background: an RGB
        triple (default: the run's)."""
        from trisplat.eval.views import eval_supersample, render_shaded, render_view, soft_sigma
        from trisplat.run import open_run

        run = open_run(self.path)
        cam = self._camera(view, split)
        ss = eval_supersample(run) if supersample is None else int(supersample)
        bg = self.data().background if background is None else background
        near = float(run.config.get("near", 0.01))
        if mode == "shaded":
            return render_shaded(self.model(), cam, bg, near=near, supersample=ss)
        if mode == "file":
            from trisplat.eval.spec_render import render_asset

            return render_asset(self._file_asset(), cam.world_to_camera, cam.K, cam.width, cam.height, bg, ss, near)
        if mode not in ("hard", "soft"):
            raise ValueError(f"mode must be one of hard, soft, file, shaded; got {mode!r}")
        sigma = soft_sigma(run) if mode == "soft" else None
        return render_view(self.model(), cam, mode, bg, sigma, options={"near": near}, supersample=ss)

    def _file_asset(self):
        if self._asset is None:
            from trisplat.eval.file_scores import file_to_normalized
            from trisplat.eval.spec_render import prepare_asset
            from trisplat.io.gltf import read_glb
            from trisplat.run import open_run

            glb = self.path / "mesh.glb"
            if not glb.is_file():
                raise FileNotFoundError(f"{glb}: no such file (a run writes it when it finishes)")
            self._asset = prepare_asset(read_glb(glb), file_to_normalized(open_run(self.path), self.data(), glb))
        return self._asset

    def mesh(self, name: str = "mesh.ply") -> trimesh.Trimesh:
        """A mesh file of the run as a trimesh.Trimesh (mesh.ply: per-vertex sRGB colours, the capture's frame)."""
        import trimesh

        path = self.path / name
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file")
        return trimesh.load(path, process=False, force="mesh")

    def export(self, out: str | Path, formats=("ply", "obj", "glb"), up: str | None = "auto", faces: int | None = None,
               texture_size: int = 0, fit_colours: bool = True, force: bool = False) -> list[Path]:
        """Write the run's mesh into `out` (as `trisplat export RUN --out OUT`); see `export`."""
        return export(self.path, out, formats=formats, up=up, faces=faces, texture_size=texture_size,
                      fit_colours=fit_colours, force=force)


def load_run(path: str | Path) -> TrainedRun:
    """A run folder written by `trisplat train`, finished or not (its config.json must exist)."""
    from trisplat.run import open_run

    run = open_run(path)  # raises, naming the folder, when it is no run
    return TrainedRun(path=run.path, metrics=_read_metrics(run.path))


def train(data: str | Path, out: str | Path, *, minutes: float | None = None, preset: str = "default",
          steps: int | None = None, resume: bool = False, force: bool = False, quiet: bool = False,
          device: Literal["cpu", "cuda", "auto"] = "cpu", **config) -> TrainedRun:
    """Train a capture into the run folder `out`, as `trisplat train DATA --out OUT ...` does: a folder of photos
    (or a video) without poses is posed first, `minutes` without `downscale` picks the training resolution, and
    every field of trisplat.train.config.TrainConfig can be given (`output="soup"`, `texture_size=0`, ...; None
    values keep the preset's). Returns the finished run."""
    from trisplat.commands.train import make_train_args

    given = {"minutes": minutes, "steps": steps, **config}
    args = make_train_args(data, out, preset, resume=resume, force=force, quiet=quiet, **given)
    args.device = device
    return train_from_args(args, {k for k, v in given.items() if v is not None})


def train_from_args(args: TrainArgs, explicit: set[str]) -> TrainedRun:
    """The path `trisplat train` and `train` share: cheap checks first, photos posed, the resolution chosen,
    then trisplat.commands.train.run_training. `explicit`: the configuration fields the user set."""
    from trisplat.commands.train import check_cheap_options, choose_downscale, pose_plain_photos, run_training

    check_cheap_options(args)  # a typo costs nothing, not minutes of structure from motion
    args = pose_plain_photos(args)
    args = choose_downscale(args, explicit)
    result = run_training(args, explicit)
    return TrainedRun(path=Path(result.run_dir), metrics=dict(result.metrics), wall_s=float(result.wall_s))


def export(run: str | Path, out: str | Path, formats=("ply", "obj", "glb"), up: str | None = "auto",
           faces: int | None = None, texture_size: int = 0, fit_colours: bool = True,
           force: bool = False) -> list[Path]:
    """Write a run's mesh as `mesh.<format>` (ply, obj, glb; `model`: the full model PLY) into `out`, in the capture's
    frame: what `trisplat export` writes (trisplat.io.export_run: up 'auto' = GLB Y-up, 'y'/'z' every format, None
    the capture's axes; faces: decimate to about N; texture_size > 0: a texture fitted to the photos). Existing files
    are refused (FileExistsError) unless `force`. Returns the files written."""
    from trisplat.io.atomic import refuse_to_overwrite
    from trisplat.io.export_run import export_run, export_targets

    if faces is not None and faces < 1:  # cheap checks before the model and the photos are loaded
        raise ValueError(f"--faces must be at least 1, got {faces}")
    if texture_size < 0:
        raise ValueError(f"--texture-size must be >= 0 (0: vertex colours only), got {texture_size}")
    formats = tuple(dict.fromkeys(formats))
    refuse_to_overwrite(export_targets(Path(out), formats), force)
    return export_run(run, formats=formats, up=up, out_dir=out, faces=faces, texture_size=texture_size,
                      fit_colours=fit_colours)


@dataclass
class SlamRun:
    """A run folder written by `trisplat slam` (or `slam`), read back."""

    path: Path
    metrics: dict = field(default_factory=dict)
    """RUN/metrics.json: ate (when the capture has reference poses), held_out, mesh, frames, ..."""

    @property
    def ate_rmse_m(self) -> float | None:
        """Absolute trajectory error (RMSE, metres) against the capture's reference poses, when it has them."""
        return (self.metrics.get("ate") or {}).get("rmse_m")

    def trajectory(self) -> np.ndarray:
        """Camera-to-world poses of the processed frames, float64 [N,4,4] (RUN/trajectory.txt; the first frame's
        camera frame, OpenCV axes, metres)."""
        from trisplat.slam.system import TRAJECTORY
        from trisplat.slam.trajectory import read_tum_trajectory

        return read_tum_trajectory(self.path / TRAJECTORY)[1]

    def mesh(self, name: str = "mesh.ply") -> trimesh.Trimesh:
        """The run's connected mesh (mesh.ply, per-vertex sRGB colours) as a trimesh.Trimesh."""
        import trimesh

        path = self.path / name
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file")
        return trimesh.load(path, process=False, force="mesh")


def load_slam_run(path: str | Path) -> SlamRun:
    """A run folder written by `trisplat slam`."""
    path = Path(path)
    if not (path / "config.json").is_file():
        raise FileNotFoundError(f"{path}: not a trisplat slam run (no config.json); make one with `trisplat slam`")
    return SlamRun(path=path, metrics=_read_metrics(path))


def slam(capture: str | Path, out: str | Path, *, depth_scale: float | None = None, resume: bool = False,
         force: bool = False, colour_registration: str = "auto", quiet: bool = False, **slam_config) -> SlamRun:
    """Track and map an RGB-D stream without poses into `out`, as `trisplat slam CAPTURE --out OUT` does.
    slam_config: fields of trisplat.slam.system.SlamConfig (`downscale=2`, `max_frames=100`, `texture_size=2048`,
    ...). Returns the finished run (trajectory, mesh, metrics)."""
    from trisplat.commands.slam import SlamArgs
    from trisplat.slam.system import SlamConfig

    args = SlamArgs(capture=Path(capture), out=Path(out), depth_scale=depth_scale, resume=resume, force=force,
                    colour_registration=colour_registration, slam=SlamConfig(**slam_config))
    return slam_from_args(args, log=_silent if quiet else print)


def _silent(*args, **kwargs) -> None:
    pass


def slam_from_args(args: SlamArgs, log=print) -> SlamRun:
    """The path `trisplat slam` and `slam` share: the run rules checked before the capture is read, the stream
    opened and its colour registered to depth, the kernels compiled (not counted in the frames/s), then
    trisplat.slam.system.run_slam. `log`: where the progress lines go (print's signature)."""
    import torch

    from trisplat.data.colour_registration import apply_colour_registration
    from trisplat.data.rgbd_stream import open_stream
    from trisplat.run import prepare_run_dir
    from trisplat.slam.system import CHECKPOINT, run_slam
    from trisplat.slam.warmup import warm_up

    prepare_run_dir(args.out, args.resume, args.force, checkpoint=CHECKPOINT)  # before reading the capture
    torch.set_num_threads(max(1, torch.get_num_threads()))
    stream = open_stream(args.capture, depth_scale=args.depth_scale)
    log(f"{stream.format} stream: {len(stream)} frames {stream.width}x{stream.height}, processing at "
        f"1/{args.slam.downscale}; reference poses: {'yes' if stream.has_reference else 'no'}", flush=True)
    for w in stream.warnings:
        log(f"warning: {w}", flush=True)
    log(apply_colour_registration(stream, args.colour_registration).describe(stream.K), flush=True)
    log("preparing the kernels (compiled once, then cached) ...", flush=True)
    compile_s = warm_up(args.slam, log=log)
    log(f"kernels ready in {compile_s:.1f} s (not counted in the run's frames/s)", flush=True)
    metrics = run_slam(stream, args.out, args.slam, resume=args.resume, log=log, force=args.force,
                       compile_s=compile_s)
    return SlamRun(path=Path(args.out), metrics=dict(metrics))
