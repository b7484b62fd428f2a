"""`trisplat compare IMG_A IMG_B`: PSNR, SSIM and LPIPS between two images of the same size, printed as JSON."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT


@dataclass
class CompareConfig:
    """Score image B against image A (PSNR in dB, SSIM, LPIPS-AlexNet v0.1). Alpha is composited over white."""

    image_a: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="IMG_A")]
    """reference image (PNG/JPEG/...)"""
    image_b: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="IMG_B")]
    """image to score against the reference, same size"""
    lpips_weights: Annotated[Path | None, NO_DEFAULT_HINT] = None
    """LPIPS .npz (default: $TRISPLAT_LPIPS_WEIGHTS, else ~/.cache/trisplat/lpips_alexnet_full_oihw.npz)"""


def read_rgb(path: Path, background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """An image file as float32 [H,W,3] in [0,1]; an alpha channel is composited over `background`."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such image file")
    try:
        with Image.open(path) as im:
            im.load()
            rgba = np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"{path}: not a readable image ({exc})") from exc
    rgb, a = rgba[..., :3], rgba[..., 3:]
    return rgb * a + np.asarray(background, dtype=np.float32) * (1.0 - a)


def compare_images(a: np.ndarray, b: np.ndarray, lpips_weights: Path | None = None) -> dict:
    """{"psnr", "ssim", "lpips", "lpips_note"} for two [H,W,3] images in [0,1].

    lpips is None and lpips_note says how to obtain the weights when the weights file is missing. PSNR of identical
    images is +inf (serialise with `trisplat.eval.report.json_safe`).
    """
    from trisplat.eval.image_metrics import psnr, ssim
    from trisplat.eval.lpips import lpips

    out = {"psnr": psnr(a, b), "ssim": ssim(a, b), "lpips": None, "lpips_note": None}
    try:
        out["lpips"] = lpips(a, b, lpips_weights)
    except FileNotFoundError as exc:
        out["lpips_note"] = str(exc)
    return out


def main(argv: list[str]) -> int:
    cfg = tyro.cli(CompareConfig, args=argv, description=__doc__, prog="trisplat compare", config=CLI_STYLE)
    a, b = read_rgb(cfg.image_a), read_rgb(cfg.image_b)
    if a.shape != b.shape:
        raise ValueError(f"{cfg.image_b}: size {b.shape[1]}x{b.shape[0]} differs from {cfg.image_a} "
                         f"({a.shape[1]}x{a.shape[0]})")  # fmt: skip
    res = compare_images(a, b, cfg.lpips_weights)
    res = {"image_a": str(cfg.image_a), "image_b": str(cfg.image_b), **res}
    if res["lpips_note"] is None:
        del res["lpips_note"]
    from trisplat.eval.report import json_safe

    print(json.dumps(json_safe(res), indent=2))
    return 0
