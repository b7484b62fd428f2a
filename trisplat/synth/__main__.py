"""`python -m trisplat.synth SCENE OUT`: write a synthetic Blender-format capture (demo, two-objects or Spot);
`python -m trisplat.synth rgbd-room OUT`: a hand-held RGB-D walk through a room with exact poses (7-Scenes layout)."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro


@dataclass
class SynthArgs:
    """Render a known mesh from orbit cameras with the independent ray caster and write a NeRF-synthetic folder
    (transforms_*.json, RGBA PNGs, gt_mesh.ply, points3d.ply, synth.json) that `trisplat train` reads.
    For an RGB-D sequence of a room with exact poses (what `trisplat slam` reads) see
    `python -m trisplat.synth rgbd-room --help`."""

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


@dataclass
class RGBDRoomArgs:
    """Ray-cast a hand-held RGB-D walk once around a furnished 5 x 5 m room (exact camera-to-world poses, Kinect-like
    depth noise and dropouts unless --no-sensor) and write it in the 7-Scenes layout (frame-NNNNNN.color.png,
    .depth.png in millimetres, .pose.txt; camera-intrinsics.txt; gt_mesh.ply) that `trisplat slam` and
    `trisplat bench slam --capture OUT` read. Scene, path, units and axes: trisplat/synth/rgbd_room.py."""

    out: tyro.conf.Positional[Path]
    """Folder to write (created; an older rgbd-room capture there is replaced)."""
    frames: int = 300
    """Frames along the closed walk (about 9 m; 300 frames: about 3 cm and 1.2 degrees a frame, 30 frames/s)."""
    width: int = 320
    height: int = 240
    fov_deg: float = 60.0
    """Horizontal field of view, degrees (a Kinect's depth camera: about 58)."""
    sensor: bool = True
    """Kinect-like sensor: depth noise 1.5 mm * z^2, missing beyond 4 m and at grazing angles, colour noise;
    --no-sensor: exact depth (to the millimetre) and colour."""
    color_samples: int = 2
    """Colour antialiasing: color_samples x color_samples rays per pixel (depth: the pixel-centre ray)."""
    workers: int = 0
    """Rendering processes (0: one per available core)."""
    seed: int = 0


def _rgbd_room(argv: list[str]) -> int:
    args = tyro.cli(RGBDRoomArgs, args=argv, prog="python -m trisplat.synth rgbd-room", description=RGBDRoomArgs.__doc__)
    from trisplat.synth.rgbd_room import default_workers, write_rgbd_room

    info = write_rgbd_room(args.out, n_frames=args.frames, width=args.width, height=args.height,
                           fov_deg=args.fov_deg, seed=args.seed, sensor=args.sensor, color_samples=args.color_samples,
                           workers=args.workers or default_workers(), progress=True)
    print(f"wrote rgbd-room ({info.n_frames} frames, {info.width}x{info.height}, "
          f"{'Kinect-like sensor' if info.sensor else 'exact depth'}; walk {info.path_length_m:.2f} m, "
          f"{100 * info.mean_step_m:.1f} cm and {info.mean_step_deg:.2f} deg a frame; "
          f"{100 * info.missing_depth_fraction:.1f}% depth missing) to {args.out} in {info.seconds:.0f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "rgbd-room":
        return _rgbd_room(argv[1:])
    args = tyro.cli(SynthArgs, args=argv, description=SynthArgs.__doc__)
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
