"""The full-quality model as a PLY: every SH coefficient, the opacity logit and floor, and the faces, in the capture frame.

Layout (binary little endian), readable by any PLY reader and close to 3DGS files:
  element vertex: double x, y, z (capture frame, so other tools show the model where the capture was);
                  float f_dc_0..2 (SH band 0, RGB); float f_rest_0..3*(K-1)-1 (higher bands, channel-major as in
                  3DGS: f_rest_{c*(K-1) + k-1} = sh[:, k, c]); float opacity (the logit).
  element face:   list uchar int vertex_indices.
  comments:       'trisplat model', 'sh_degree D', 'opacity_floor F', 'normalization m00 ... m33' (row-major), and
                  'linear_light 1' when the colours are blended in linear light (TriangleScene.linear_light; absent: 0).
Positions are stored as doubles computed in float64 from the normalised frame, so reading them back and
re-applying the normalisation returns the float32 positions bit for bit (unless a coordinate is below ~1e-8 of
the normalisation's translation, where the capture frame cannot hold it; the error there is ~1e-16 units).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from trisplat.io.atomic import atomic_target
from trisplat.scene.model import TriangleScene
from trisplat.scene.sh import sh_degree_from_bases

MAGIC = "trisplat model"
# How far the normalisation's 3x3 block may be from s * identity (relative) and still count as translation + scale.
SIMILARITY_TOLERANCE = 1e-9


def _scale_translation(normalization: np.ndarray, where: str) -> tuple[float, np.ndarray]:
    N = np.asarray(normalization, dtype=np.float64)
    if N.shape != (4, 4) or not np.isfinite(N).all():
        raise ValueError(f"{where}: normalization must be a finite [4,4] matrix, got shape {N.shape}")
    s = float(N[0, 0])
    if (
        s <= 0
        or np.abs(N[:3, :3] - s * np.eye(3)).max() > SIMILARITY_TOLERANCE * s
        or not np.array_equal(N[3], [0.0, 0.0, 0.0, 1.0])
    ):
        raise ValueError(
            f"{where}: normalization must be a translation and one positive uniform scale (docs/conventions.md), got\n{N}"
        )
    return s, N[:3, 3].copy()


def save_model_ply(path: str | Path, scene: TriangleScene, normalization: np.ndarray) -> Path:
    """Write `scene` (normalised frame) with every SH band and the opacity, positions in the capture frame
    (x_capture = (x_norm - t) / s for normalization = [[s*I, t], [0, 1]])."""
    path = Path(path)
    s, t = _scale_translation(normalization, str(path))
    pos = scene.positions.detach().cpu().numpy().astype(np.float32)
    sh = scene.sh.detach().cpu().numpy().astype(np.float32)
    logit = scene.opacity_logit.detach().cpu().numpy().astype(np.float32)
    faces = scene.faces.detach().cpu().numpy().astype(np.int32)
    V, K, _ = sh.shape
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(V, 3 * (K - 1))  # channel-major like 3DGS

    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    fields += [(f"f_dc_{c}", "<f4") for c in range(3)]
    fields += [(f"f_rest_{i}", "<f4") for i in range(rest.shape[1])]
    fields += [("opacity", "<f4")]
    vert = np.empty(V, dtype=fields)
    capture = (pos.astype(np.float64) - t) / s
    vert["x"], vert["y"], vert["z"] = capture.T
    for c in range(3):
        vert[f"f_dc_{c}"] = sh[:, 0, c]
    for i in range(rest.shape[1]):
        vert[f"f_rest_{i}"] = rest[:, i]
    vert["opacity"] = logit
    face = np.empty(len(faces), dtype=[("vertex_indices", "<i4", (3,))])
    face["vertex_indices"] = faces

    N = np.asarray(normalization, dtype=np.float64)
    comments = [
        MAGIC,
        f"sh_degree {sh_degree_from_bases(K)}",
        f"opacity_floor {float(scene.opacity_floor)!r}",
        "normalization " + " ".join(repr(float(v)) for v in N.reshape(-1)),
    ] + (["linear_light 1"] if scene.linear_light else [])
    elements = [
        PlyElement.describe(vert, "vertex"),
        PlyElement.describe(face, "face", len_types={"vertex_indices": "u1"}),
    ]
    with atomic_target(path) as tmp:  # a run killed mid-write leaves the old file (or none), never half a model
        PlyData(elements, text=False, byte_order="<", comments=comments).write(str(tmp))
    return path


def load_model_ply(path: str | Path) -> tuple[TriangleScene, np.ndarray]:
    """Read a model written by `save_model_ply`: the TriangleScene in the normalised frame (CPU tensors) and the
    normalization [4,4] float64."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such model file")
    try:
        ply = PlyData.read(str(path))
    except Exception as exc:  # plyfile raises several types for malformed headers
        raise ValueError(f"{path}: not a readable PLY ({exc})") from exc
    meta = {}
    for line in ply.comments:
        key, _, value = line.partition(" ")
        meta[key] = value
    if MAGIC not in ply.comments:
        raise ValueError(f"{path}: not a trisplat model PLY (no '{MAGIC}' comment); for a plain mesh use load_mesh")
    for key in ("sh_degree", "opacity_floor", "normalization"):
        if key not in meta:
            raise ValueError(f"{path}: header lacks the '{key}' comment")
    try:
        degree = int(meta["sh_degree"])
        floor = float(meta["opacity_floor"])
        linear = meta.get("linear_light", "0").strip()
        if linear not in ("0", "1"):
            raise ValueError(f"linear_light must be 0 or 1, got {linear!r}")
        N = np.array([float(v) for v in meta["normalization"].split()], dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}: malformed header comment ({exc})") from exc
    if N.size != 16:
        raise ValueError(f"{path}: 'normalization' comment has {N.size} numbers, expected 16")
    N = N.reshape(4, 4)
    s, t = _scale_translation(N, str(path))
    K = (degree + 1) ** 2
    names = ["x", "y", "z", "opacity"] + [f"f_dc_{c}" for c in range(3)]
    names += [f"f_rest_{i}" for i in range(3 * (K - 1))]
    if "vertex" not in ply or "face" not in ply:
        raise ValueError(f"{path}: needs 'vertex' and 'face' elements")
    v = ply["vertex"].data
    missing = [n for n in names if n not in v.dtype.names]
    if missing:
        raise ValueError(f"{path}: vertex properties missing for SH degree {degree}: {', '.join(missing[:5])}")
    capture = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    pos = (s * capture + t).astype(np.float32)
    V = len(v)
    sh = np.empty((V, K, 3), dtype=np.float32)
    for c in range(3):
        sh[:, 0, c] = v[f"f_dc_{c}"]
    if K > 1:
        rest = np.column_stack([v[f"f_rest_{i}"] for i in range(3 * (K - 1))]).astype(np.float32)
        sh[:, 1:, :] = rest.reshape(V, 3, K - 1).transpose(0, 2, 1)
    face_data = ply["face"].data["vertex_indices"]
    try:
        faces = np.stack(face_data).astype(np.int32) if len(face_data) else np.zeros((0, 3), np.int32)
    except ValueError as exc:
        raise ValueError(f"{path}: faces must all be triangles ({exc})") from exc
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{path}: faces must all be triangles, got shape {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= V):
        raise ValueError(f"{path}: faces index vertices outside 0..{V - 1}")
    scene = TriangleScene(
        positions=torch.from_numpy(pos),
        sh=torch.from_numpy(sh),
        opacity_logit=torch.from_numpy(np.asarray(v["opacity"], dtype=np.float32).copy()),
        faces=torch.from_numpy(faces),
        opacity_floor=floor,
        linear_light=linear == "1",
    )
    return scene, N
