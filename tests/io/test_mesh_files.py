"""Round trips of the coloured-mesh formats (.ply, .obj + .mtl, .glb), up-axis rotations and input errors."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from trisplat.cameras import Camera
from trisplat.io import FORMATS, estimate_capture_up, export_mesh, load_mesh, up_rotation

COLOR_TOLERANCE = 0.5 / 255 + 1e-6  # colours are stored as 8-bit


def _mesh(seed: int = 0):
    m = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(seed)
    positions = (m.vertices * [1.0, 2.0, 0.5] + [10.0, -3.0, 0.25]).astype(np.float32)
    return positions, m.faces.astype(np.int32), rng.random((len(positions), 3))


@pytest.mark.parametrize("suffix", sorted(FORMATS))
def test_round_trip_keeps_positions_faces_and_colours(tmp_path, suffix):
    positions, faces, colors = _mesh()
    written = export_mesh(tmp_path / f"m{suffix}", positions, faces, colors, up=None)  # None: axes as given
    assert written[0] == tmp_path / f"m{suffix}"
    p, f, c = load_mesh(written[0])
    np.testing.assert_array_equal(p, positions)
    np.testing.assert_array_equal(f, faces)
    assert c is not None and np.abs(c - colors).max() <= COLOR_TOLERANCE


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_uncoloured_mesh_reads_back_without_colours(tmp_path, suffix):
    positions, faces, _ = _mesh()
    p, f, c = load_mesh(export_mesh(tmp_path / f"m{suffix}", positions, faces)[0])
    assert c is None
    np.testing.assert_array_equal(f, faces)


def test_obj_comes_with_mtl_and_vertex_colour_lines(tmp_path):
    positions, faces, colors = _mesh()
    written = export_mesh(tmp_path / "m.obj", positions, faces, colors)
    assert written == [tmp_path / "m.obj", tmp_path / "m.mtl"]
    text = (tmp_path / "m.obj").read_text().splitlines()
    assert "mtllib m.mtl" in text and "usemtl default" in text
    first_v = next(line for line in text if line.startswith("v "))
    assert len(first_v.split()) == 7  # v x y z r g b
    mtl = (tmp_path / "m.mtl").read_text()
    assert "newmtl default" in mtl and "Kd 1 1 1" in mtl


def test_ply_is_binary_with_uchar_rgb(tmp_path):
    positions, faces, colors = _mesh()
    export_mesh(tmp_path / "m.ply", positions, faces, colors)
    header = (tmp_path / "m.ply").read_bytes().split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in header
    for ch in ("red", "green", "blue"):
        assert f"property uchar {ch}" in header


def test_reads_meshes_written_by_another_tool(tmp_path):
    positions, faces, colors = _mesh()
    rgba = np.column_stack([np.round(colors * 255), np.full(len(colors), 255)]).astype(np.uint8)
    trimesh.Trimesh(positions, faces, vertex_colors=rgba, process=False).export(tmp_path / "other.ply")
    p, f, c = load_mesh(tmp_path / "other.ply")
    np.testing.assert_array_equal(f, faces)
    assert np.abs(c - colors).max() <= COLOR_TOLERANCE


def test_transform_then_up_rotation_known_answers(tmp_path):
    positions = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], np.float32)
    faces = np.array([[0, 1, 2]])
    T = np.eye(4)
    T[:3, :3] *= 2.0
    T[:3, 3] = [1.0, 0.0, 0.0]
    # transform: (1,2,3) -> (3,4,6); up='y' turns a Z-up capture Y-up: (x, y, z) -> (x, z, -y)
    p, _, _ = load_mesh(export_mesh(tmp_path / "y.ply", positions, faces, up="y", transform=T)[0])
    np.testing.assert_allclose(p[0], [3.0, 6.0, -4.0], atol=1e-6)
    # up='z' turns a Y-up capture Z-up: (x, y, z) -> (x, -z, y)
    p, _, _ = load_mesh(export_mesh(tmp_path / "z.ply", positions, faces, up="z")[0])
    np.testing.assert_allclose(p[0], [1.0, -3.0, 2.0], atol=1e-6)
    # an explicit capture up (COLMAP-like, -Y) is mapped onto +Z by a proper rotation
    R = up_rotation("z", capture_up=np.array([0.0, -1.0, 0.0]))[:3, :3]
    np.testing.assert_allclose(R @ [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_mirroring_transform_keeps_normals_outward(tmp_path):
    box = trimesh.creation.box()
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    p, f, _ = load_mesh(export_mesh(tmp_path / "b.ply", box.vertices, box.faces, transform=mirror)[0])
    out = trimesh.Trimesh(p, f, process=False)
    centre_dirs = out.triangles_center - out.vertices.mean(0)
    assert (np.einsum("ij,ij->i", out.face_normals, centre_dirs) > 0).all()
    assert out.volume > 0


def test_estimate_capture_up_from_upright_cameras():
    cams = []
    for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        centre = np.array([3 * np.cos(a), 3 * np.sin(a), 1.0])  # a ring above a Z-up ground
        fwd = -centre / np.linalg.norm(centre)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ centre
        cams.append(Camera(w2c, np.diag([100.0, 100.0, 1.0]), 64, 64))
    np.testing.assert_array_equal(estimate_capture_up(cams), [0.0, 0.0, 1.0])  # snapped onto the axis
    tilted = np.eye(4)
    tilted[:3, :3] = trimesh.transformations.rotation_matrix(np.radians(30), [1, 0, 0])[:3, :3]
    up = estimate_capture_up([Camera(c.world_to_camera @ tilted.T, c.K, 64, 64) for c in cams])
    np.testing.assert_allclose(up, tilted[:3, :3] @ [0.0, 0.0, 1.0], atol=1e-9)  # 30 degrees off: kept as is
    assert estimate_capture_up([]) is None


def test_bad_input_gets_precise_errors(tmp_path):
    positions, faces, colors = _mesh()
    with pytest.raises(ValueError, match=r"m\.stl: unknown mesh format '\.stl'"):
        export_mesh(tmp_path / "m.stl", positions, faces)
    with pytest.raises(ValueError, match="faces index vertices outside"):
        export_mesh(tmp_path / "m.ply", positions, faces + len(positions))
    with pytest.raises(ValueError, match=r"colors must be finite and in \[0, 1\]"):
        export_mesh(tmp_path / "m.ply", positions, faces, colors * 2)
    with pytest.raises(ValueError, match="up axis must be None, 'y' or 'z'"):
        export_mesh(tmp_path / "m.ply", positions, faces, up="x")
    with pytest.raises(FileNotFoundError, match="nothere.ply: no such mesh file"):
        load_mesh(tmp_path / "nothere.ply")
    (tmp_path / "junk.glb").write_bytes(b"not a glb at all")
    with pytest.raises(ValueError, match="junk.glb"):
        load_mesh(tmp_path / "junk.glb")


def test_textured_obj_gets_its_texture_sampled_at_the_vertices(tmp_path):
    from PIL import Image

    texture = np.zeros((8, 8, 3), np.uint8)
    texture[:, :4] = [255, 0, 0]  # left half red, right half blue (u < 0.5 / u > 0.5)
    texture[:, 4:] = [0, 0, 255]
    Image.fromarray(texture).save(tmp_path / "tex.png")
    (tmp_path / "t.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd tex.png\n")
    (tmp_path / "t.obj").write_text(
        "mtllib t.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0.1 0.5\nvt 0.9 0.5\nvt 0.1 0.6\nvt 0.9 0.6\n"
        "usemtl m\nf 1/1 2/2 3/3\nf 2/2 4/4 3/3\n"
    )
    p, f, c = load_mesh(tmp_path / "t.obj")
    assert c is not None
    left = p[:, 0] < 0.5
    np.testing.assert_allclose(c[left], np.tile([1.0, 0.0, 0.0], (left.sum(), 1)), atol=0.02)
    np.testing.assert_allclose(c[~left], np.tile([0.0, 0.0, 1.0], ((~left).sum(), 1)), atol=0.02)
