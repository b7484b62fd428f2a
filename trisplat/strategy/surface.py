"""The final surface pass of a connected run: drop degenerate and duplicate faces and small detached pieces, and
orient every piece consistently, each as the majority of its faces already faces (the fusion's surface faces the
free space the cameras looked through; the restricted Delaunay surface was turned towards the soup's normals: turning
pieces outward instead flipped bonsai's room, seen from inside, to face away from every camera). Never welds or moves
a vertex, so the render of what stays is unchanged; the trainer measures what the removed pieces cost in PSNR."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from trisplat.mesh.cleanup import CleanupConfig, clean_mesh, face_components
from trisplat.strategy import ops

MIN_PIECE_FRACTION = 0.01  # pieces with fewer faces than this share of the largest piece's are dropped


@dataclass(frozen=True)
class SurfacePassResult:
    faces_before: int
    faces_removed: int
    pieces_removed: int
    faces_flipped: int
    vertices_removed: int


def final_surface_pass(ts: ops.TrainableScene, min_piece_fraction: float = MIN_PIECE_FRACTION,
                       keep_last: int = 0) -> SurfacePassResult:
    """Clean the face table of `ts` in place (see the module docstring); vertex rows are kept unless orphaned.
    keep_last: the last rows of the face table (a far-field soup) are left as they are and stay the last rows."""
    pos = ts.params["positions"].detach().cpu().numpy().astype(np.float64)
    all_faces = ts.faces.detach().cpu().numpy()
    keep_last = int(min(max(keep_last, 0), len(all_faces)))
    faces, tail = all_faces[: len(all_faces) - keep_last], all_faces[len(all_faces) - keep_last:]
    F = len(faces)
    if F == 0:
        return SurfacePassResult(0, 0, 0, 0, 0)
    n, label = face_components(faces, len(pos))
    sizes = np.bincount(label, minlength=n)
    small = sizes < min_piece_fraction * sizes.max()
    kept = faces[~small[label]]
    res = clean_mesh(pos, kept, CleanupConfig(weld=False, min_face_area=0.0, drop_duplicate_faces=True, orient=True,
                                              orient_by="winding", drop_unreferenced_vertices=False))
    # weld=False and drop_unreferenced_vertices=False: the vertex table (and its indices) is unchanged
    assert len(res.vertex_source) == len(pos)
    ops.set_faces(ts, torch.as_tensor(np.concatenate([np.asarray(res.faces, np.int64).reshape(-1, 3),
                                                      tail.astype(np.int64)]), dtype=torch.int64))
    v_removed = ops.remove_orphan_vertices(ts)
    return SurfacePassResult(F, F - len(res.faces), int(small.sum()), int(res.num_flipped), v_removed)
