"""Structure from motion built in: photos or a video without poses -> a COLMAP capture (pycolmap, CPU)."""

from trisplat.sfm.align import CentreError, camera_centre_error, umeyama
from trisplat.sfm.inputs import IMAGE_SUFFIXES, VIDEO_SUFFIXES, find_images, is_video
from trisplat.sfm.pipeline import PosesOptions, PosesReport, run_poses
from trisplat.sfm.video import extract_frames

__all__ = [
    "IMAGE_SUFFIXES",
    "VIDEO_SUFFIXES",
    "CentreError",
    "PosesOptions",
    "PosesReport",
    "camera_centre_error",
    "extract_frames",
    "find_images",
    "is_video",
    "run_poses",
    "umeyama",
]
