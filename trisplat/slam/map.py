"""The SLAM map: a triangle soup (TriangleScene, SH degree 0, metres, capture frame) with per-face spawn sizes;
spawning from back-projected depth where the map is thin, and pruning."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from trisplat.render.rasterize import rasterize
from trisplat.scene.init import init_soup
from trisplat.scene.model import TriangleScene
from trisplat.train.losses import depth_to_normal


@dataclass
class SpawnConfig:
    """Where and how new triangles are spawned on a keyframe."""

    stride: int = 3
    """pixel stride (at the mapping resolution) of the back-projected depth samples"""
    thin_alpha: float = 0.6
    """a pixel is thin where the rendered alpha is below this (unitless)"""
    front_margin: float = 0.05
    """or where observed depth is in front of the rendered surface by more than this (metres)..."""
    front_relative: float = 0.03
    """... plus this fraction of the depth (unitless)"""
    color_error: float = 0.12
    """or where the map is there (at the observed depth) but renders the photo's colour off by more than this (mean
    absolute RGB error in [0,1], box-filtered over the spawn stride): densify where the photometric error is high
    (0 = off)"""
    size_factor: float = 2.0
    """triangle circumradius / RMS distance to the 3 nearest new samples (unitless)"""
    opacity: float = 0.97
    """vertex opacity of new triangles"""
    max_depth: float = 6.0
    """samples farther than this (metres) are not spawned (noisy far depth)"""
    min_valid_neighbours: bool = True
    """require a valid depth normal (all four neighbours measured)"""
    fill_holes_px: int = 0
    """pixels without a depth measurement that the map leaves thin, within this many pixels of a measured one, get
    the nearest measured depth for spawning (things nearer than the sensor's range, dark or shiny surfaces): the map
    then covers them, at a guessed depth (0 = off). 7-Scenes at 24: held-out map / mesh.ply 20.5 -> 21.6 / 20.3 ->
    21.1 dB, Chamfer 1.90 -> 2.00 cm. Off by default: where no depth means nothing there (an object against empty
    space), it grows the object's outline by up to this many pixels of guessed surface"""


@dataclass
class PruneConfig:
    min_opacity: float = 0.05
    """triangles whose mean vertex opacity fell below this are removed"""
    max_growth: float = 4.0
    """triangles whose longest edge grew beyond this x their spawn edge are removed"""


@dataclass
class SlamMap:
    """scene: the soup (3 private vertices per face); spawn_edge float32 [F] edge length at spawn (metres);
    birth int64 [F] keyframe index at spawn."""

    scene: TriangleScene
    spawn_edge: torch.Tensor
    birth: torch.Tensor

    @staticmethod
    def empty() -> SlamMap:
        sc = TriangleScene.from_rgb(torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.int32), torch.zeros(0, 3), 0.5, 0)
        return SlamMap(sc, torch.zeros(0), torch.zeros(0, dtype=torch.int64))

    @property
    def num_faces(self) -> int:
        return self.scene.num_faces

    def colors(self) -> torch.Tensor:
        from trisplat.scene.sh import sh_dc_to_rgb

        return sh_dc_to_rgb(self.scene.sh[:, 0, :]).clamp(0.0, 1.0)

    def render(self, w2c: np.ndarray | torch.Tensor, K: np.ndarray, width: int, height: int, sigma: float, **opts):
        w2c = torch.as_tensor(w2c, dtype=torch.float64)
        return rasterize(self.scene.positions, self.scene.faces, self.colors(), self.scene.opacities(),
                         torch.tensor(float(sigma)), w2c, torch.as_tensor(K, dtype=torch.float64), width, height,
                         opacity_mode="mean", **opts)

    def append(self, other: TriangleScene, spawn_edge: torch.Tensor, birth: int) -> None:
        s = self.scene
        V = s.num_vertices
        self.scene = TriangleScene(
            positions=torch.cat([s.positions.detach(), other.positions]),
            sh=torch.cat([s.sh.detach(), other.sh]),
            opacity_logit=torch.cat([s.opacity_logit.detach(), other.opacity_logit]),
            faces=torch.cat([s.faces, other.faces + V]).to(torch.int32),
        )
        self.spawn_edge = torch.cat([self.spawn_edge, spawn_edge.float()])
        self.birth = torch.cat([self.birth, torch.full((other.num_faces,), birth, dtype=torch.int64)])

    def keep_faces(self, keep: torch.Tensor) -> int:
        """Keep the faces where `keep` [F] bool is True (and their private vertices); returns the number removed."""
        s = self.scene
        faces = s.faces[keep].long()
        used = torch.unique(faces.reshape(-1))
        remap = torch.full((s.num_vertices,), -1, dtype=torch.long)
        remap[used] = torch.arange(len(used))
        self.scene = TriangleScene(
            positions=s.positions.detach()[used].clone(),
            sh=s.sh.detach()[used].clone(),
            opacity_logit=s.opacity_logit.detach()[used].clone(),
            faces=remap[faces].to(torch.int32),
        )
        self.spawn_edge, self.birth = self.spawn_edge[keep], self.birth[keep]
        return int((~keep).sum())


def edge_lengths(positions: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Longest edge length [F] of each face."""
    t = positions[faces.long()]
    return torch.stack([(t[:, 1] - t[:, 0]).norm(dim=1), (t[:, 2] - t[:, 1]).norm(dim=1),
                        (t[:, 0] - t[:, 2]).norm(dim=1)], 1).max(1).values


def fill_depth_holes(depth: np.ndarray, where: np.ndarray, max_px: float) -> np.ndarray:
    """depth [H,W] (0 = no measurement) with the pixels of `where` that have no measurement, within max_px of one,
    set to the nearest measured depth (a copy; the input when there is nothing to fill)."""
    from scipy.ndimage import distance_transform_edt

    missing = depth <= 0
    if not missing.any() or missing.all():
        return depth
    dist, (iy, ix) = distance_transform_edt(missing, return_indices=True)
    fill = missing & where & (dist <= max_px)
    out = depth.copy()
    out[fill] = depth[iy[fill], ix[fill]]
    return out


def thin_mask(rgb_obs: np.ndarray, depth_obs: np.ndarray, alpha: np.ndarray, surf_depth: np.ndarray,
              cfg: SpawnConfig, rgb_map: np.ndarray | None = None) -> np.ndarray:
    """Pixels [H,W] bool where the map is thin: valid observed depth and (low rendered alpha, or observed surface in
    front of the rendered one, or (rgb_map given: the map's render) the colour off by more than cfg.color_error
    where the map's surface is at the observed depth)."""
    valid = (depth_obs > 0) & (depth_obs < cfg.max_depth)
    front = depth_obs < surf_depth - (cfg.front_margin + cfg.front_relative * depth_obs)
    thin = (alpha < cfg.thin_alpha) | front
    if rgb_map is not None and cfg.color_error > 0:
        from scipy.ndimage import uniform_filter

        err = uniform_filter(np.abs(rgb_map - rgb_obs).mean(-1), size=max(1, cfg.stride), mode="nearest")
        on = np.abs(surf_depth - depth_obs) < cfg.front_margin + cfg.front_relative * depth_obs
        thin |= on & (alpha >= cfg.thin_alpha) & (err > cfg.color_error)
    return valid & thin


def spawn(smap: SlamMap, rgb: np.ndarray, depth: np.ndarray, c2w: np.ndarray, K: np.ndarray, keyframe: int,
          cfg: SpawnConfig, sigma: float, rng: np.random.Generator) -> int:
    """Add triangles on thin pixels of one frame (rgb [H,W,3], depth [H,W] metres at K): one small equilateral
    triangle per stride-grid sample, in the plane of the depth normal, sized from the neighbour distance.
    Returns the number of triangles added."""
    H, W = depth.shape
    if smap.num_faces:
        with torch.no_grad():
            out = smap.render(np.linalg.inv(c2w), K, W, H, sigma)
        alpha = out.alpha.numpy()
        surf = np.where(alpha > 1e-3, out.depth.numpy() / np.maximum(alpha, 1e-3), np.inf)
        rgb_map = out.rgb.numpy()
    else:
        alpha, surf = np.zeros((H, W), np.float32), np.full((H, W), np.inf, np.float32)
        rgb_map = None
    if cfg.fill_holes_px > 0:
        depth = fill_depth_holes(depth, alpha < cfg.thin_alpha, cfg.fill_holes_px)
    mask = thin_mask(rgb, depth, alpha, surf, cfg, rgb_map)
    n_cam, n_ok = depth_to_normal(torch.from_numpy(depth.astype(np.float64)), torch.from_numpy(K))
    if cfg.min_valid_neighbours:
        mask &= n_ok.numpy()
    grid = np.zeros_like(mask)
    s = cfg.stride
    grid[s // 2 :: s, s // 2 :: s] = True
    mask &= grid
    rows, cols = np.nonzero(mask)
    if len(rows) < 4:
        return 0
    z = depth[rows, cols].astype(np.float64)
    x = (cols + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (rows + 0.5 - K[1, 2]) / K[1, 1] * z
    pc = np.stack([x, y, z], 1)
    R, t = c2w[:3, :3], c2w[:3, 3]
    pts = pc @ R.T + t
    normals = n_cam.numpy()[rows, cols] @ R.T
    new, _ = init_soup(pts, rgb[rows, cols], rng=rng, opacity=cfg.opacity, sh_degree=0,
                       size_factor=cfg.size_factor, normals=normals)
    # Cap each triangle's size at the sample spacing of its own depth (the kNN distance is large at sparse spots).
    P = new.positions.reshape(-1, 3, 3)
    centre = P.mean(1, keepdim=True)
    zc = (centre[:, 0].double() - torch.from_numpy(t)) @ torch.from_numpy(R)[:, 2]
    r = (P - centre).norm(dim=2).mean(1)
    cap = (cfg.size_factor * 1.5 * zc * s / K[0, 0]).float()
    scale = torch.clamp(cap / r.clamp_min(1e-9), max=1.0)
    new.positions = (centre + (P - centre) * scale[:, None, None]).reshape(-1, 3).contiguous()
    smap.append(new, edge_lengths(new.positions, new.faces), keyframe)
    return new.num_faces


def prune(smap: SlamMap, cfg: PruneConfig) -> int:
    """Remove low-opacity and oversize triangles; returns the number removed."""
    if smap.num_faces == 0:
        return 0
    with torch.no_grad():
        op = smap.scene.opacities()[smap.scene.faces.long()].mean(1)
        grown = edge_lengths(smap.scene.positions, smap.scene.faces) > cfg.max_growth * smap.spawn_edge
        keep = (op >= cfg.min_opacity) & ~grown & torch.isfinite(smap.scene.positions[smap.scene.faces.long()]).all(2).all(1)
    return smap.keep_faces(keep) if not bool(keep.all()) else 0
