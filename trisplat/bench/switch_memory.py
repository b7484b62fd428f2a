"""`trisplat bench switch-memory`: peak memory of the stage-2 switch (soup -> one surface) on a large capture.

A synthetic COLMAP capture of VIEWS photos of WIDTH x HEIGHT pixels (default 300 x 4000x3000, a phone's 12 MP) is
written (one noise JPEG, hard-linked under every view's name: each is decoded again at its turn) and loaded with the
real data loader. The soup is the synthetic room (`trisplat.synth.room`: walls, floor, ceiling, objects; every pixel
covered, as in a real photo), in the capture's normalised frame, seen from a ring of cameras inside it. The render
is a cheap stand-in: the opaque z-buffer renderer (`trisplat.render.hard`) at 1/RENDER_STEP of the resolution, its
face ids repeated to full size (only the face ids are used). Everything after the render is the trainer's path
(`_connect_fusion` for photos without alpha): `soup_to_surface` in the inner box with the trainer's settings
(resolution capped by surface_resolution and max_voxels, unseen faces 'drop_enclosed', empty pixels unknown, the
photos' colours through the loader's `load_image`): surface depth at full resolution, hole filling, streamed
fusion, depth store, marching cubes, decimation, photo colours.

Reported: the process's peak resident set size before and after the switch (getrusage), the switch's own peak
above its start (psutil samples every 0.2 s), wall time per stage, the grid, and how many depth maps went to disk.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import tyro

from trisplat.bench.common import BenchTable, peak_rss_mb
from trisplat.commands.style import CLI_STYLE


@dataclass
class SwitchMemoryArgs:
    """Peak memory of the switch on a large synthetic capture."""

    views: int = 300
    """photos, all fused (the trainer would fuse its training views, 7 of every 8)"""
    width: int = 4000
    """photo width, pixels"""
    height: int = 3000
    """photo height, pixels"""
    surface_resolution: int = 512
    """the trainer's --surface-resolution (voxels along the fused box's longest side, before the voxel cap)"""
    capture: Path | None = None
    """where to write the synthetic capture (default: a temporary folder, removed at the end)"""
    out: Path = Path("bench_results")
    """folder for switch-memory.json and switch-memory.md"""


class _RssSampler:
    """Largest resident set size (MiB) of this process seen between start() and stop(), sampled every `period` s."""

    def __init__(self, period: float = 0.2):
        import psutil

        self._proc, self._period, self.peak = psutil.Process(), period, 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self._proc.memory_info().rss / 2**20)
            self._stop.wait(self._period)

    def start(self) -> _RssSampler:
        self._thread.start()
        return self

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return max(self.peak, self._proc.memory_info().rss / 2**20)


RENDER_STEP = 8  # the stand-in render's pixel step (face ids repeated to full size)


def write_capture(out: Path, views: int, width: int, height: int, seed: int = 0) -> list:
    """A COLMAP capture of `views` ring cameras inside the synthetic room (radius 1.6, height 1.1, fov 70
    degrees), all photos the same noise JPEG (hard links, or copies where links fail). Returns the room mesh."""
    from PIL import Image

    from trisplat.synth.room import ring_cameras, room_mesh, write_colmap_text

    (out / "images").mkdir(parents=True, exist_ok=True)
    cams = [replace(c, name=c.name.replace(".png", ".jpg"))  # a phone's photos: JPEG
            for c in ring_cameras(views, 1.6, 1.1, (0.0, 0.0, 0.3), width, height, 70.0, jitter=0.15, seed=seed)]
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(height // 16 + 1, width // 16 + 1, 3), dtype=np.uint8)
    photo = Image.fromarray(small).resize((width, height), Image.BILINEAR)
    first = out / "images" / cams[0].name
    photo.save(first, quality=90)
    for cam in cams[1:]:
        target = out / "images" / cam.name
        if not target.exists():
            try:
                os.link(first, target)
            except OSError:
                shutil.copyfile(first, target)
    mesh = room_mesh(seed=seed)
    pts = np.asarray(mesh.sample(3000, return_index=False))
    write_colmap_text(out, cams, pts, np.full((len(pts), 3), 0.5))
    return mesh


def main(argv: list[str]) -> int:
    args = tyro.cli(SwitchMemoryArgs, args=argv, prog="trisplat bench switch-memory", description=__doc__,
                    config=CLI_STYLE)
    import torch

    from trisplat.data import load_dataset
    from trisplat.data.normalize import apply_to_points
    from trisplat.render.hard import rasterize_hard
    from trisplat.scene.model import TriangleScene
    from trisplat.train.switch import SurfaceConfig, inner_box, soup_to_surface

    table = BenchTable("switch-memory", [
        "views", "photo", "grid", "voxels M", "depth maps on disk", "RSS before MiB", "switch peak MiB",
        "process peak MiB", "render s", "fuse s", "mesh s", "total s", "surface faces"])
    tmp = None
    capture = args.capture
    if capture is None:
        tmp = tempfile.TemporaryDirectory(prefix="trisplat-switch-memory-")
        capture = Path(tmp.name) / "capture"
    try:
        t0 = time.perf_counter()
        mesh = write_capture(capture, args.views, args.width, args.height)
        print(f"capture: {args.views} views of {args.width}x{args.height} in {capture} "
              f"({time.perf_counter() - t0:.1f} s)", flush=True)
        data = load_dataset(capture, downscale=1)
        pos = apply_to_points(data.normalization, np.asarray(mesh.vertices, np.float64))
        rgb = np.asarray(mesh.visual.vertex_colors, np.float32)[:, :3] / 255.0
        from trisplat.scene.sh import rgb_to_sh_dc

        soup = TriangleScene(torch.as_tensor(pos, dtype=torch.float32),
                             rgb_to_sh_dc(torch.as_tensor(rgb))[:, None, :].contiguous(),
                             torch.full((len(pos),), 4.0), torch.as_tensor(mesh.faces, dtype=torch.int32), 0.0)
        # every photo is fused (the trainer fuses its training views: 7 of every 8 photos of a capture without
        # splits), so VIEWS photos are VIEWS views through the switch
        train = list(range(len(data.cameras)))
        cams = list(data.cameras)
        step = RENDER_STEP

        class _Render:  # what soup_to_surface reads of a RenderOutput
            def __init__(self, face_id):
                self.face_id = face_id

        def render(n):
            c = cams[n]
            K = np.asarray(c.K, np.float64).copy()
            K[:2] /= step  # the same view at 1/step of the resolution (pixel centres: a sub-pixel offset)
            w, h = -(-c.width // step), -(-c.height // step)
            out = rasterize_hard(soup.positions, soup.faces, torch.as_tensor(rgb),
                                 torch.as_tensor(c.world_to_camera, dtype=torch.float32),
                                 torch.as_tensor(K, dtype=torch.float32), w, h)
            fid = out.face_id.numpy().repeat(step, 0).repeat(step, 1)[: c.height, : c.width]
            if n % 25 == 0:
                print(f"view {n}: RSS {sampler._proc.memory_info().rss / 2**20:.0f} MiB, peak {sampler.peak:.0f} MiB "
                      f"({time.perf_counter() - t0:.0f} s)", flush=True)
            return _Render(torch.from_numpy(np.ascontiguousarray(fid)))

        side = max(max(c.width, c.height) for c in cams)
        # the trainer's settings for a capture without alpha (trisplat/train/trainer.py, _connect_fusion)
        scfg = SurfaceConfig(resolution=int(min(args.surface_resolution, max(2 * side, 32))),
                             unseen_faces="drop_enclosed", empty_is_free=False)
        before = peak_rss_mb()
        sampler = _RssSampler().start()
        start_rss = sampler._proc.memory_info().rss / 2**20
        t0 = time.perf_counter()
        surface, rep = soup_to_surface(soup, cams, render, inner_box(), scfg,
                                       lambda m: print(f"switch: {m}", flush=True),
                                       images=lambda n: data.load_image(train[n]))
        total = time.perf_counter() - t0
        peak = sampler.stop()
        spilled = next((note.split(" ")[0] for note in rep.notes if "on disk" in note), "0")
        print(f"switch: {rep.summary()}", flush=True)
        table.add(len(cams), f"{args.width}x{args.height}", "x".join(map(str, rep.grid)),
                  round(float(np.prod(rep.grid)) / 1e6, 1), spilled, round(start_rss), round(peak),
                  round(peak_rss_mb()), round(rep.render_s, 1), round(rep.fuse_s, 1), round(rep.mesh_s, 1),
                  round(total, 1), surface.num_faces)
        table.notes.append(f"Process peak RSS before the switch (capture written, loader and soup ready): "
                           f"{before:.0f} MiB. Render: opaque z-buffer stand-in at 1/{step} resolution, face ids "
                           f"repeated; depth maps kept in memory up to "
                           f"{scfg.depth_memory_mb:.0f} MiB, the rest in TMPDIR. Notes: {'; '.join(rep.notes)}")
    finally:
        if tmp is not None:
            tmp.cleanup()
    path = table.write(args.out, "trisplat bench switch-memory " + " ".join(argv))
    print(table.markdown())
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))
