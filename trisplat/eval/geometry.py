"""Geometry metrics between a predicted surface and ground truth: Chamfer (DTU style), F-score, normal consistency.

Both surfaces are turned into point samples: a mesh is sampled area-uniformly with a fixed seed (trimesh.sample),
a point cloud is used as is (randomly subsampled with the seed when it has more points than asked). Both sides use
the same seed, so a mesh compared with itself (or with a copy moved by d along its normal) gets exactly 0 (or d). Distances are
nearest-neighbour distances between the two sample sets (scipy KD-tree), in the surfaces' units:
accuracy = mean distance pred -> gt, completeness = mean distance gt -> pred, chamfer = their mean;
precision / recall = fraction of pred / gt samples within `threshold` of the other set, fscore their harmonic mean.
Normal consistency = mean |n_pred . n_gt| over nearest pairs in both directions (orientation-agnostic; None when
either side has no normals). Unlike the DTU script, no observation mask or outlier cut-off is applied.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

DEFAULT_SAMPLES = 200_000  # points sampled on each mesh
DEFAULT_THRESHOLD_FRACTION = 0.01  # default F-score threshold, as a fraction of the GT bounding-box diagonal
DEFAULT_SEED = 0


@dataclass(frozen=True)
class Surface:
    """A mesh (faces given) or a point cloud (faces None). vertices float [N,3]; faces int [F,3];
    normals: optional unit [N,3] per point of a point cloud (meshes use face normals)."""

    vertices: np.ndarray
    faces: np.ndarray | None = None
    normals: np.ndarray | None = None

    @property
    def is_mesh(self) -> bool:
        return self.faces is not None and len(self.faces) > 0

    def bbox_diagonal(self) -> float:
        v = np.asarray(self.vertices, dtype=np.float64)
        if self.is_mesh:
            v = v[np.unique(np.asarray(self.faces))]
        return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) if len(v) else 0.0


@dataclass
class GeometryMetrics:
    """Distances in the surfaces' units; precision/recall/fscore in [0,1]."""

    accuracy: float
    completeness: float
    chamfer: float
    precision: float
    recall: float
    fscore: float
    threshold: float
    normal_consistency: float | None
    gt_bbox_diagonal: float
    chamfer_over_diagonal: float  # chamfer / gt_bbox_diagonal
    num_pred_samples: int
    num_gt_samples: int
    seed: int

    def to_dict(self) -> dict:
        return asdict(self)


def sample_surface(surface: Surface, count: int, seed: int = DEFAULT_SEED) -> tuple[np.ndarray, np.ndarray | None]:
    """Points [N,3] (float64) on the surface and their unit normals [N,3] (None for a point cloud without normals).
    Meshes: `count` area-uniform samples with `seed`. Point clouds: all points, or `count` of them drawn with `seed`."""
    import trimesh

    if count <= 0:
        raise ValueError(f"sample count must be positive, got {count}")
    v = np.asarray(surface.vertices, dtype=np.float64)
    if surface.is_mesh:
        mesh = trimesh.Trimesh(v, np.asarray(surface.faces, dtype=np.int64), process=False)
        if mesh.area <= 0:
            raise ValueError("mesh has zero surface area: nothing to sample")
        pts, face_idx = trimesh.sample.sample_surface(mesh, count, seed=seed)
        return np.asarray(pts, dtype=np.float64), np.asarray(mesh.face_normals[face_idx], dtype=np.float64)
    if len(v) == 0:
        raise ValueError("point cloud is empty")
    normals = None if surface.normals is None else np.asarray(surface.normals, dtype=np.float64)
    if len(v) > count:
        idx = np.sort(np.random.default_rng(seed).choice(len(v), count, replace=False))
        v = v[idx]
        normals = None if normals is None else normals[idx]
    if normals is not None:
        normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    return v, normals


def compare_surfaces(
    pred: Surface, gt: Surface, threshold: float | None = None, samples: int = DEFAULT_SAMPLES, seed: int = DEFAULT_SEED
) -> GeometryMetrics:
    """Chamfer / F-score / normal consistency of `pred` against `gt` (see the module docstring).
    threshold: F-score distance in the surfaces' units; None = DEFAULT_THRESHOLD_FRACTION of the GT bbox diagonal."""
    diag = gt.bbox_diagonal()
    if threshold is None:
        threshold = DEFAULT_THRESHOLD_FRACTION * diag
    if not threshold > 0:
        raise ValueError(f"F-score threshold must be positive, got {threshold}")
    p, pn = sample_surface(pred, samples, seed)
    g, gn = sample_surface(gt, samples, seed)
    d_pg, i_pg = cKDTree(g).query(p, workers=-1)
    d_gp, i_gp = cKDTree(p).query(g, workers=-1)
    acc, comp = float(d_pg.mean()), float(d_gp.mean())
    prec, rec = float(np.mean(d_pg < threshold)), float(np.mean(d_gp < threshold))
    f = 2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0
    nc = None
    if pn is not None and gn is not None:
        nc = 0.5 * (
            float(np.abs(np.einsum("ij,ij->i", pn, gn[i_pg])).mean())
            + float(np.abs(np.einsum("ij,ij->i", gn, pn[i_gp])).mean())
        )
    chamfer = 0.5 * (acc + comp)
    return GeometryMetrics(
        accuracy=acc,
        completeness=comp,
        chamfer=chamfer,
        precision=prec,
        recall=rec,
        fscore=f,
        threshold=float(threshold),
        normal_consistency=nc,
        gt_bbox_diagonal=diag,
        chamfer_over_diagonal=chamfer / diag if diag > 0 else float("inf"),
        num_pred_samples=len(p),
        num_gt_samples=len(g),
        seed=seed,
    )


def load_surface(path: str | Path) -> Surface:
    """A mesh or point cloud from a file trimesh reads (.ply, .obj, .glb, .stl, .off, ...). A file with vertices and
    no faces is a point cloud (its vertex normals are used when the file has them)."""
    import trimesh

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such mesh or point-cloud file")
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ValueError(f"{path}: cannot read as a mesh or point cloud ({exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        geoms = list(loaded.dump()) if hasattr(loaded, "dump") else list(loaded.geometry.values())
        meshes = [g for g in geoms if isinstance(g, trimesh.Trimesh)]
        if meshes:
            loaded = trimesh.util.concatenate(meshes)
        elif geoms:
            loaded = geoms[0]
        else:
            raise ValueError(f"{path}: the file holds no geometry")
    if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces):
        return Surface(np.asarray(loaded.vertices), np.asarray(loaded.faces))
    if isinstance(loaded, (trimesh.PointCloud, trimesh.Trimesh)):
        verts = np.asarray(loaded.vertices)
        if len(verts) == 0:
            raise ValueError(f"{path}: no vertices")
        normals = _ply_vertex_normals(loaded)
        return Surface(verts, None, normals)
    raise ValueError(f"{path}: unsupported geometry type {type(loaded).__name__}")


def _ply_vertex_normals(geom) -> np.ndarray | None:
    """Vertex normals nx, ny, nz of a PLY point cloud, when trimesh kept them in its metadata."""
    try:
        vert = geom.metadata["_ply_raw"]["vertex"]["data"]
        return np.stack([vert["nx"], vert["ny"], vert["nz"]], axis=1).astype(np.float64)
    except (KeyError, ValueError, TypeError, IndexError):
        return None
