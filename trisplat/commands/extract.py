"""`trisplat extract RUN --masks DIR`: cut an object out of a trained mesh with 2D masks of some views."""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT, flowing_help, help_description


@flowing_help
@dataclass
class ExtractArgs:
    """Cut an object out of a trained run's mesh: faces that are the dominant face of masked pixels, aggregated
    over the masked views, go to object.ply; the rest to remainder.ply (capture frame and units)."""

    run: tyro.conf.Positional[Path]
    """The run folder written by `trisplat train`."""
    masks: Path
    """Folder of binary mask PNGs (white = object), each named after the source image of a view (matched by file
    stem, e.g. r_12.png for train/r_12.png); any size with the image's aspect ratio."""
    ratio: float = 0.5
    """A face is the object's when at least this fraction of the masked-view pixels showing it are masked."""
    out: Annotated[Path | None, NO_DEFAULT_HINT] = None
    """Output folder (default: RUN/extract)."""
    min_pixels: int = 1
    """A face must be shown by at least this many pixels over the masked views to be selected."""
    fill_hidden: bool = False
    """Also take unseen faces enclosed by selected ones (e.g. an object's hidden underside). Off: faces that no
    masked view shows stay in the remainder."""
    renderer: Literal["auto", "hard", "soft", "raycast"] = "auto"
    """How pixels get their face: hard z-buffer (auto), soft splatting at the run's final sigma (the face where the
    accumulated weight passes 0.5), or embree ray casting."""
    train_views_only: bool = False
    """Match masks against the training views only. Without it masks match any view; a name shared by a training
    and a test view, as in Blender captures, means the training view."""
    mesh_format: Literal["ply", "obj", "glb"] = "ply"
    """File format of the output meshes object.* and remainder.* (a GLB is Y-up)."""
    force: bool = False
    """Replace an earlier extraction's files in the output folder."""


@dataclass(frozen=True)
class ExtractResult:
    """What an extraction did (also written as extract.json)."""

    masks: int
    faces: int
    object_faces: int
    remainder_faces: int
    faces_seen: int
    unmatched_mask_pixels: int
    object_path: str
    remainder_path: str


def extract_run(args: ExtractArgs) -> ExtractResult:
    """Run the extraction for `args` and write the two meshes and extract.json; returns the summary."""
    from trisplat.io import export_mesh
    from trisplat.io.atomic import atomic_write_text, refuse_to_overwrite
    from trisplat.run import open_run
    from trisplat.select import extract_faces, match_masks, split_mesh
    from trisplat.select.extract import SOFT_SIGMA

    if not 0.0 < args.ratio <= 1.0:
        raise ValueError(f"--ratio must be in (0, 1], got {args.ratio}")
    run = open_run(args.run)
    out = args.out if args.out is not None else args.run / "extract"
    obj_path, rest_path = out / f"object.{args.mesh_format}", out / f"remainder.{args.mesh_format}"
    mtl = [out / "object.mtl", out / "remainder.mtl"] if args.mesh_format == "obj" else []
    refuse_to_overwrite([obj_path, rest_path, out / "extract.json", *mtl], args.force, "choose another --out")
    scene, normalization = run.load_model()
    data = run.load_scene_data()
    candidates = data.train_indices if args.train_views_only else None
    masks = match_masks(args.masks, data.cameras, candidates, preferred=data.train_indices)
    opacities, sigma = None, SOFT_SIGMA
    if args.renderer == "soft":
        from trisplat.eval.views import soft_sigma

        opacities, sigma = scene.opacities().detach(), soft_sigma(run)
    positions = scene.positions.detach().cpu().numpy()
    faces = scene.faces.detach().cpu().numpy()
    selected, votes = extract_faces(positions, faces, data.cameras, masks, ratio=args.ratio, renderer=args.renderer,
                                    min_pixels=args.min_pixels, fill_hidden=args.fill_hidden, opacities=opacities,
                                    sigma=sigma, return_votes=True)
    if not selected.any():
        raise ValueError(f"no face reached the mask ratio {args.ratio} in {len(masks)} masked view(s) of {args.masks}; "
                         "check that the masks show the object in white and belong to these views")
    colors = scene.base_colors().detach().cpu().numpy().clip(0.0, 1.0)
    obj, rest = split_mesh(positions, faces, colors, selected)
    out.mkdir(parents=True, exist_ok=True)
    to_capture = np.linalg.inv(np.asarray(normalization, dtype=np.float64))
    from trisplat.io import capture_up

    up = capture_up(data)  # a GLB is turned Y-up (glTF's up); other formats keep the capture's axes
    export_mesh(obj_path, obj.positions, obj.faces, obj.colors, transform=to_capture, capture_up=up)
    if len(rest.faces):
        export_mesh(rest_path, rest.positions, rest.faces, rest.colors, transform=to_capture, capture_up=up)
    result = ExtractResult(masks=len(masks), faces=len(faces), object_faces=len(obj.faces),
                           remainder_faces=len(rest.faces), faces_seen=int(votes.seen.sum()),
                           unmatched_mask_pixels=votes.unmatched_mask_pixels, object_path=str(obj_path),
                           remainder_path=str(rest_path) if len(rest.faces) else "")
    atomic_write_text(out / "extract.json", json.dumps({"args": {k: str(v) for k, v in asdict(args).items()},
                                                  **asdict(result)}, indent=2))
    return result


def main(argv: list[str]) -> int:
    args = tyro.cli(ExtractArgs, args=argv, prog="trisplat extract", description=help_description(ExtractArgs.__doc__),
                    config=CLI_STYLE)
    r = extract_run(args)
    print(f"{r.masks} masked views; {r.faces_seen} of {r.faces} faces seen in them; "
          f"object: {r.object_faces} faces -> {r.object_path}; remainder: {r.remainder_faces} faces"
          + (f" -> {r.remainder_path}" if r.remainder_path else ""))
    if r.unmatched_mask_pixels:
        print(f"note: {r.unmatched_mask_pixels} masked pixels showed no face (mask larger than the mesh there)")
    return 0
