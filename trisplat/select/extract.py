"""Object selection from 2D masks: per-face votes from the face each pixel shows, aggregated over views by a ratio.

For each masked view the mesh is rendered to a face-id map (the face a pixel shows). A face collects one "inside"
vote per masked pixel it is the dominant face of and one "outside" vote per unmasked pixel. A face is selected when
inside / (inside + outside) >= ratio and it was seen in at least `min_pixels` pixels. Faces that no masked view
shows (hidden, behind the object, outside every mask view) stay unselected unless `fill_hidden` is set, which then
adds every connected patch of unseen faces whose seen neighbours are mostly selected (e.g. the hidden underside
of an object).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from trisplat.cameras import Camera

RENDERERS = ("auto", "hard", "soft", "raycast")
SOFT_SIGMA = 1e-4  # window sharpness used for the soft renderer's face ids (the final, near-opaque value)


@dataclass(frozen=True)
class FaceVotes:
    """Pixel votes per face over all masked views. inside/outside: int64 [F] counts of masked / unmasked pixels
    at which the face is the dominant face. unmatched_mask_pixels: masked pixels that showed no face at all."""

    inside: np.ndarray
    outside: np.ndarray
    unmatched_mask_pixels: int = 0

    @property
    def seen(self) -> np.ndarray:
        return (self.inside + self.outside) > 0

    def ratio(self) -> np.ndarray:
        """inside / (inside + outside) per face, NaN for faces no masked view shows."""
        total = self.inside + self.outside
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(total > 0, self.inside / np.maximum(total, 1), np.nan)


def _check_mesh(positions, faces) -> tuple[np.ndarray, np.ndarray]:
    positions = np.asarray(positions.detach().cpu() if hasattr(positions, "detach") else positions, np.float64)
    faces = np.asarray(faces.detach().cpu() if hasattr(faces, "detach") else faces, np.int64)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must be [V,3], got {positions.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be [F,3], got {faces.shape}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(positions)):
        raise ValueError(f"faces index vertices outside [0, {len(positions)})")
    return positions, faces


def _resolve_renderer(renderer: str) -> str:
    if renderer not in RENDERERS:
        raise ValueError(f"renderer must be one of {RENDERERS}, got {renderer!r}")
    if renderer != "auto":
        return renderer
    try:
        from trisplat.render import rasterize_hard  # noqa: F401

        return "hard"
    except ImportError:
        return "raycast"


def face_id_maps(
    positions,
    faces,
    cameras: Sequence[Camera],
    renderer: str = "auto",
    opacities=None,
    sigma: float = SOFT_SIGMA,
) -> Iterator[np.ndarray]:
    """Per camera, int64 [H,W]: the face each pixel shows, -1 for none.

    renderer: 'hard' (trisplat.render.rasterize_hard, a z-buffer of the opaque mesh), 'soft' (trisplat.render.
    rasterize: the face at which the accumulated blending weight first passes 0.5, with `opacities` [V] (default
    all 1) and `sigma`), 'raycast' (embree through trimesh: the first face each pixel-centre ray hits), or 'auto'
    (hard when available, else raycast). All sample pixel centres at +0.5 (docs/conventions.md).
    """
    positions, faces = _check_mesh(positions, faces)
    kind = _resolve_renderer(renderer)
    if kind == "raycast":
        import trimesh

        from trisplat.synth.raycast import render_face_ids

        mesh = trimesh.Trimesh(positions, faces, process=False, validate=False)
        for cam in cameras:
            yield render_face_ids(mesh, [cam])[0]
        return
    import torch

    pos = torch.as_tensor(positions, dtype=torch.float32)
    fac = torch.as_tensor(faces, dtype=torch.int32)
    colors = torch.full_like(pos, 0.5)
    if kind == "hard":
        from trisplat.render import rasterize_hard

        for cam in cameras:
            out = rasterize_hard(
                pos,
                fac,
                colors,
                torch.as_tensor(cam.world_to_camera, dtype=torch.float32),
                torch.as_tensor(cam.K, dtype=torch.float32),
                cam.width,
                cam.height,
            )
            yield out.face_id.detach().cpu().numpy().astype(np.int64)
        return
    from trisplat.render import rasterize

    op = (
        torch.ones(len(pos))
        if opacities is None
        else torch.as_tensor(
            opacities.detach().cpu() if hasattr(opacities, "detach") else opacities, dtype=torch.float32
        )
    )
    with torch.no_grad():
        for cam in cameras:
            out = rasterize(
                pos,
                fac,
                colors,
                op,
                float(sigma),
                torch.as_tensor(cam.world_to_camera, dtype=torch.float32),
                torch.as_tensor(cam.K, dtype=torch.float32),
                cam.width,
                cam.height,
            )
            yield out.face_id.cpu().numpy().astype(np.int64)


def count_votes(face_ids: Sequence[np.ndarray], masks: Sequence[np.ndarray], num_faces: int) -> FaceVotes:
    """Accumulate FaceVotes from face-id maps int [H,W] (-1: no face) and boolean masks [H,W] of the same views."""
    if len(face_ids) != len(masks):
        raise ValueError(f"{len(face_ids)} face-id maps for {len(masks)} masks")
    inside = np.zeros(num_faces, np.int64)
    outside = np.zeros(num_faces, np.int64)
    unmatched = 0
    for i, (fid, m) in enumerate(zip(face_ids, masks)):
        fid = np.asarray(fid)
        m = np.asarray(m, dtype=bool)
        if fid.shape != m.shape:
            raise ValueError(
                f"view {i}: mask is {m.shape[1]}x{m.shape[0]} pixels but the render is {fid.shape[1]}x{fid.shape[0]}"
            )
        hit = fid >= 0
        if hit.any() and fid[hit].max() >= num_faces:
            raise ValueError(f"view {i}: face id {int(fid[hit].max())} out of range for {num_faces} faces")
        inside += np.bincount(fid[hit & m], minlength=num_faces)
        outside += np.bincount(fid[hit & ~m], minlength=num_faces)
        unmatched += int((m & ~hit).sum())
    return FaceVotes(inside=inside, outside=outside, unmatched_mask_pixels=unmatched)


def fill_hidden_faces(faces: np.ndarray, selected: np.ndarray, seen: np.ndarray, ratio: float = 0.5) -> np.ndarray:
    """Add to `selected` every edge-connected patch of unseen faces whose edges to seen faces lead mostly (share
    >= ratio) to selected faces. Faces sharing no edge with anything are left as they are. Returns a new [F] mask."""
    import scipy.sparse as sp
    import trimesh

    F = len(faces)
    out = selected.copy()
    if F == 0 or seen.all():
        return out
    adj = trimesh.graph.face_adjacency(faces=faces)  # [E,2] pairs of faces sharing an edge
    if len(adj) == 0:
        return out
    unseen = ~seen
    both = unseen[adj[:, 0]] & unseen[adj[:, 1]]
    pairs = adj[both]
    g = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(F, F))
    _, comp = sp.csgraph.connected_components(g, directed=False)
    # border edges: unseen face on one side, seen face on the other
    border = adj[unseen[adj[:, 0]] ^ unseen[adj[:, 1]]]
    u = np.where(unseen[border[:, 0]], border[:, 0], border[:, 1])
    s = np.where(unseen[border[:, 0]], border[:, 1], border[:, 0])
    n_comp = comp.max() + 1
    votes_sel = np.bincount(comp[u], weights=selected[s].astype(float), minlength=n_comp)
    votes_all = np.bincount(comp[u], minlength=n_comp)
    take = (votes_all > 0) & (votes_sel >= ratio * votes_all)
    out[unseen & take[comp]] = True
    return out


def extract_faces(
    positions,
    faces,
    cameras: Sequence[Camera],
    masks: dict[int, np.ndarray],
    ratio: float = 0.5,
    renderer: str = "auto",
    min_pixels: int = 1,
    fill_hidden: bool = False,
    opacities=None,
    sigma: float = SOFT_SIGMA,
    return_votes: bool = False,
):
    """Faces of the masked object: bool [F].

    positions [V,3] and faces [F,3] in the cameras' world frame; cameras: all cameras; masks: camera index ->
    bool [H,W] (True = object) for the views that have a mask, each exactly that camera's image size.
    ratio: selected when (masked pixels showing the face) / (all masked-view pixels showing it) >= ratio, in (0, 1].
    min_pixels: a face must be shown by at least this many pixels (over all masked views) to be selected.
    Faces no masked view shows stay unselected, unless fill_hidden (see fill_hidden_faces).
    renderer, opacities, sigma: how face ids are made (see face_id_maps). return_votes: also return the FaceVotes.
    """
    if not 0.0 < ratio <= 1.0:
        raise ValueError(f"ratio must be in (0, 1], got {ratio}")
    if min_pixels < 1:
        raise ValueError(f"min_pixels must be >= 1, got {min_pixels}")
    if not masks:
        raise ValueError("no masks given")
    positions, faces = _check_mesh(positions, faces)
    idx = sorted(masks)
    for i in idx:
        if not 0 <= i < len(cameras):
            raise ValueError(f"mask for camera index {i}, but there are {len(cameras)} cameras")
        cam, m = cameras[i], np.asarray(masks[i])
        if m.shape != (cam.height, cam.width):
            raise ValueError(
                f"mask for camera {i} ({cam.name or cam.image_path}) is {m.shape[1]}x{m.shape[0]} "
                f"pixels, its image is {cam.width}x{cam.height}"
            )
    views = [cameras[i] for i in idx]
    ids = list(face_id_maps(positions, faces, views, renderer, opacities=opacities, sigma=sigma))
    votes = count_votes(ids, [np.asarray(masks[i], bool) for i in idx], len(faces))
    total = votes.inside + votes.outside
    selected = (total >= min_pixels) & (votes.inside >= ratio * total) & (total > 0)
    if fill_hidden:
        selected = fill_hidden_faces(faces, selected, votes.seen, ratio)
    return (selected, votes) if return_votes else selected
