"""Registration check and repair: find photos that structure from motion placed where their own matches say they are
not, and register them again.

Why: incremental mapping registers each photo from 2D-3D matches. In a scene with repeated or symmetric content (a
round tree on a square table seen from all sides), a photo can be registered first through matches to the far side
of the object, at a mirror position, with a low reprojection error. The photos around it, registered later, match it
with a thousand verified inliers that its pose contradicts, and nothing in COLMAP looks back. On bonsai's 168 photos
5 were placed so (4 consecutive photos 5 units from their neighbours, one more on the other side of the room); one
was a test view, scored at 14 dB, and the per-photo colour correction crushed the red channel of the others to
explain them away.

The check: for every verified pair of registered images with at least `min_inliers` inliers, the inlier matches
are tested against the essential matrix of the two reconstructed poses (Sampson distance in pixels). A pair whose
matches mostly disagree contradicts one of its images. Each image's share of contradicting inliers is computed;
the worst image above `max_bad_share` is flagged, its pairs are set aside (they say nothing about its partners),
and the shares are computed again, until none is above. The repair deregisters the flagged images and lets
COLMAP's incremental mapper register them again into the rest of the model (where the correct matches now
outnumber the ghost ones); images still flagged after that are deregistered for good.
"""
from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MIN_INLIERS = 50  # pairs with fewer verified inliers are not used (weak pairs are noisy)
MAX_ERROR_PX = 4.0  # an inlier agrees with the poses when its Sampson distance is below this (pixels)
AGREE = 0.5  # a pair agrees with the poses when at least this share of its inliers does
MAX_BAD_SHARE = 0.25  # an image is flagged when more of its inliers than this lie in disagreeing pairs
# ... unless its STRONGEST pairs (by inliers) agree with its pose, on average (inlier-weighted) at least STRONG_AGREE:
# then its disagreeing pairs are matches to the far side of symmetric content, not a wrong pose. On 84 of bonsai's
# photos the check flagged DSCF5843 and DSCF5846 (shares 0.25 and 0.33: pairs of 288, 218, 339 and 267 inliers with
# photos across the room, 0% agreeing) and left them out; with the check off both sat within 0.12% of their place in
# the 168-photo model, and their three strongest pairs (862, 660, 510 ... inliers) agreed at 97%. A photo at a true
# mirror position disagrees with its strongest pairs: on a 24-photo subset, the flagged ones agreed at 25-70%.
STRONGEST = 3
STRONG_AGREE = 0.9


@dataclass
class PairCheck:
    """One verified pair against the reconstructed poses."""

    a: str
    b: str
    inliers: int
    agreeing: float  # share of its inliers within MAX_ERROR_PX of their epipolar lines


@dataclass
class RegistrationCheck:
    """The result: the flagged images (in the order found) and each image's share of contradicting inliers as
    first measured (before any image was set aside)."""

    flagged: list[str]
    bad_share: dict[str, float]


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def sampson_px(x1: np.ndarray, x2: np.ndarray, cam1_from_world: np.ndarray, cam2_from_world: np.ndarray,
               focal: float) -> np.ndarray:
    """Sampson distance of matches (normalised camera coordinates x1, x2 [N,2]) to the epipolar geometry of two
    poses (3x4 cam_from_world), in pixels (times `focal`)."""
    R1, t1 = cam1_from_world[:, :3], cam1_from_world[:, 3]
    R2, t2 = cam2_from_world[:, :3], cam2_from_world[:, 3]
    R = R2 @ R1.T
    E = _skew(t2 - R @ t1) @ R
    h1 = np.c_[x1, np.ones(len(x1))]
    h2 = np.c_[x2, np.ones(len(x2))]
    Ex1 = h1 @ E.T
    Etx2 = h2 @ E
    num = np.sum(h2 * Ex1, axis=1) ** 2
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30)) * focal


def check_pairs(database: Path, reconstruction, min_inliers: int = MIN_INLIERS,
                max_error_px: float = MAX_ERROR_PX) -> list[PairCheck]:
    """Every verified pair of registered images with at least `min_inliers` inliers, tested against the poses."""
    import pycolmap

    registered = {reconstruction.images[i].name: reconstruction.images[i] for i in reconstruction.reg_image_ids()}
    out: list[PairCheck] = []
    with pycolmap.Database.open(str(database)) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, geometries = db.read_two_view_geometries()
        points: dict[int, np.ndarray] = {}

        def normalised(image_id: int, idx: np.ndarray) -> tuple[np.ndarray, float]:
            if image_id not in points:
                points[image_id] = np.asarray(db.read_keypoints(image_id))[:, :2]
            cam = reconstruction.cameras[registered[names[image_id]].camera_id]
            return np.asarray(cam.cam_from_img(points[image_id][idx])), float(cam.mean_focal_length())

        for pid, geometry in zip(pair_ids, geometries):
            i1, i2 = pycolmap.pair_id_to_image_pair(pid)
            n1, n2 = names.get(i1), names.get(i2)
            matches = np.asarray(geometry.inlier_matches)
            if n1 not in registered or n2 not in registered or len(matches) < min_inliers:
                continue
            x1, f1 = normalised(i1, matches[:, 0])
            x2, f2 = normalised(i2, matches[:, 1])
            err = sampson_px(x1, x2, registered[n1].cam_from_world().matrix(),
                             registered[n2].cam_from_world().matrix(), math.sqrt(f1 * f2))
            out.append(PairCheck(n1, n2, len(matches), float(np.mean(err < max_error_px))))
    return out


def strongest_agreement(pairs: list[PairCheck], strongest: int = STRONGEST) -> dict[str, float]:
    """Per image, the inlier-weighted share of agreeing inliers over its `strongest` pairs with the most inliers."""
    by_image: dict[str, list[PairCheck]] = {}
    for p in pairs:
        for n in (p.a, p.b):
            by_image.setdefault(n, []).append(p)
    out = {}
    for n, ps in by_image.items():
        top = sorted(ps, key=lambda p: -p.inliers)[:strongest]
        out[n] = sum(p.inliers * p.agreeing for p in top) / max(sum(p.inliers for p in top), 1)
    return out


def flag_images(pairs: list[PairCheck], max_bad_share: float = MAX_BAD_SHARE,
                agree: float = AGREE, strong_agree: float = STRONG_AGREE) -> RegistrationCheck:
    """Greedy: flag the image with the largest share of contradicting inliers while it is above `max_bad_share`,
    setting its pairs aside each time (a misregistered photo makes its good partners look bad too). An image whose
    strongest pairs agree with its pose (strongest_agreement >= strong_agree) is never flagged (see STRONG_AGREE)."""
    sound = {n for n, a in strongest_agreement(pairs).items() if a >= strong_agree}
    active = list(pairs)
    flagged: list[str] = []
    first: dict[str, float] | None = None
    while True:
        total: dict[str, int] = {}
        bad: dict[str, int] = {}
        for p in active:
            for n in (p.a, p.b):
                total[n] = total.get(n, 0) + p.inliers
                if p.agreeing < agree:
                    bad[n] = bad.get(n, 0) + p.inliers
        share = {n: bad.get(n, 0) / t for n, t in total.items()}
        if first is None:
            first = share
        suspects = {n: v for n, v in share.items() if n not in sound}
        if not suspects:
            break
        worst = max(suspects, key=lambda n: (suspects[n], n))
        if suspects[worst] <= max_bad_share:
            break
        flagged.append(worst)
        active = [p for p in active if worst not in (p.a, p.b)]
    return RegistrationCheck(flagged=flagged, bad_share=first or {})


def check_registration(database: Path, reconstruction, max_bad_share: float = MAX_BAD_SHARE) -> RegistrationCheck:
    return flag_images(check_pairs(database, reconstruction), max_bad_share)


def deregister(reconstruction, names: list[str]) -> None:
    """Remove the named images from the model (their observations go; 3D points left with fewer than 2 go too)."""
    by_name = {reconstruction.images[i].name: reconstruction.images[i] for i in reconstruction.reg_image_ids()}
    for n in names:
        if n in by_name:
            reconstruction.deregister_frame(by_name[n].frame_id)


def register_again(database: Path, image_dir: Path, reconstruction, names: list[str], work: Path, seed: int = 0):
    """Deregister `names` and let COLMAP's incremental mapper register them again into the rest of the model.
    Returns the continued model (the input one, minus `names`, if none registers or the mapper fails)."""
    import pycolmap

    deregister(reconstruction, names)
    src, dst = work / "reregister_in", work / "reregister_out"
    for d in (src, dst):
        if d.exists():
            shutil.rmtree(d)
        d.mkdir(parents=True)
    reconstruction.write(str(src))
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = seed
    opts.mapper.random_seed = seed
    opts.triangulation.random_seed = seed
    try:
        models = pycolmap.incremental_mapping(str(database), str(image_dir), str(dst), options=opts,
                                              input_path=str(src))
        best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), default=None)
        if best is None or best.num_reg_images() < reconstruction.num_reg_images():
            best = reconstruction
    except Exception:  # noqa: BLE001 - COLMAP failing here leaves the flagged images out, as registering none would
        best = reconstruction
    finally:
        shutil.rmtree(src, ignore_errors=True)
        shutil.rmtree(dst, ignore_errors=True)
    return best


@dataclass
class Repair:
    """What `repair_registration` did: images flagged first, those registered again consistently, those dropped."""

    flagged: list[str]
    reregistered: list[str]
    dropped: list[str]
    worst_share_after: float

    def as_dict(self) -> dict:
        return {"flagged": self.flagged, "reregistered": self.reregistered, "dropped": self.dropped,
                "worst_share_after": self.worst_share_after}


def repair_registration(database: Path, image_dir: Path, reconstruction, work: Path, seed: int = 0,
                        max_bad_share: float = MAX_BAD_SHARE):
    """Check the model; register flagged images again; deregister any still flagged. Returns (model, Repair)."""
    first = check_registration(database, reconstruction, max_bad_share)
    if not first.flagged:
        worst = max(first.bad_share.values(), default=0.0)
        return reconstruction, Repair([], [], [], worst)
    model = register_again(database, image_dir, reconstruction, first.flagged, work, seed)
    second = check_registration(database, model, max_bad_share)
    registered = {model.images[i].name for i in model.reg_image_ids()}
    deregister(model, second.flagged)
    dropped = sorted(set(second.flagged) | (set(first.flagged) - registered))
    after = {n: s for n, s in second.bad_share.items() if n not in second.flagged}
    return model, Repair(first.flagged, [n for n in first.flagged if n not in dropped], dropped,
                         max(after.values(), default=0.0))
