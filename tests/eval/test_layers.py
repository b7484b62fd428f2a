"""Scores by layer (trisplat.eval.layers): each pixel is labelled by the rows of the face table its face id falls in,
and each layer's PSNR pools its pixels' squared errors over the views."""
import numpy as np
import pytest

from trisplat.eval.layers import LAYERS, LayerScores, layer_labels


def test_labels_follow_the_face_tables_rows():
    # 10 faces: rows 0-5 the surface, 6-9 the far field, of which 8-9 the background sphere
    fid = np.array([[-1, 0, 5], [6, 7, 8], [9, 3, -1]])
    lab = layer_labels(fid, num_faces=10, far_faces=4, background_faces=2)
    names = np.array(LAYERS)[lab]
    assert names.tolist() == [["empty", "surface", "surface"],
                              ["far_field", "far_field", "background_sphere"],
                              ["background_sphere", "surface", "empty"]]
    # no far field: everything drawn is surface
    assert (np.array(LAYERS)[layer_labels(fid, 10, 0, 0)][fid >= 0] == "surface").all()


def test_bad_layer_sizes_and_face_ids_are_refused():
    with pytest.raises(ValueError, match="background_faces"):
        layer_labels(np.zeros((2, 2), int), num_faces=10, far_faces=2, background_faces=3)
    with pytest.raises(ValueError, match="face ids"):
        layer_labels(np.array([[10]]), num_faces=10, far_faces=0, background_faces=0)


def test_scores_pool_squared_errors_per_layer_over_views():
    rng = np.random.default_rng(0)
    scores = LayerScores()
    errs = {name: [] for name in LAYERS}
    for _ in range(3):
        photo = rng.random((6, 8, 3))
        render = np.clip(photo + rng.normal(0, 0.05, photo.shape), 0, 1)
        lab = rng.integers(0, 3, size=(6, 8)).astype(np.int8)  # no empty pixel
        scores.add(lab, render, photo)
        e = ((render - photo) ** 2).mean(-1)
        for k, name in enumerate(LAYERS):
            errs[name].extend(e[lab == k].tolist())
    d = scores.to_dict()
    assert "empty" not in d and sum(v["pixels"] for v in d.values()) == pytest.approx(1.0)
    for name in ("surface", "far_field", "background_sphere"):
        assert d[name]["pixels"] == pytest.approx(len(errs[name]) / (3 * 48))
        assert d[name]["psnr"] == pytest.approx(-10 * np.log10(np.mean(errs[name])), rel=1e-9)
