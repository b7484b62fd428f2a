"""The initial focal length comes from EXIF where photos carry it (COLMAP's reader), else 1.2 x the longest side."""
from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from trisplat.sfm.pipeline import PosesOptions, _extract


def _photos(folder, exif: bool, n: int = 3):
    rng = np.random.default_rng(0)
    folder.mkdir()
    for i in range(n):
        im = Image.fromarray(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8))
        ex = Image.Exif()
        if exif:
            ex[0x010F], ex[0x0110] = "Acme", "Cam1"  # Make, Model
            ifd = ex.get_ifd(0x8769)  # Exif IFD
            ifd[0x920A] = 4.0  # FocalLength, mm
            ifd[0xA405] = 28  # FocalLengthIn35mmFilm, mm
        im.save(folder / f"p{i}.jpg", exif=ex)
    return [f"p{i}.jpg" for i in range(n)]


@pytest.mark.parametrize("exif", [True, False])
def test_focal_prior(tmp_path, exif):
    import pycolmap

    folder = tmp_path / "photos"
    names = _photos(folder, exif)
    (tmp_path / "work").mkdir()
    feats = _extract(tmp_path / "work" / "db.db", folder, names, PosesOptions(), progress=False)
    assert feats["exif"] is exif and set(feats["features"]) == set(names)
    with pycolmap.Database.open(str(tmp_path / "work" / "db.db")) as db:
        cams = db.read_all_cameras()
    assert len(cams) == 1  # one camera shared by all photos
    # COLMAP scales the 35 mm equivalent focal length by the diagonals (36 x 24 mm film, 160 x 120 pixels)
    want = 28 * math.hypot(160, 120) / math.hypot(36, 24) if exif else 1.2 * 160
    assert cams[0].params[0] == pytest.approx(want, rel=1e-3)
