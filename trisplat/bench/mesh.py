"""`trisplat bench mesh`: restricted Delaunay time (Qhull / dual edges / BVH / orientation) vs vertex count.

The scene imitates a trained soup: points sampled area-uniformly on a torus, each the centre of a small triangle in
the tangent plane with a random rotation; the triangles' corners are the vertex set and the triangles the soup, as in
`connect_scene`. Triangle size is `SOUP_SIZE_SPACINGS` times the mean point spacing, so neighbours overlap.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro

from trisplat.commands.style import CLI_STYLE
from trisplat.bench.common import BenchTable, peak_rss_mb

SOUP_SIZE_SPACINGS = 1.5  # soup triangle circumradius, in mean point spacings (dimensionless)
TORUS_RADII = (1.0, 0.35)  # major, minor radius (scene units)


@dataclass
class MeshBenchArgs:
    """Restricted Delaunay timing vs vertex count on a synthetic torus soup."""

    sizes: list[int] = field(default_factory=lambda: [100_000, 1_000_000])
    """vertex counts (3 per soup triangle)"""
    out: Path = Path("bench_results")
    """folder for mesh.json and mesh.md"""
    seed: int = 0


def torus_soup(num_vertices: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [3n,3] and soup faces [n,3] (n = num_vertices // 3): a small tangent triangle around each of n
    points sampled on a torus."""
    import trimesh

    n = max(num_vertices // 3, 2)
    R, r = TORUS_RADII
    torus = trimesh.creation.torus(R, r, major_sections=256, minor_sections=128)
    pts, face_idx = trimesh.sample.sample_surface(torus, n, seed=seed)
    normal = torus.face_normals[face_idx]
    rng = np.random.default_rng(seed)
    t1 = np.cross(normal, rng.normal(size=(n, 3)))
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normal, t1)
    spacing = np.sqrt(torus.area / n)
    s = SOUP_SIZE_SPACINGS * spacing
    c, si = np.cos(2 * np.pi / 3), np.sin(2 * np.pi / 3)
    corners = np.stack([pts + s * t1, pts + s * (c * t1 + si * t2), pts + s * (c * t1 - si * t2)], axis=1)
    return corners.reshape(-1, 3), np.arange(3 * n, dtype=np.int64).reshape(-1, 3)


def main(argv: list[str]) -> int:
    args = tyro.cli(MeshBenchArgs, args=argv, prog="trisplat bench mesh", description=__doc__, config=CLI_STYLE)
    from trisplat.mesh.restricted_delaunay import restricted_delaunay_report
    from trisplat.mesh.stats import mesh_statistics

    table = BenchTable("mesh", [
        "vertices", "soup faces", "tets", "dual edges", "qhull s", "qhull cpu s", "dual s", "bvh build s", "bvh test s",
        "orient s", "total s", "total cpu s", "faces kept", "V/F", "non-manifold %", "boundary %", "peak RSS MiB"])
    v, f = torus_soup(3000, args.seed)
    restricted_delaunay_report(v, v, f)  # compile the Numba kernels outside the timings
    for size in args.sizes:
        v, f = torus_soup(size, args.seed)
        t0, c0 = time.perf_counter(), time.process_time()
        faces, rep = restricted_delaunay_report(v, v, f)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        st = mesh_statistics(v, faces, check_self_intersections=False)
        used = len(v) - st.num_unreferenced_vertices
        row = [len(v), len(f), rep.num_tets, rep.num_interior_faces + rep.num_hull_faces, rep.qhull_s,
               rep.qhull_cpu_s, rep.dual_s, rep.bvh_build_s, rep.bvh_test_s, rep.orient_s, wall, cpu, len(faces),
               used / max(len(faces), 1), 100.0 * st.non_manifold_edge_fraction,
               100.0 * st.boundary_edges / max(st.num_edges, 1), peak_rss_mb()]
        table.add(*row)
        print(dict(zip(table.columns, row)), flush=True)
    table.notes.append("Times are wall seconds; 'cpu s' is process CPU time (all threads), which on a shared "
                       "machine shows how much of the wall time was waiting for a core.")
    table.notes.append("V/F counts only vertices used by a kept face. Scene: torus soup, "
                       f"{SOUP_SIZE_SPACINGS} spacings per soup triangle (see trisplat/bench/mesh.py).")
    md = table.write(args.out, "trisplat bench mesh " + " ".join(argv))
    print(md.read_text())
    return 0
