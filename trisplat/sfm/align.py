"""Alignment of two point sets (similarity or rigid, Umeyama 1991) or of two camera paths (whole poses), and the
camera-centre error of a pose estimate."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _rotation_onto(dst: np.ndarray, src: np.ndarray) -> np.ndarray:
    """The proper rotation R [3,3] minimising sum |dst_i - R src_i|^2 (Kabsch, by scipy's Rotation.align_vectors).
    Where it is not unique (vectors all along one line) scipy warns and returns one of the minimisers: the residual
    is the same for all of them, which is what the callers that allow it (rigid ATE) measure."""
    import warnings

    from scipy.spatial.transform import Rotation

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*(not uniquely|poorly) defined.*", category=UserWarning)
        rot, _ = Rotation.align_vectors(dst, src)
    return rot.as_matrix()


def umeyama(src: np.ndarray, dst: np.ndarray, scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity taking `src` [N,3] onto `dst` [N,3]: (s, R [3,3], t [3]) with dst ~ s R src + t
    (Umeyama 1991); scale=False: the rigid motion (Horn / Kabsch), s = 1. The one point-set alignment of trisplat
    (camera centres of SfM, ATE of SLAM; align_poses for whole poses).

    Needs N >= 3 points. With scale, they must not be all collinear (raises ValueError: the similarity is undefined);
    without, collinear points are accepted (the rotation about their line is arbitrary, the residual is not). R is a
    proper rotation.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama: need two [N,3] arrays of the same shape, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"umeyama: need at least 3 point pairs, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    if scale:
        sv = np.linalg.svd(xs, compute_uv=False)
        if sv[0] <= 0 or sv[1] <= 1e-12 * sv[0]:
            raise ValueError("umeyama: the source points are (nearly) collinear or coincide: the similarity is "
                             "undefined")
    R = _rotation_onto(xd, xs)
    # the least-squares scale for that rotation: sum dst_i . R src_i / sum |src_i|^2 (centred)
    s = float((xd * (xs @ R.T)).sum() / (xs**2).sum()) if scale else 1.0
    return s, R, mu_d - s * R @ mu_s


def align_poses(est_c2w: np.ndarray, ref_c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (R [3,3], t [3]) taking the estimate's world into the reference's, from whole camera-to-world poses
    [N,4,4]: R the rotation nearest to every R_ref_i R_est_i^T (chordal L2: the columns of the rotations aligned as
    vectors), t the mean of c_ref_i - R c_est_i. Unlike a centre-only alignment it is well determined on short,
    nearly straight paths (where a rotation about the path's direction hardly moves the centres but swings a scene
    metres away)."""
    est_c2w, ref_c2w = np.asarray(est_c2w, np.float64), np.asarray(ref_c2w, np.float64)
    cols = lambda T: T[:, :3, :3].transpose(0, 2, 1).reshape(-1, 3)  # the columns of every rotation
    R = _rotation_onto(cols(ref_c2w), cols(est_c2w))
    return R, (ref_c2w[:, :3, 3] - est_c2w[:, :3, 3] @ R.T).mean(0)


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
