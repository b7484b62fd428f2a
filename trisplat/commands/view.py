"""`trisplat view RUN|MESH`: serve a local web viewer (mesh, cameras, ground-truth photos) and open it in a browser."""
from __future__ import annotations

import webbrowser
from dataclasses import dataclass
from pathlib import Path

import tyro

from trisplat.commands.style import CLI_STYLE
from trisplat.io.mesh_files import FORMATS


@dataclass
class ViewConfig:
    """Show a trained run (its mesh in the capture frame, the training cameras as frusta, the photos) or a mesh
    file (.ply/.obj/.glb) in the browser. A run shows its mesh.glb (else mesh.ply) loaded by three.js's glTF loader,
    as an engine shows it; `?testcam=K` in the address puts the view at test camera K exactly. Orbit or walk (WASD)
    around; N jumps to the nearest training camera and G toggles between the mesh and that camera's ground-truth
    photo. Ctrl-C stops the server."""

    target: tyro.conf.Positional[Path]
    """run folder written by `trisplat train`, or a mesh file"""
    port: int = 8080
    """port on 127.0.0.1 (0 picks a free one)"""
    no_browser: bool = False
    """only print the address; do not open a browser"""
    verbose: bool = False
    """log every HTTP request"""
    file: Path | None = None
    """the run's mesh to show (.glb/.ply/.obj, relative to the run folder; default mesh.glb, else mesh.ply)"""


def main(argv: list[str]) -> int:
    from trisplat.viewer.data import viewer_data_from_mesh, viewer_data_from_run
    from trisplat.viewer.server import ViewerServer

    cfg = tyro.cli(ViewConfig, args=argv, prog="trisplat view", description=__doc__, config=CLI_STYLE)
    if cfg.target.is_dir():
        data = viewer_data_from_run(cfg.target, cfg.file)
    elif cfg.target.suffix.lower() in FORMATS:
        data = viewer_data_from_mesh(cfg.target)
    else:
        raise FileNotFoundError(
            f"{cfg.target}: neither a run folder nor a mesh file ({', '.join(FORMATS)})"
        )
    try:
        server = ViewerServer(data, port=cfg.port, quiet=not cfg.verbose)
    except OSError as exc:
        raise ValueError(f"cannot listen on 127.0.0.1:{cfg.port} ({exc.strerror}); pick another --port") from exc
    shown = "the GLB as a glTF viewer loads it, " if data.glb is not None else ""
    print(f"trisplat view: {shown}{len(data.faces):,} faces, {len(data.cameras)} cameras at {server.url}  (Ctrl-C stops)")
    if not cfg.no_browser:
        webbrowser.open(server.url)
    try:
        server.serve_forever()
    finally:
        server.server_close()
    return 0
