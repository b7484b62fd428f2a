"""Frame sampling from videos: the sharpness measure, the frame cap, unreadable files."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image, ImageFilter

from trisplat.sfm.video import extract_frames, sharpness


def _noise(seed: int, size=(64, 64)) -> Image.Image:
    rng = np.random.default_rng(seed)
    return Image.fromarray(rng.integers(0, 256, size=(*size, 3), dtype=np.uint8)).filter(ImageFilter.GaussianBlur(1))


def test_sharpness_orders_blur_levels():
    img = _noise(0, (96, 96))
    s = [sharpness(np.asarray(img.filter(ImageFilter.GaussianBlur(r)))) for r in (0.01, 1.0, 2.0, 4.0)]
    assert s == sorted(s, reverse=True) and s[0] > 5 * s[-1]


def test_frame_cap_lowers_the_rate(tmp_path):
    import imageio.v2 as iio

    video = tmp_path / "clip.mp4"
    with iio.get_writer(video, format="ffmpeg", fps=10, codec="libx264", quality=8, macro_block_size=16) as w:
        for i in range(20):  # 2 seconds
            w.append_data(np.asarray(_noise(i)))
    sel = extract_frames(video, tmp_path / "frames", rate=5.0, max_frames=4, progress=False)
    assert sel.frames_read == 20 and sel.fps == pytest.approx(10.0)
    assert sel.rate == pytest.approx(2.0)  # 4 frames over 2 s
    assert len(sel.files) == 4 and [f.name for f in sel.files] == sorted(f.name for f in sel.files)
    # one frame from each half-second: indices 0-4, 5-9, 10-14, 15-19
    assert [i // 5 for i in sel.frame_indices] == [0, 1, 2, 3]


def test_unreadable_video_is_named(tmp_path):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00" * 1000)
    with pytest.raises(ValueError, match="broken.mp4"):
        extract_frames(bad, tmp_path / "frames", progress=False)
