"""Synthetic camera rigs: look-at cameras on a Fibonacci spiral around a centre, OpenCV axes."""
from __future__ import annotations

import math

import numpy as np

from trisplat.cameras import Camera

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))  # radians between successive spiral points


def intrinsics(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    """Pinhole K [3,3] with horizontal field of view `fov_x_deg` (degrees), square pixels, centred principal point."""
    if not 0.0 < fov_x_deg < 180.0:
        raise ValueError(f"fov_deg must be in (0, 180) degrees, got {fov_x_deg}")
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera [4,4] (OpenCV: x right, y down, z towards `target`) for a camera at `eye`.

    `up` is the world direction that appears upwards in the image; when the view is (nearly) parallel to it,
    another axis is used so the result is always a proper rotation.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    n = np.linalg.norm(z)
    if n == 0:
        raise ValueError("look_at: eye and target coincide")
    z /= n
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-8 * np.linalg.norm(up):
        alt = np.eye(3)[int(np.argmin(np.abs(z)))]
        x = np.cross(z, alt)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def orbit_cameras(
    n: int,
    radius: float,
    width: int,
    height: int,
    fov_deg: float = 40.0,
    center=(0.0, 0.0, 0.0),
    seed: int = 0,
    elevation_deg: tuple[float, float] = (10.0, 80.0),
    up=(0.0, 0.0, 1.0),
    name_prefix: str = "view",
) -> list[Camera]:
    """`n` cameras at distance `radius` from `center`, all looking at it, spread evenly over a band of elevations.

    Positions follow a Fibonacci spiral over the spherical zone between elevation_deg[0] and elevation_deg[1]
    (degrees above the plane orthogonal to `up`; (10, 80) is the upper hemisphere without its rim and pole,
    (-90, 90) the whole sphere), so each camera covers an equal area. `seed` rotates the spiral about `up`.
    fov_deg is the horizontal field of view; pixels are square; the principal point is the image centre.
    """
    if n < 1:
        raise ValueError(f"orbit_cameras: n must be >= 1, got {n}")
    if radius <= 0:
        raise ValueError(f"orbit_cameras: radius must be > 0, got {radius}")
    lo, hi = sorted(float(e) for e in elevation_deg)
    if lo < -90.0 or hi > 90.0:
        raise ValueError(f"orbit_cameras: elevations must lie in [-90, 90] degrees, got {elevation_deg}")
    up = np.asarray(up, dtype=np.float64)
    up /= np.linalg.norm(up)
    # an orthonormal frame (a, b, up)
    a = np.cross(up, np.eye(3)[int(np.argmin(np.abs(up)))])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    K = intrinsics(width, height, fov_deg)
    center = np.asarray(center, dtype=np.float64)
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0.0, 2.0 * math.pi)
    s_lo, s_hi = math.sin(math.radians(lo)), math.sin(math.radians(hi))
    cams = []
    for i in range(n):
        s = s_lo + (s_hi - s_lo) * (i + 0.5) / n  # uniform in sin(elevation) = uniform in area
        c = math.sqrt(max(0.0, 1.0 - s * s))
        az = phase + i * GOLDEN_ANGLE
        direction = c * math.cos(az) * a + c * math.sin(az) * b + s * up
        eye = center + radius * direction
        cams.append(Camera(world_to_camera=look_at(eye, center, up), K=K.copy(), width=width, height=height,
                           name=f"{name_prefix}_{i:03d}"))
    return cams
