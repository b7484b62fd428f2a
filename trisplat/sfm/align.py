"""Similarity (Sim3) alignment of two point sets (Umeyama 1991) and the camera-centre error of a pose estimate."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity taking `src` [N,3] onto `dst` [N,3]: (s, R [3,3], t [3]) with dst ~ s R src + t.

    Needs N >= 3 points that are not all collinear (raises ValueError otherwise). R is a proper rotation.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama: need two [N,3] arrays of the same shape, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"umeyama: need at least 3 point pairs, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs**2).sum() / len(src)
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    if var_s <= 0 or D[1] <= 1e-12 * max(D[0], 1e-300):
        raise ValueError("umeyama: the source points are (nearly) collinear or coincide: the similarity is undefined")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s)
    t = mu_d - s * R @ mu_s
    return s, R, t


@dataclass(frozen=True)
class CentreError:
    """Camera centres of an estimate aligned onto a reference by a similarity, errors in the reference's units.

    extent: the largest distance between two reference centres (the camera-path extent); errors are also given as
    fractions of it. n: the number of cameras compared.
    """

    n: int
    extent: float
    mean: float
    median: float
    max: float
    scale: float

    @property
    def mean_fraction(self) -> float:
        return self.mean / self.extent

    @property
    def max_fraction(self) -> float:
        return self.max / self.extent

    def as_dict(self) -> dict:
        return {"n": self.n, "extent": self.extent, "mean": self.mean, "median": self.median, "max": self.max,
                "mean_percent_of_extent": 100 * self.mean_fraction, "max_percent_of_extent": 100 * self.max_fraction,
                "scale": self.scale}


def camera_centre_error(estimate: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> CentreError:
    """Align the camera centres of `estimate` onto `reference` (dicts: image name -> centre [3]) over the names they
    share, by the least-squares similarity, and measure the remaining distances in the reference's units."""
    names = sorted(set(estimate) & set(reference))
    if len(names) < 3:
        raise ValueError(f"camera_centre_error: only {len(names)} image name(s) in common; need at least 3")
    est = np.array([estimate[n] for n in names], dtype=np.float64)
    ref = np.array([reference[n] for n in names], dtype=np.float64)
    s, R, t = umeyama(est, ref)
    err = np.linalg.norm((s * est @ R.T + t) - ref, axis=1)
    d = ref[:, None, :] - ref[None, :, :]
    extent = float(np.sqrt((d**2).sum(-1)).max())
    return CentreError(len(names), extent, float(err.mean()), float(np.median(err)), float(err.max()), s)


def centres_from_model(model_dir) -> dict[str, np.ndarray]:
    """Image name -> camera centre (world frame) of every posed image of a COLMAP model folder."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    out = {}
    for im in rec.images.values():
        if im.has_pose:
            out[im.name] = np.asarray(im.projection_center(), dtype=np.float64)
    return out
