"""Walk check: can a physics engine stand on the mesh? Spheres are dropped from just above the surfaces that face up
(floor, rug, table tops, steps) where the cameras see them, and simulated against the mesh as one static concave
triangle mesh (PyBullet's Bullet BVH triangle mesh); a sphere that comes to rest with the mesh under it stands on the
surface, one that keeps falling went through a gap (between the shards of a soup, through a hole).

Everything is in the normalised frame of the run (docs/conventions.md: the cameras within the unit sphere), with
gravity 9.81 units/s^2 along -up; `up` is the cameras' mean up direction (-y of the OpenCV camera: photos are held
upright) unless given. The background sphere (the sky) is not part of the collision mesh.
PyBullet rather than MuJoCo (a test dependency too): MuJoCo collides a mesh through its convex hull, so a room would
need one convex geom per triangle; Bullet takes the room as one concave mesh.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

GRAVITY = 9.81  # units / s^2 of the normalised frame
TIMESTEP = 1.0 / 480.0  # s: at 4 radii of fall a sphere moves about a fifth of its radius per step (no tunnelling)


@dataclass(frozen=True)
class WalkConfig:
    """Settings of the walk check. Lengths in sphere radii unless said otherwise."""

    drops: int = 200
    """spheres dropped (each alone: they do not collide with one another)."""
    radius: float = 0.01
    """sphere radius, normalised units (the cameras lie within the unit sphere: 1% of that)."""
    height: float = 4.0
    """drop height above the surface point, in radii."""
    spread: float = 3.0
    """each sphere is dropped over a point up to this many radii (uniform in a disc across `up`) from a seen surface
    point: over a welded floor it lands on the floor all the same, over a soup of shards it finds the gaps."""
    up_cos: float = 0.8
    """a surface point qualifies when its face normal is within acos(up_cos) (37 degrees) of up."""
    settle_s: float = 3.0
    """simulated seconds before the spheres are checked."""
    rest_speed: float = 0.05
    """radii per second: slower than this at the end is at rest."""
    support: float = 2.0
    """a sphere whose centre has the mesh within this many radii straight below stands on the surface."""
    views_scale: float = 0.25
    """the cameras render the mesh at this fraction of their size to find surface points (cheap; points are
    spread over views and pixels)."""
    seed: int = 0


@dataclass
class Drop:
    """One sphere: where it was dropped over (target: the surface point, normalised frame), where it ended, its speed
    (radii/s) and whether it stands on the surface."""

    target: list[float]
    end: list[float]
    speed: float
    on_surface: bool
    at_rest: bool


@dataclass
class WalkReport:
    up: list[float]
    radius: float
    drops: list[Drop] = field(default_factory=list)
    faces: int = 0
    candidates: int = 0

    @property
    def on_surface(self) -> int:
        return sum(d.on_surface for d in self.drops)

    @property
    def fraction(self) -> float:
        """Share of the dropped spheres that stand on the surface."""
        return self.on_surface / max(len(self.drops), 1)

    def to_dict(self) -> dict:
        out = asdict(self)
        out.update(on_surface=self.on_surface, fell_through=len(self.drops) - self.on_surface, fraction=self.fraction,
                   at_rest=sum(d.at_rest for d in self.drops))
        return out


def up_direction(cameras: Sequence) -> np.ndarray:
    """Unit vector [3]: the mean of the cameras' up directions (-y of the OpenCV camera frame, in the world)."""
    ups = np.stack([-np.asarray(c.world_to_camera, np.float64)[1, :3] for c in cameras])
    u = ups.mean(0)
    n = np.linalg.norm(u)
    if n < 1e-6:
        raise ValueError("the cameras' up directions cancel out (no common up): give the up direction explicitly")
    return u / n


def drop_targets(positions: np.ndarray, faces: np.ndarray, cameras: Sequence, up: np.ndarray, config: WalkConfig,
                 ) -> tuple[np.ndarray, int]:
    """Up to config.drops surface points [N,3] that the cameras see on faces facing up (normal within
    acos(up_cos) of `up`, and towards the camera), spread uniformly over all such pixels of all views; and how
    many such pixels there were."""
    import torch

    from trisplat.render import rasterize_hard

    pos = torch.as_tensor(np.asarray(positions, np.float32))
    fc = torch.as_tensor(np.asarray(faces, np.int32))
    tri = np.asarray(positions, np.float64)[np.asarray(faces, np.int64)]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
    upward = normal @ up >= config.up_cos
    grey = torch.zeros((len(positions), 3))
    points = []
    for cam in cameras:
        s = config.views_scale
        W, H = max(int(cam.width * s), 8), max(int(cam.height * s), 8)
        K = np.asarray(cam.K, np.float64).copy()
        K[0] *= W / cam.width
        K[1] *= H / cam.height
        out = rasterize_hard(pos, fc, grey, torch.as_tensor(cam.world_to_camera, dtype=torch.float32),
                             torch.as_tensor(K, dtype=torch.float32), W, H)
        fid = out.face_id.numpy().reshape(H, W)
        depth = out.depth.numpy().reshape(H, W)
        rows, cols = np.nonzero(fid >= 0)
        ok = upward[fid[rows, cols]]
        rows, cols = rows[ok], cols[ok]
        if len(rows) == 0:
            continue
        rays = np.stack([cols + 0.5, rows + 0.5, np.ones(len(rows))], 1) @ np.linalg.inv(K).T
        c2w = np.linalg.inv(np.asarray(cam.world_to_camera, np.float64))
        pts = (rays * depth[rows, cols, None]) @ c2w[:3, :3].T + c2w[:3, 3]
        toward = (normal[fid[rows, cols]] * (c2w[:3, 3] - pts)).sum(1) > 0  # seen from the front
        points.append(pts[toward])
    if not points:
        return np.zeros((0, 3)), 0
    allp = np.concatenate(points)
    rng = np.random.default_rng(config.seed)
    pick = rng.choice(len(allp), size=min(config.drops, len(allp)), replace=False)
    return allp[pick], len(allp)


def _static_mesh(pb, client, positions: np.ndarray, faces: np.ndarray) -> int:
    """The mesh as one static concave body (Bullet's BVH triangle mesh). Read from a Wavefront OBJ file: PyBullet's
    in-memory call refuses meshes of more than 2^17 vertices, a file has no such limit."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory(prefix="trisplat-walk-") as tmp:
        path = Path(tmp) / "mesh.obj"
        v = np.asarray(positions, np.float64)
        f = np.asarray(faces, np.int64).reshape(-1, 3) + 1
        with open(path, "w") as fh:
            fh.write("".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in v))
            fh.write("".join(f"f {a} {b} {c}\n" for a, b, c in f))
        shape = pb.createCollisionShape(pb.GEOM_MESH, fileName=str(path), flags=pb.GEOM_FORCE_CONCAVE_TRIMESH,
                                        physicsClientId=client)
    return pb.createMultiBody(0, shape, physicsClientId=client)


def simulate_drops(positions: np.ndarray, faces: np.ndarray, targets: np.ndarray, up: np.ndarray,
                   config: WalkConfig) -> list[Drop]:
    """Drop one sphere over each target (config.height radii above it, moved down to just under anything that
    hangs lower over it, then moved across `up` by up to config.spread radii) onto the static mesh; each is checked
    after config.settle_s simulated seconds."""
    try:
        import pybullet as pb
    except ImportError as exc:
        raise ImportError("the walk check needs PyBullet: pip install pybullet (part of trisplat's test and bench "
                          "extras)") from exc
    r = float(config.radius)
    up = np.asarray(up, np.float64)
    client = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(*(-GRAVITY * up), physicsClientId=client)
        pb.setTimeStep(TIMESTEP, physicsClientId=client)
        mesh = _static_mesh(pb, client, positions, faces)
        pb.setCollisionFilterGroupMask(mesh, -1, 1, -1, physicsClientId=client)  # (mask -1: rays hit it too)
        # the drop point: `height` radii above the target, or just under whatever hangs lower over it
        above = targets + 1.5 * r * up
        tops = targets + (config.height + 1.0) * r * up
        hits = pb.rayTestBatch(above.tolist(), tops.tolist(), physicsClientId=client)
        frac = np.array([h[2] if h[0] >= 0 else 1.0 for h in hits])
        room = 1.5 + frac * (config.height - 0.5)  # radii of free space above the target, from 1.5
        starts = targets + np.minimum(config.height, room - 1.0)[:, None] * r * up
        rng = np.random.default_rng(config.seed)
        a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(up, a)
        rho = config.spread * r * np.sqrt(rng.random(len(targets)))
        phi = 2.0 * np.pi * rng.random(len(targets))
        starts = starts + (rho * np.cos(phi))[:, None] * a + (rho * np.sin(phi))[:, None] * b
        sphere = pb.createCollisionShape(pb.GEOM_SPHERE, radius=r, physicsClientId=client)
        balls = []
        for s in starts:
            b = pb.createMultiBody(1.0, sphere, basePosition=s.tolist(), physicsClientId=client)
            pb.changeDynamics(b, -1, lateralFriction=0.8, rollingFriction=0.2 * r, spinningFriction=0.2 * r,
                              restitution=0.0, ccdSweptSphereRadius=0.5 * r, physicsClientId=client)
            # spheres pass through one another (group 2 collides with group 1, the mesh, only): each drop is alone
            pb.setCollisionFilterGroupMask(b, -1, 2, 1, physicsClientId=client)
            balls.append(b)
        for _ in range(int(round(config.settle_s / TIMESTEP))):
            pb.stepSimulation(physicsClientId=client)
        ends = np.array([pb.getBasePositionAndOrientation(b, physicsClientId=client)[0] for b in balls])
        speeds = np.array([np.linalg.norm(pb.getBaseVelocity(b, physicsClientId=client)[0]) for b in balls]) / r
        for b in balls:
            pb.removeBody(b, physicsClientId=client)
        below = pb.rayTestBatch(ends.tolist(), (ends - config.support * r * up).tolist(), physicsClientId=client)
        supported = np.array([h[0] >= 0 for h in below])
    finally:
        pb.disconnect(client)
    return [Drop(target=[float(x) for x in t], end=[float(x) for x in e], speed=float(v), on_surface=bool(s),
                 at_rest=bool(v < config.rest_speed))
            for t, e, v, s in zip(targets, ends, speeds, supported)]


def walk_check(positions: np.ndarray, faces: np.ndarray, cameras: Sequence, config: WalkConfig = WalkConfig(),
               up: np.ndarray | None = None) -> WalkReport:
    """The walk check of a mesh (positions [V,3], faces [F,3], normalised frame) seen by `cameras`."""
    if len(faces) == 0:
        raise ValueError("the walk check needs a mesh with faces")
    up = up_direction(cameras) if up is None else np.asarray(up, np.float64) / np.linalg.norm(up)
    targets, candidates = drop_targets(positions, faces, cameras, up, config)
    rep = WalkReport(up=[float(x) for x in up], radius=float(config.radius), faces=int(len(faces)),
                     candidates=int(candidates))
    if len(targets):
        rep.drops = simulate_drops(positions, faces, targets, up, config)
    return rep


def plot_walk(report: WalkReport, positions: np.ndarray, path) -> None:
    """A top-down map (looking along -up) of the mesh's vertices (grey) and the drops: green where the sphere stands
    on the surface, red where it fell through (marked at its drop point)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    up = np.asarray(report.up)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    rng = np.random.default_rng(0)
    v = np.asarray(positions)[rng.choice(len(positions), size=min(len(positions), 60_000), replace=False)]
    fig, ax = plt.subplots(figsize=(6, 6), dpi=100)
    ax.scatter(v @ a, v @ b, s=0.2, c="0.75", linewidths=0)
    t = np.array([d.target for d in report.drops]).reshape(-1, 3)
    ok = np.array([d.on_surface for d in report.drops], bool)
    ax.scatter(t[ok] @ a, t[ok] @ b, s=12, c="tab:green", label=f"stands on the surface ({int(ok.sum())})")
    ax.scatter(t[~ok] @ a, t[~ok] @ b, s=16, c="tab:red", marker="x", label=f"fell through ({int((~ok).sum())})")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("walk check (seen from above)", fontsize=10)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
