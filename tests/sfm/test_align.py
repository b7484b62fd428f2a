"""umeyama and camera_centre_error against similarities made by hand."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trisplat.sfm.align import camera_centre_error, umeyama


def test_umeyama_recovers_a_known_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(30, 3))
    R = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    s, t = 3.7, np.array([1.0, -2.0, 5.0])
    dst = s * src @ R.T + t
    s2, R2, t2 = umeyama(src, dst)
    assert s2 == pytest.approx(s, rel=1e-10)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-9)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: the best proper rotation is not exact
    _, R, _ = umeyama(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_rejects_collinear_points():
    src = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="collinear"):
        umeyama(src, src)


def test_centre_error_is_zero_for_a_similar_copy_and_measures_a_displacement():
    rng = np.random.default_rng(3)
    ref = {f"im{i}.jpg": rng.normal(size=3) * 4 for i in range(12)}
    R = Rotation.from_rotvec([1.0, 0.2, -0.4]).as_matrix()
    est = {k: 0.1 * R @ v + 7.0 for k, v in ref.items()}
    est["only_in_estimate.jpg"] = np.zeros(3)
    e = camera_centre_error(est, ref)
    assert e.n == 12 and e.max < 1e-9 and e.scale == pytest.approx(10.0)
    pts = np.array(list(ref.values()))
    assert e.extent == pytest.approx(max(np.linalg.norm(a - b) for a in pts for b in pts))
    # move one reference camera: the error appears (shared among cameras by least squares, but non-zero)
    ref2 = dict(ref)
    ref2["im0.jpg"] = ref["im0.jpg"] + np.array([0.5, 0, 0])
    assert camera_centre_error(est, ref2).max > 0.3


def test_centre_error_needs_three_common_names():
    a = {"a": np.zeros(3), "b": np.ones(3), "c": np.array([0, 1.0, 0])}
    with pytest.raises(ValueError, match="only 2 image name"):
        camera_centre_error(a, {"a": np.zeros(3), "b": np.ones(3), "x": np.zeros(3)})
