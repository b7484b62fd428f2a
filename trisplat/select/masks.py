"""Binary object masks on disk: read a PNG as a boolean image and match a folder of them to cameras by file stem."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from trisplat.cameras import Camera

MASK_SUFFIXES = (".png",)
MASK_THRESHOLD = 127  # 8-bit grey level above which a pixel is "object" (masks stored as 0/1 use > 0 instead)
MASK_RESAMPLE_THRESHOLD = 0.5  # a resized mask pixel is "object" when at least this fraction of its area was


def _to_bool(arr: np.ndarray) -> np.ndarray:
    if arr.max(initial=0) <= 1:  # 0/1 label images
        return arr > 0
    return arr > MASK_THRESHOLD


def read_mask(path: str | Path, width: int | None = None, height: int | None = None) -> np.ndarray:
    """A mask PNG as bool [H,W] (True = object).

    Grey or RGB masks: object where the grey level is > 127 (or > 0 for masks stored as 0/1). Masks with a
    non-constant alpha channel use the alpha instead. With width/height given, a mask of the same aspect ratio but a
    different size (e.g. made on the full-resolution photo of a downscaled view) is area-resampled and thresholded
    at half coverage; any other size is an error. Empty masks are an error.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: mask file not found")
    try:
        img = Image.open(path)
        img.load()
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"{path}: not a readable image ({exc})") from exc
    if img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info):
        alpha = np.asarray(img.convert("RGBA"))[..., 3]
        arr = alpha if alpha.min() != alpha.max() else np.asarray(img.convert("L"))
    else:
        arr = np.asarray(img.convert("L"))
    mask = _to_bool(arr)
    h, w = mask.shape
    if width is not None and height is not None and (w, h) != (width, height):
        if abs(w * height - h * width) > max(w, h, width, height):  # aspect ratios differ by more than a pixel
            raise ValueError(f"{path}: mask is {w}x{h} pixels, but its view's image is {width}x{height} "
                             "(and the aspect ratios differ, so it cannot be resized)")
        cover = Image.fromarray(mask.astype(np.float32)).resize((width, height), Image.Resampling.BOX)
        mask = np.asarray(cover) >= MASK_RESAMPLE_THRESHOLD
    if not mask.any():
        raise ValueError(f"{path}: mask is empty (no pixel above grey level {MASK_THRESHOLD}; "
                         "object pixels should be white)")
    return mask


def _camera_stem(cam: Camera) -> str:
    return cam.stem  # the source photo's stem, also when the loader cached a resized copy under another name


def match_masks(mask_dir: str | Path, cameras: Sequence[Camera], candidates: Sequence[int] | None = None,
                preferred: Sequence[int] | None = None) -> dict[int, np.ndarray]:
    """Read every PNG in `mask_dir` and assign it to the camera whose image has the same file stem.

    candidates: camera indices allowed to match (default all). preferred: when a stem names several views (Blender
    captures have train/r_0 and test/r_0), the one among these indices (e.g. the training views) wins; a stem that
    is still ambiguous is an error. Returns camera index ->
    bool [H,W] mask at that camera's resolution. Errors name the files: no masks, a name matching no view (with
    examples of view names), a name matching several views, wrong size, empty mask.
    """
    mask_dir = Path(mask_dir)
    if not mask_dir.is_dir():
        raise FileNotFoundError(f"{mask_dir}: mask folder not found")
    files = sorted(p for p in mask_dir.iterdir() if p.is_file() and p.suffix.lower() in MASK_SUFFIXES)
    if not files:
        raise ValueError(f"{mask_dir}: no mask images (*.png) in this folder")
    allowed = list(range(len(cameras))) if candidates is None else [int(i) for i in candidates]
    by_stem: dict[str, list[int]] = {}
    for i in allowed:
        by_stem.setdefault(_camera_stem(cameras[i]), []).append(i)
    unmatched = [p.name for p in files if p.stem not in by_stem]
    if unmatched:
        examples = ", ".join(sorted(by_stem)[:5])
        raise ValueError(f"{mask_dir}: {len(unmatched)} mask(s) match no view by file stem: "
                         f"{', '.join(unmatched[:5])}{' ...' if len(unmatched) > 5 else ''} "
                         f"(view names look like: {examples})")
    out: dict[int, np.ndarray] = {}
    for p in files:
        hits = by_stem[p.stem]
        if len(hits) > 1 and preferred is not None:
            pref = {int(i) for i in preferred}
            hits = [i for i in hits if i in pref] if sum(i in pref for i in hits) == 1 else hits
        if len(hits) > 1:
            names = ", ".join(str(cameras[i].image_path or cameras[i].name) for i in hits)
            raise ValueError(f"{p}: stem {p.stem!r} matches {len(hits)} views ({names}); rename the images or masks")
        i = hits[0]
        if i in out:
            raise ValueError(f"{p}: a second mask for view {p.stem!r} (masks differ only in suffix case?)")
        out[i] = read_mask(p, cameras[i].width, cameras[i].height)
    return out
