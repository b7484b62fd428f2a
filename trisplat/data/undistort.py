"""Undistortion of COLMAP camera models to pinhole (pycolmap's undistorter: bilinear, cropped to valid pixels)."""
from __future__ import annotations

import numpy as np

from trisplat.data.capture import SourceCamera


def _options():
    import pycolmap

    # blank_pixels = 0: the pinhole image is cropped so that every pixel comes from inside the original image.
    return pycolmap.UndistortCameraOptions()


def _pycolmap_camera(src: SourceCamera):
    import pycolmap

    return pycolmap.Camera(model=src.model, width=src.width, height=src.height, params=list(src.params))


def pinhole_camera(src: SourceCamera) -> tuple[np.ndarray, int, int]:
    """(K [3,3], width, height) of the pinhole camera the undistorted image of `src` will have."""
    if not src.needs_undistortion:
        return src.pinhole_K(), src.width, src.height
    import pycolmap

    cam = pycolmap.undistort_camera(_options(), _pycolmap_camera(src))
    return np.asarray(cam.calibration_matrix(), dtype=np.float64), int(cam.width), int(cam.height)


def undistort_array(img: np.ndarray, src: SourceCamera) -> np.ndarray:
    """Undistort uint8 [H,W,3] or [H,W,4] (straight alpha, resampled premultiplied) to the pinhole camera."""
    if not src.needs_undistortion:
        return img
    import pycolmap

    h, w = img.shape[:2]
    if (w, h) != (src.width, src.height):
        raise ValueError(f"image is {w}x{h} but its camera is {src.width}x{src.height}")
    cam = _pycolmap_camera(src)
    opts = _options()
    if img.shape[-1] == 3:
        out, _ = pycolmap.undistort_image(opts, pycolmap.Bitmap.from_array(np.ascontiguousarray(img)), cam)
        return out.to_array()
    alpha = img[..., 3:4].astype(np.float32) / 255.0
    premult = np.clip(img[..., :3].astype(np.float32) * alpha + 0.5, 0, 255).astype(np.uint8)
    rgb, _ = pycolmap.undistort_image(opts, pycolmap.Bitmap.from_array(premult), cam)
    a, _ = pycolmap.undistort_image(opts, pycolmap.Bitmap.from_array(np.ascontiguousarray(img[..., 3])), cam)
    rgb = rgb.to_array().astype(np.float32)
    a = a.to_array().astype(np.float32)
    if a.ndim == 3:
        a = a[..., 0]
    straight = np.where(a[..., None] > 0, rgb * 255.0 / np.maximum(a[..., None], 1.0), 0.0)
    return np.dstack([np.clip(straight + 0.5, 0, 255), a]).astype(np.uint8)
