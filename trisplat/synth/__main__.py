"""`python -m trisplat.synth SCENE OUT`: write a synthetic Blender-format capture (demo, two-objects or Spot)."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro


@dataclass
class SynthArgs:
    """Render a known mesh from orbit cameras with the independent ray caster and write a NeRF-synthetic folder
    (transforms_*.json, RGBA PNGs, gt_mesh.ply, points3d.ply, synth.json) that `trisplat train` reads."""

    scene: tyro.conf.Positional[Literal["demo", "two-objects", "spot"]]
    out: tyro.conf.Positional[Path]
    spot_path: Path | None = None
    """spot_triangulated.obj (the texture spot_texture.png is looked up beside it); needed for scene 'spot'."""
    train: int = 64
    test: int = 16
    size: int = 160
    """Image width and height, pixels."""
    fov_deg: float = 40.0
    """Horizontal field of view, degrees."""
    samples: int = 2
    """Antialiasing: samples x samples rays per pixel."""
    lit: bool = True
    """Spot / two-objects: bake the fixed demo light into the render (view independent); the demo mesh carries
    its light in its vertex colours already."""
    seed: int = 0


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(SynthArgs, args=sys.argv[1:] if argv is None else argv, description=SynthArgs.__doc__)
    from trisplat.synth import DEMO_SHADING, demo_mesh, spot_mesh, two_object_mesh, write_blender_scene

    shading = None
    if args.scene == "demo":
        mesh = demo_mesh(args.seed)
    elif args.scene == "two-objects":
        mesh, _ = two_object_mesh()
        shading = DEMO_SHADING if args.lit else None
    else:
        if args.spot_path is None:
            raise SystemExit("scene 'spot' needs --spot-path PATH/spot_triangulated.obj")
        mesh = spot_mesh(args.spot_path)
        shading = DEMO_SHADING if args.lit else None
    out = write_blender_scene(args.out, mesh, n_train=args.train, n_test=args.test, width=args.size,
                              height=args.size, fov_deg=args.fov_deg, samples_per_pixel=args.samples,
                              shading=shading, seed=args.seed, progress=True)
    print(f"wrote {args.scene} ({args.train} train + {args.test} test views, {args.size}x{args.size}) to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
