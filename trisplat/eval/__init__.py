"""Evaluation: image metrics (PSNR, SSIM, LPIPS), geometry metrics, and HTML reports of runs.

LPIPS lives in `trisplat.eval.lpips` (function `lpips`, network `load_lpips`); it is not re-exported here so that
the submodule name is not shadowed by the function.
"""
from trisplat.eval.image_metrics import psnr, psnr_torch, ssim, ssim_torch

__all__ = ["psnr", "psnr_torch", "ssim", "ssim_torch"]
