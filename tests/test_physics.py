"""Physics-ready exports: MuJoCo loads exported meshes as static collision geometry and a dropped sphere rests on them."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from trisplat.io import export_mesh, load_mesh

mujoco = pytest.importorskip("mujoco", reason="mujoco is not installed (pip install mujoco, part of the test extra)")

SPHERE_RADIUS = 0.1  # metres
SETTLE_TIME_S = 5.0  # simulated seconds before the sphere is checked
REST_SPEED = 2e-2  # m/s: slower than this counts as at rest
HEIGHT_TOLERANCE = 0.01  # metres between the sphere centre and surface + radius
ROLLING_FRICTION = 0.02  # MuJoCo torsional/rolling coefficients (m): a rolling ball stops within SETTLE_TIME_S
PRISM_DEPTH = 0.05  # metres: each surface triangle becomes a convex prism this deep below it


def _simulate(assets_xml: str, geoms_xml: str, start: tuple[float, float, float], meshdir: str = ".") -> tuple:
    xml = f"""
<mujoco>
  <compiler meshdir="{meshdir}"/>
  <option timestep="0.002" gravity="0 0 -9.81"/>
  <asset>{assets_xml}</asset>
  <worldbody>
    {geoms_xml}
    <body name="ball" pos="{start[0]} {start[1]} {start[2]}">
      <freejoint/>
      <geom type="sphere" size="{SPHERE_RADIUS}" mass="0.1" condim="6" friction="0.8 {ROLLING_FRICTION} {ROLLING_FRICTION}"/>
    </body>
  </worldbody>
</mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    for _ in range(int(SETTLE_TIME_S / model.opt.timestep)):
        mujoco.mj_step(model, data)
    return data.qpos[:3].copy(), float(np.linalg.norm(data.qvel[:3]))


def test_sphere_rests_on_exported_box_loaded_by_mujoco(tmp_path):
    # a 2 x 2 x 0.5 m slab whose top sits at z = 0.5, exported Z-up (MuJoCo's convention) as OBJ + MTL
    box = trimesh.creation.box(extents=[2.0, 2.0, 0.5])
    y_up = box.vertices[:, [0, 2, 1]] * [1, 1, -1] + [0.0, 0.25, 0.0]  # the same slab in a Y-up capture frame
    colours = np.full((len(y_up), 3), 0.5)
    export_mesh(tmp_path / "slab.obj", y_up, box.faces[:, [0, 1, 2]], colours, up="z")
    pos, speed = _simulate(
        '<mesh name="slab" file="slab.obj"/>', '<geom type="mesh" mesh="slab"/>', (0.3, -0.2, 1.5), str(tmp_path)
    )
    assert speed < REST_SPEED
    assert pos[2] == pytest.approx(0.5 + SPHERE_RADIUS, abs=HEIGHT_TOLERANCE)
    assert np.allclose(pos[:2], [0.3, -0.2], atol=0.05)  # flat top: it stays where it landed


def _bowl_surface(n: int = 21, half: float = 1.0, curvature: float = 0.5):
    """A terrain-like valley z = curvature * (x^2 + y^2) on an n x n grid (non-convex from above)."""
    xs = np.linspace(-half, half, n)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    positions = np.column_stack([X.ravel(), Y.ravel(), curvature * (X.ravel() ** 2 + Y.ravel() ** 2)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])  # counter-clockwise from +z
    return positions, faces


def _static_prisms(positions: np.ndarray, faces: np.ndarray) -> tuple[str, str]:
    """MuJoCo collides meshes through their convex hulls, so a non-convex surface goes in as one thin convex
    prism per triangle (the triangle and a copy PRISM_DEPTH below it, along the inward normal)."""
    tri = positions[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    prisms = np.concatenate([tri, tri - PRISM_DEPTH * n[:, None, :]], axis=1)  # [F,6,3]
    assets = "".join(
        f'<mesh name="t{i}" vertex="{" ".join(f"{v:.7g}" for v in p.ravel())}"/>' for i, p in enumerate(prisms)
    )
    geoms = "".join(f'<geom type="mesh" mesh="t{i}"/>' for i in range(len(prisms)))
    return assets, geoms


def test_sphere_rolls_into_exported_valley_instead_of_falling_through(tmp_path):
    positions, faces = _bowl_surface()
    colours = np.clip(positions[:, [2, 2, 2]], 0, 1)
    export_mesh(tmp_path / "valley.glb", positions, faces, colours)
    p, f, _ = load_mesh(tmp_path / "valley.glb")
    np.testing.assert_array_equal(f, faces)
    # glTF is Y-up; MuJoCo is Z-up: an importer maps glTF (x, y, z) to (x, -z, y), as Blender's does
    assert np.allclose(p[:, 1], positions[:, 2], atol=1e-6), "the GLB is not Y-up"
    p = np.column_stack([p[:, 0], -p[:, 2], p[:, 1]])
    np.testing.assert_allclose(p, positions, atol=1e-6)
    assets, geoms = _static_prisms(p.astype(np.float64), f)
    # dropped over the slope, off-centre: it must land on the surface and roll down to the bottom of the valley
    pos, speed = _simulate(assets, geoms, (0.4, 0.3, 0.8))
    assert pos[2] > 0.0, f"the sphere fell through the surface (z = {pos[2]:.3f})"
    assert speed < REST_SPEED
    surface = 0.5 * (pos[0] ** 2 + pos[1] ** 2)
    assert pos[2] == pytest.approx(surface + SPHERE_RADIUS, abs=HEIGHT_TOLERANCE)
    assert np.hypot(pos[0], pos[1]) < 0.1  # at rest near the lowest point, not on the slope
