"""`trisplat export RUN`: write a trained run as PLY / OBJ (+MTL) / GLB meshes and the full model PLY."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT, flowing_help
from trisplat.io.export_run import EXPORT_FORMATS, export_targets

EXPORT_SUBDIR = "export"


@flowing_help
@dataclass
class ExportConfig:
    """Export a run's mesh in the capture's own frame and units (the inverse of the scene normalisation).

    Meshes carry a view-independent colour per vertex, fitted to the photos (or SH band 0), and with --texture-size
    a texture fitted to the photos; `model` is the full model PLY with every SH
    coefficient and the opacity, which reloads losslessly."""

    run: tyro.conf.Positional[Path]
    """run folder written by `trisplat train`"""
    formats: tuple[Literal["ply", "obj", "glb", "model"], ...] = ("ply", "obj", "glb")
    """formats to write: ply (binary, per-vertex RGB), obj (+ mtl), glb (glTF 2.0, COLOR_0), model (SH PLY)"""
    up: Literal["auto", "y", "z", "capture"] = "auto"
    """rotate meshes so the capture's up (+Z for Blender captures, else estimated from the cameras) becomes +Y
    (glTF, Unity) or +Z (Blender, MuJoCo); capture: keep the capture's own axes in every format; auto: GLB Y-up
    (glTF defines +Y as up), PLY and OBJ in the capture's axes"""
    out: Annotated[Path | None, NO_DEFAULT_HINT] = None
    """output folder (default: RUN/export)"""
    force: bool = False
    """replace files that already exist in the output folder"""
    faces: Annotated[int | None, NO_DEFAULT_HINT] = None
    """decimate the meshes to about N faces (level of detail; quadric edge collapse), then texture them"""
    texture_size: int = 0
    """side of a base-colour texture fitted to the run's training photos (OBJ map_Kd + PNG, GLB baseColorTexture);
    0: vertex colours only. Score the result with `trisplat eval RUN --file OUT/mesh.glb`"""
    fit_colours: bool = True
    """fit the meshes' vertex colours to the run's training photos as a glTF viewer shows them (kept unless the
    model's band-0 colours beat them by more than 1 dB on held-out photos); --no-fit-colours: band 0 as it is"""


def main(argv: list[str]) -> int:
    cfg = tyro.cli(ExportConfig, args=argv, prog="trisplat export", description=__doc__, config=CLI_STYLE)
    if cfg.faces is not None and cfg.faces < 1:  # cheap checks before the model and the photos are loaded
        raise ValueError(f"--faces must be at least 1, got {cfg.faces}")
    if cfg.texture_size < 0:
        raise ValueError(f"--texture-size must be >= 0 (0: vertex colours only), got {cfg.texture_size}")
    out = cfg.run / EXPORT_SUBDIR if cfg.out is None else cfg.out
    formats = tuple(dict.fromkeys(cfg.formats))
    assert set(formats) <= set(EXPORT_FORMATS)
    existing = [p for p in export_targets(out, formats) if p.exists()]
    if existing and not cfg.force:
        names = ", ".join(str(p) for p in existing)
        print(f"trisplat export: error: would overwrite {names}; pass --force to replace them", file=sys.stderr)
        return 1
    up = None if cfg.up == "capture" else cfg.up
    from trisplat.api import export

    for path in export(cfg.run, out, formats=formats, up=up, faces=cfg.faces, texture_size=cfg.texture_size,
                       fit_colours=cfg.fit_colours, force=True):  # the path of trisplat.api.export (checked above)
        print(path)
    return 0
