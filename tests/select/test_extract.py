"""Object extraction from masks: IoU on the generated two-object scene, vote counting, hidden-face filling, splitting."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from trisplat.select import count_votes, extract_faces, face_id_maps, fill_hidden_faces, split_mesh
from trisplat.synth import orbit_cameras, raycast_view, render_face_ids, two_object_mesh

OBJECT = 1
MIN_IOU = 0.9


def _iou(a, b):
    return (a & b).sum() / (a | b).sum()


def _segmenter_masks(mesh, label, cameras, obj=OBJECT, samples=4):
    """Masks as a perfect segmenter would draw them: pixels at least half covered by the visible object (made from
    a 4x4-supersampled render in which the object is white and everything else black)."""
    flat = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    white = np.where((label == obj)[:, None], 255, 0).astype(np.uint8)
    flat.visual = trimesh.visual.ColorVisuals(flat, face_colors=np.c_[white, white, white, np.full_like(white, 255)])
    return {
        i: raycast_view(flat, c, background=(0, 0, 0), samples_per_pixel=samples).rgba[..., 0] >= 0.5
        for i, c in enumerate(cameras)
    }


def _available_renderers():
    out = ["raycast"]
    try:
        from trisplat.render import rasterize_hard  # noqa: F401

        out.append("hard")
    except ImportError:
        pass
    return out


@pytest.fixture(scope="module")
def scene():
    mesh, label = two_object_mesh()
    cams = orbit_cameras(12, 3.0, 96, 96, fov_deg=40, seed=0, elevation_deg=(-70, 70))
    return mesh, label, cams, _segmenter_masks(mesh, label, cams)


@pytest.mark.parametrize("error_px", [-2, 2])
def test_extraction_survives_sloppy_masks(scene, error_px):
    """Masks eroded or dilated by 2 pixels (a sloppy segmenter) still give the object."""
    from scipy import ndimage

    mesh, label, cams, masks = scene
    op = ndimage.binary_dilation if error_px > 0 else ndimage.binary_erosion
    sloppy = {i: op(m, iterations=abs(error_px)) for i, m in masks.items()}
    sel = extract_faces(mesh.vertices, mesh.faces, cams, sloppy, renderer="raycast")
    assert _iou(sel, label == OBJECT) >= MIN_IOU


@pytest.mark.parametrize("renderer", _available_renderers())
def test_extraction_iou_on_two_object_scene(scene, renderer):
    mesh, label, cams, masks = scene
    truth = label == OBJECT
    sel, votes = extract_faces(mesh.vertices, mesh.faces, cams, masks, ratio=0.5, renderer=renderer, return_votes=True)
    iou = _iou(sel, truth)
    assert iou >= MIN_IOU, f"IoU {iou:.3f}"
    # the other object is never taken: its faces get (almost) no masked votes
    assert (sel & (label == 2)).sum() <= 2
    # every selected face was seen, and extracting the other object with its own masks gives the complement
    assert votes.seen[sel].all()
    other = extract_faces(
        mesh.vertices, mesh.faces, cams, _segmenter_masks(mesh, label, cams, obj=2), renderer=renderer
    )
    assert _iou(other, label == 2) >= MIN_IOU


def test_hidden_underside_stays_out_unless_filled():
    mesh, label = two_object_mesh(ground=True)
    cams = orbit_cameras(10, 3.0, 96, 96, fov_deg=40, seed=1, elevation_deg=(15, 70))  # never from below
    masks = _segmenter_masks(mesh, label, cams)
    truth = label == OBJECT
    sel, votes = extract_faces(mesh.vertices, mesh.faces, cams, masks, renderer="raycast", return_votes=True)
    unseen_obj = truth & ~votes.seen
    assert unseen_obj.sum() > 0.15 * truth.sum()  # the sphere's underside is hidden from every view ...
    assert not sel[unseen_obj].any()  # ... and stays unselected by default
    filled = extract_faces(mesh.vertices, mesh.faces, cams, masks, renderer="raycast", fill_hidden=True)
    assert _iou(filled, truth) >= 0.97 and _iou(filled, truth) > _iou(sel, truth)
    assert not filled[label == 0].any() and not filled[label == 2].any()  # the ground and the cube stay out


def test_count_votes_and_ratio_threshold_by_hand():
    # 3 faces; view A: face 0 fully masked (4 px), face 1 half masked (2 of 4); view B: face 1 unmasked (2 px)
    fid_a = np.array([[0, 0, 1, 1], [0, 0, 1, 1], [-1, -1, 2, -1]])
    m_a = np.array([[1, 1, 1, 0], [1, 1, 1, 0], [1, 0, 0, 0]], bool)
    fid_b = np.array([[1, 1, -1, -1]])
    m_b = np.zeros((1, 4), bool)
    v = count_votes([fid_a, fid_b], [m_a, m_b], 4)
    np.testing.assert_array_equal(v.inside, [4, 2, 0, 0])
    np.testing.assert_array_equal(v.outside, [0, 4, 1, 0])
    assert v.unmatched_mask_pixels == 1
    np.testing.assert_allclose(v.ratio()[:3], [1.0, 1 / 3, 0.0])
    assert np.isnan(v.ratio()[3]) and list(v.seen) == [True, True, True, False]
    with pytest.raises(ValueError, match="mask is 4x1 pixels but the render is 4x3"):
        count_votes([fid_a], [m_b], 4)


def test_fill_hidden_faces_on_a_strip():
    # a strip of 6 quads along x whose 12 faces form a chain of edge neighbours 0-1-2-...-11; faces 4-5 and 10-11
    # are unseen
    # (vertices 0-6 along the bottom edge, 7-13 along the top; only the connectivity matters)
    faces = np.concatenate([[[i, i + 1, i + 8], [i, i + 8, i + 7]] for i in range(6)])
    seen = np.ones(12, bool)
    seen[[4, 5, 10, 11]] = False
    sel = np.zeros(12, bool)
    sel[:4] = True
    # the patch 4-5 borders face 3 (selected) and face 6 (not): half its border is selected
    np.testing.assert_array_equal(np.nonzero(fill_hidden_faces(faces, sel, seen, ratio=0.75))[0], [0, 1, 2, 3])
    np.testing.assert_array_equal(np.nonzero(fill_hidden_faces(faces, sel, seen, ratio=0.5))[0], np.arange(6))
    sel[6:8] = True  # now the patch 4-5 is enclosed by selected faces; 10-11 border only unselected face 9
    out = fill_hidden_faces(faces, sel, seen, ratio=0.75)
    np.testing.assert_array_equal(np.nonzero(out)[0], np.arange(8))


def test_bad_arguments_are_precise():
    mesh, _ = two_object_mesh()
    cams = orbit_cameras(2, 3.0, 32, 24, seed=0)
    good = {0: np.ones((24, 32), bool)}
    with pytest.raises(ValueError, match=r"mask for camera 0 .* is 24x32 pixels, its image is 32x24"):
        extract_faces(mesh.vertices, mesh.faces, cams, {0: np.ones((32, 24), bool)})
    with pytest.raises(ValueError, match="ratio must be in"):
        extract_faces(mesh.vertices, mesh.faces, cams, good, ratio=0)
    with pytest.raises(ValueError, match="mask for camera index 5, but there are 2 cameras"):
        extract_faces(mesh.vertices, mesh.faces, cams, {5: good[0]})
    with pytest.raises(ValueError, match="renderer must be one of"):
        list(face_id_maps(mesh.vertices, mesh.faces, cams, renderer="nope"))


def test_raycast_face_ids_match_synth_renderer():
    mesh, _ = two_object_mesh()
    cams = orbit_cameras(2, 3.0, 40, 40, seed=2)
    for got, ref in zip(face_id_maps(mesh.vertices, mesh.faces, cams, renderer="raycast"), render_face_ids(mesh, cams)):
        np.testing.assert_array_equal(got, ref)


def test_split_mesh_partitions_faces_and_compacts_vertices():
    mesh, label = two_object_mesh()
    colors = mesh.visual.vertex_colors[:, :3] / 255.0
    obj, rest = split_mesh(mesh.vertices, mesh.faces, colors, label == 1)
    assert len(obj.faces) + len(rest.faces) == len(mesh.faces)
    np.testing.assert_array_equal(np.sort(np.r_[obj.face_index, rest.face_index]), np.arange(len(mesh.faces)))
    for part in (obj, rest):
        np.testing.assert_allclose(part.positions[part.faces], mesh.vertices[mesh.faces[part.face_index]])
        np.testing.assert_allclose(part.colors, colors[part.vertex_index])
        assert len(np.unique(part.faces)) == len(part.positions)  # no unused vertices
    assert len(obj.positions) == len(np.unique(mesh.faces[label == 1]))


def test_soft_renderer_face_ids_agree_with_ray_casting(scene):
    """The splatting renderer at a near-zero sigma shows the same faces as a z-buffer (ray casting), so extraction
    through it finds the object too."""
    pytest.importorskip("trisplat.render")
    mesh, label, cams, masks = scene
    soft = list(face_id_maps(mesh.vertices, mesh.faces, cams[:3], renderer="soft"))
    ref = list(face_id_maps(mesh.vertices, mesh.faces, cams[:3], renderer="raycast"))
    for s, r in zip(soft, ref):
        assert (s == r).mean() >= 0.99
    sel = extract_faces(mesh.vertices, mesh.faces, cams, masks, renderer="soft")
    assert _iou(sel, label == OBJECT) >= MIN_IOU
