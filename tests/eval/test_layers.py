"""Scores by layer (trisplat.eval.layers): each pixel is labelled by the rows of the face table its face id falls in
and, among the surface rows, by whether its piece (vertices merged) is the one the views show most; each layer's PSNR
pools its pixels' squared errors over the views."""
import numpy as np
import pytest

from trisplat.eval.layers import LAYERS, LayerScores, face_layers, layer_labels, main_piece, surface_pieces


def test_labels_follow_the_face_tables_rows_and_the_pieces():
    # 10 faces: rows 0-5 the surface rows (pieces 0,0,1,1,0,2), 6-9 the far field, of which 8-9 the background sphere
    fid = np.array([[-1, 0, 5], [6, 7, 8], [9, 3, -1]])
    of_face = face_layers(10, far_faces=4, background_faces=2, piece=np.array([0, 0, 1, 1, 0, 2]), main_piece=1)
    names = np.array(LAYERS)[layer_labels(fid, of_face)]
    assert names.tolist() == [["empty", "other_pieces", "other_pieces"],
                              ["far_field", "far_field", "background_sphere"],
                              ["background_sphere", "surface", "empty"]]
    # no far field, no pieces given: everything drawn is surface
    assert (np.array(LAYERS)[layer_labels(fid, face_layers(10, 0, 0))][fid >= 0] == "surface").all()


def test_pieces_merge_coincident_vertices_and_the_main_piece_is_the_most_seen():
    # two triangles sharing an edge through duplicated vertices (an unwelded export) are one piece; a third apart
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]],
                   float)
    faces = np.array([[0, 1, 2], [3, 5, 4], [6, 7, 8], [0, 1, 2]])  # the last row: the far field
    piece = surface_pieces(pos, faces, 3)
    assert piece[0] == piece[1] != piece[2]
    # the far piece by faces is smaller, but the views show it most: it is the surface
    views = [np.array([[2, 2, 2, 0, -1, 3]]), np.array([[2, 1, 2]])]
    assert main_piece(views, piece) == piece[2]


def test_bad_layer_sizes_and_face_ids_are_refused():
    with pytest.raises(ValueError, match="background_faces"):
        face_layers(10, far_faces=2, background_faces=3)
    with pytest.raises(ValueError, match="surface rows"):
        face_layers(10, far_faces=2, background_faces=0, piece=np.zeros(3, int))
    with pytest.raises(ValueError, match="face ids"):
        layer_labels(np.array([[10]]), face_layers(10, 0, 0))


def test_scores_pool_squared_errors_per_layer_over_views():
    rng = np.random.default_rng(0)
    scores = LayerScores()
    errs = {name: [] for name in LAYERS}
    for _ in range(3):
        photo = rng.random((6, 8, 3))
        render = np.clip(photo + rng.normal(0, 0.05, photo.shape), 0, 1)
        lab = rng.integers(0, 4, size=(6, 8)).astype(np.int8)  # no empty pixel
        scores.add(lab, render, photo)
        e = ((render - photo) ** 2).mean(-1)
        for k, name in enumerate(LAYERS):
            errs[name].extend(e[lab == k].tolist())
    d = scores.to_dict()
    assert "empty" not in d and sum(v["pixels"] for v in d.values()) == pytest.approx(1.0)
    for name in ("surface", "other_pieces", "far_field", "background_sphere"):
        assert d[name]["pixels"] == pytest.approx(len(errs[name]) / (3 * 48))
        assert d[name]["psnr"] == pytest.approx(-10 * np.log10(np.mean(errs[name])), rel=1e-9)
