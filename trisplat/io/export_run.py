"""Export a trained run: plain-colour meshes (ply/obj/glb) and the full model PLY, in the capture's frame."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from trisplat.io.axes import capture_up as capture_up_of
from trisplat.io.mesh_files import FORMATS, export_mesh, resolve_up
from trisplat.io.model_ply import save_model_ply

MODEL_FORMAT = "model"  # the full model PLY (every SH band, opacity): `model.ply`
MESH_STEM = "mesh"
EXPORT_FORMATS = tuple(s.lstrip(".") for s in FORMATS) + (MODEL_FORMAT,)


def export_targets(out_dir: Path, formats: Sequence[str]) -> list[Path]:
    """The files `export_run` writes into `out_dir` for `formats` (an OBJ brings its MTL)."""
    out: list[Path] = []
    for f in formats:
        if f not in EXPORT_FORMATS:
            raise ValueError(f"unknown export format {f!r}; choose from {', '.join(EXPORT_FORMATS)}")
        if f == MODEL_FORMAT:
            out.append(out_dir / "model.ply")
        else:
            out.append(out_dir / f"{MESH_STEM}.{f}")
            if f == "obj":
                out.append(out_dir / f"{MESH_STEM}.mtl")  # and mesh.png when textured
    return out


def export_run(
    run_dir: str | Path,
    formats: Sequence[str] = ("ply", "obj", "glb"),
    up: str | None = "auto",
    out_dir: str | Path | None = None,
    faces: int | None = None,
    texture_size: int = 0,
    fit_colours: bool = True,
) -> list[Path]:
    """Write the run's model as `mesh.<fmt>` (base colour = SH DC term) and/or `model.ply` into `out_dir`
    (default: the run folder; existing files are replaced). Meshes land in the capture frame (the inverse of the
    scene normalisation); `up='y'|'z'` rotates the meshes so the capture's up direction, estimated from the
    training cameras (see trisplat.io.axes), becomes +Y / +Z; 'auto' does so (+Y) for GLB only, None for none.
    The model PLY is never rotated (SH would change). faces: decimate the meshes to about this many faces
    (level of detail; the model PLY keeps every face). texture_size > 0: fit a base-colour texture of that side to
    the run's training photos (trisplat.texture) for OBJ (map_Kd + PNG) and GLB (baseColorTexture). fit_colours:
    the meshes' vertex colours are fitted to the training photos as a glTF viewer shows them
    (trisplat.texture.vertex_colours; kept unless band 0 beats them by over 1 dB on held-out views); without the
    photos the meshes keep band 0, with a warning. Returns the files written.
    """
    from trisplat.run import open_run

    run = open_run(run_dir)
    out = Path(run_dir) if out_dir is None else Path(out_dir)
    export_targets(out, formats)  # validates the format names before any work
    out.mkdir(parents=True, exist_ok=True)
    scene, normalization = run.load_model()
    capture_up, data = None, None
    meshes = any(f != MODEL_FORMAT for f in formats)
    if meshes and texture_size:
        data = run.load_scene_data()  # texturing needs the photos: no fallback
    elif meshes and fit_colours:
        try:
            data = run.load_scene_data()
        except (FileNotFoundError, ValueError) as exc:
            warnings.warn(f"{run_dir}: cannot read the capture's photos ({exc}); the meshes keep the model's band-0 "
                          "colours instead of colours fitted to the photos", stacklevel=2)
            fit_colours = False
    if any(f != MODEL_FORMAT and resolve_up(up, f"x.{f}") is not None for f in formats):
        try:
            capture_up = capture_up_of(data or run.load_scene_data())
        except (FileNotFoundError, ValueError) as exc:
            warnings.warn(
                f"{run_dir}: cannot read the capture's cameras ({exc}); assuming the default up axis", stacklevel=2
            )
        if capture_up is None:
            warnings.warn(
                f"{run_dir}: the cameras do not agree on an up direction; assuming the default up axis", stacklevel=2
            )
    inverse = np.linalg.inv(np.asarray(normalization, dtype=np.float64))
    texture = None
    if meshes and (faces is not None or texture_size or fit_colours):
        from trisplat.texture.asset import build_asset

        asset = build_asset(scene, data, texture_size=int(texture_size), faces=faces,
                            supersample=int(run.config.get("eval_supersample", 2)),
                            near=float(run.config.get("near", 0.01)), fit_colours=fit_colours)
        positions, fc, colors, texture = asset.positions, asset.faces, asset.colors, asset.texture
        from trisplat.texture.asset import choice_message

        if (msg := choice_message(asset.texture_report)) is not None:
            import sys

            print(msg, file=sys.stderr, flush=True)
    elif meshes:
        positions = scene.positions.detach().cpu().numpy()
        fc = scene.faces.detach().cpu().numpy()
        colors = scene.base_colors().detach().cpu().clamp(0.0, 1.0).numpy()
    written: list[Path] = []
    for f in formats:
        if f == MODEL_FORMAT:
            written.append(save_model_ply(out / "model.ply", scene, normalization))
        else:
            written += export_mesh(out / f"{MESH_STEM}.{f}", positions, fc, colors, up=up, transform=inverse,
                                   capture_up=capture_up, texture=texture)
    return written
