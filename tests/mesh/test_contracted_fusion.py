"""Scene contraction and the sparse contracted fusion: the map and its inverse agree, keep orientation and the inner
cube; the sparse field equals the dense fusion's where both are defined; far walls of a room seen from inside come
out as one surface where they are, at a cost that does not grow with their distance."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from tests.mesh.test_fusion import fibonacci_cameras, look_at, sphere_depth
from trisplat.cameras import Camera
from trisplat.mesh.contracted_fusion import BLOCK, ContractedGrid, ContractedTSDF, fuse_contracted
from trisplat.mesh.cleanup import face_components
from trisplat.mesh.contraction import contract, contract_point, outer_extent, stretch, uncontract, uncontract_point
from trisplat.mesh.fusion import TSDFVolume, extract_surface
from trisplat.mesh.stats import mesh_statistics


def test_contraction_inverse_inner_cube_and_formula():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-1, 1, (200, 3)), rng.normal(0, 5, (500, 3)), rng.standard_cauchy((300, 3))])
    y = contract(x)
    assert np.abs(y).max() < 2.0
    np.testing.assert_allclose(uncontract(y), x, rtol=1e-9, atol=1e-9)
    inner = np.abs(x).max(1) <= 1
    np.testing.assert_array_equal(y[inner], x[inner])
    # the formula, written out for one point: m = 4 (the y axis), every coordinate times (2 - 1/m) / m
    np.testing.assert_allclose(contract(np.array([[1.0, -4.0, 2.0]])), [[1.75 / 4, -1.75, 1.75 / 2]])
    # continuous across the boundary between two axes' pyramids (a wall crossing it stays in one piece)
    np.testing.assert_allclose(contract(np.array([[5.0, 5.0 - 1e-9, 0.0]])), contract(np.array([[5.0 - 1e-9, 5.0, 0.0]])),
                               atol=1e-8)
    # the compiled twins agree with the numpy maps
    for p, q in zip(x[:50], y[:50]):
        np.testing.assert_allclose(contract_point(*p), q, rtol=1e-12, atol=1e-12)
        out = uncontract_point(*q)
        np.testing.assert_allclose(out[:3], p, rtol=1e-9, atol=1e-9)
        assert out[3] == pytest.approx(stretch(q[None])[0])
    with pytest.raises(ValueError, match="infinitely far"):
        uncontract(np.array([[2.0, 0.0, 0.0]]))


def test_contraction_keeps_orientation_and_stretch_is_the_radial_derivative():
    rng = np.random.default_rng(1)
    y = rng.uniform(-1.95, 1.95, (300, 3))
    h = 1e-6
    for q in y:
        J = np.stack([(uncontract((q + h * e)[None])[0] - uncontract((q - h * e)[None])[0]) / (2 * h)
                      for e in np.eye(3)], 1)
        assert np.linalg.det(J) > 0  # orientation kept: outward stays outward
        u = q / np.abs(q).max()  # the radial direction, scaled so that one unit of it is one unit of the norm
        radial = (uncontract((q + h * u)[None])[0] - uncontract((q - h * u)[None])[0]) / (2 * h)
        assert np.abs(radial).max() == pytest.approx(stretch(q[None])[0], rel=1e-4)
    assert stretch(np.array([[1.0, 0.3, 0.0]]))[0] == pytest.approx(1.0)  # continuous at the inner cube's face
    assert outer_extent(4.0) == pytest.approx(1.75)


def test_grid_for_resolution_reaches_the_extent_and_not_infinity():
    g = ContractedGrid.for_resolution(64, outer_extent(4.0))
    assert g.voxel == pytest.approx(2 / 64) and g.size % BLOCK == 0
    assert outer_extent(4.0) <= g.extent < 2.0
    g = ContractedGrid.for_resolution(64, outer_extent(100.0))  # whole blocks short of infinity
    assert 2.0 - BLOCK * g.voxel <= g.extent < 2.0 - 0.5 * g.voxel
    with pytest.raises(ValueError, match="extent"):
        ContractedGrid.for_resolution(64, 2.0)


def test_sparse_field_equals_the_dense_fusion_in_the_inner_cube():
    # a sphere inside the inner cube, cameras on a sphere of radius 0.95 around it (inside the inner cube too)
    centre, r = np.array([0.05, -0.02, 0.0]), 0.35
    cams = fibonacci_cameras(16, radius=0.95)
    depths = [sphere_depth(c, centre, r) for c in cams]
    grid = ContractedGrid.for_resolution(48, 1.2)  # voxel 2/48; the inner cube's voxels align with the dense grid's
    vol = fuse_contracted(cams, depths, grid, truncation_voxels=3.0, max_depth_voxels=6.0)
    sdf = vol.field()
    dense = TSDFVolume(np.array([[-1.0] * 3, [1.0] * 3]), 48, truncation_voxels=3.0)
    dense.integrate(cams, depths)
    field, dense_band = dense.grid(max_depth=6.0 * grid.voxel).sdf, dense.band
    shift = round((grid.extent - 1.0) / grid.voxel)
    ijk = vol.coords[:, None, :] * BLOCK + np.stack(np.unravel_index(np.arange(BLOCK**3), (BLOCK,) * 3), 1)[None]
    ijk = ijk.reshape(-1, 3) - shift
    inside = ((ijk >= 0) & (ijk < 48)).all(1)
    expect = field[tuple(ijk[inside].T)]
    got = sdf.reshape(-1)[inside]
    band = dense_band[tuple(ijk[inside].T)]  # where a view measured the surface: no cut of unseen space there
    assert band.sum() > 500
    np.testing.assert_allclose(got[band], expect[band], atol=1e-5)
    np.testing.assert_array_equal(vol.band.reshape(-1)[inside], band)
    # the surfaces: the same as the dense grid's on the sphere (the same field there), within a voxel or two
    # elsewhere (the cut of unseen space behind it, from the coarser distance transform)
    v, f = vol.surface()
    x = uncontract(v)
    dv, df = extract_surface(dense.grid(max_depth=6.0 * grid.voxel))
    gap = cKDTree(dv).query(x)[0] / grid.voxel
    near = np.abs(np.linalg.norm(x - centre, axis=1) - r) < 2 * grid.voxel
    assert near.sum() > 1000 and gap[near].max() < 1e-3
    assert np.percentile(gap, 95) < 1.5 and np.percentile(cKDTree(x).query(dv)[0] / grid.voxel, 95) < 1.5
    n, label = face_components(f, len(v))
    assert n == pytest.approx(face_components(df, len(dv))[0], rel=0.3)


def _box_room_depth(cam: Camera, half: float) -> np.ndarray:
    """View depth of the inside of the axis-aligned cube [-half, half]^3 seen from within it."""
    H, W = cam.height, cam.width
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(cam.K).T  # camera frame, z = 1
    R, t = cam.world_to_camera[:3, :3], cam.world_to_camera[:3, 3]
    o = -R.T @ t
    d = rays @ R  # world directions (rows of R.T applied)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(d > 0, (half - o) / d, np.where(d < 0, (-half - o) / d, np.inf)).min(-1)
    return s.astype(np.float32)  # ray z-component is 1 in the camera frame: s is the view depth


@pytest.mark.parametrize("half,res", [(3.0, 32), (6.0, 128)])
def test_room_seen_from_inside_is_one_closed_surface_on_its_walls(half, res):
    # cameras near the centre of a cube room looking out in every direction: walls, floor and ceiling far beyond
    # the inner cube. The fused surface is one piece on the walls (within the depth of a contracted voxel there)
    i = np.arange(20) + 0.5
    phi, theta = np.arccos(1 - 2 * i / 20), np.pi * (1 + 5**0.5) * i
    dirs = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    cams = [look_at(0.1 * d, target=3 * d, size=48, focal=24.0) for d in dirs]
    depths = [_box_room_depth(c, half) for c in cams]
    grid = ContractedGrid.for_resolution(res, outer_extent(1.5 * half))
    assert grid.extent > outer_extent(half)  # (the walls inside the grid)
    vol = fuse_contracted(cams, depths, grid, truncation_voxels=3.0, max_depth_voxels=6.0)
    v, f = vol.surface(drop_cavities=False)  # the room's inside is what its walls enclose: no cavity rule here
    x = uncontract(v)
    m = np.abs(x).max(1)
    depth_of_voxel = grid.voxel * stretch(v)
    # the walls seen from inside: within a voxel's depth of the true walls, their normals pointing into the room
    # (where the cameras are); behind them the unseen shell's back, facing away from the room
    t = x[f]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = t.mean(1)
    cm = np.abs(c).max(1)
    seen = np.abs(cm - half) < 0.05 * half  # (the unseen back lies a few voxels behind: far more, in the world)
    assert seen.mean() > 0.4
    a = np.abs(c[seen]).argmax(1)  # the wall each face is on
    rows = np.arange(len(a))
    inward = -np.sign(c[seen][rows, a]) * n[seen][rows, a]
    assert np.median(inward) > 0.8 and (inward > 0).mean() > 0.85  # (normals of a staircase: not all straight)
    assert np.all(m - half > -1.5 * depth_of_voxel)  # nothing in the room's free space
    st = mesh_statistics(v, f)
    assert st.connected_components <= 2  # the walls' inside, and the back of the unseen shell behind them
    # with the cavity rule (for objects seen from outside) the room's inside walls would go: they enclose free space
    v2, f2 = vol.surface()
    assert not (np.abs(np.abs(uncontract(v2)).max(1) - half) < 0.05 * half).any()
    if half > 3.0:
        return
    # sparse: twice the resolution allocates about 4x the voxels (the walls' area), not 8x (the volume)
    coarse, fine = (fuse_contracted(cams, depths, ContractedGrid.for_resolution(r, outer_extent(1.5 * half)), 3.0, 6.0)
                    for r in (64, 128))
    assert fine.allocated_voxels < 5.0 * coarse.allocated_voxels


def test_allocate_after_integrate_is_refused():
    cam = look_at([0.0, 0.0, 0.9], size=16, focal=16.0)
    d = np.full((16, 16), 0.9, np.float32)
    vol = ContractedTSDF(ContractedGrid.for_resolution(16, 1.5))
    vol.allocate(cam, d)
    vol.integrate([cam], [d])
    with pytest.raises(RuntimeError, match="allocate every view first"):
        vol.allocate(cam, d)
    with pytest.raises(ValueError, match="depth map 0 is 8x8"):
        ContractedTSDF(ContractedGrid.for_resolution(16, 1.5)).allocate(cam, np.ones((8, 8), np.float32))
