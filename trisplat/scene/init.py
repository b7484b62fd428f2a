"""Initial triangles from a capture: Delaunay faces of the sparse points, a per-point soup, a soup on the visual hull
of the silhouettes, or random soup."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from trisplat.scene.model import TriangleScene

TSPLUS_OPACITY = 0.28  # vertex opacity of the Triangle Splatting+ Delaunay initialisation
SOUP_SIZE_FACTOR = 2.23  # soup triangle circumradius / RMS distance to the SOUP_NEIGHBOURS nearest neighbours
SOUP_NEIGHBOURS = 3
DEDUP_RELATIVE_TOL = 1e-7  # points closer than this x bounding-box diagonal are duplicates (unitless)
FLAT_RELATIVE_TOL = 1e-6  # smallest / largest singular value of the centred points below this = flat set
JITTER_RELATIVE = 1e-4  # jitter amplitude for flat sets, x bounding-box diagonal
MIN_SOUP_RELATIVE_SIZE = 1e-4  # smallest soup triangle radius, x bounding-box diagonal (isolated duplicates)
# with soup_planes, the soup of a capture with sparse points (SfM, RGB-D) lies in each point's local plane: the normal of the
# POINT_NORMAL_NEIGHBOURS nearest points (PCA), where they are flat (smallest / middle spread of the covariance below
# POINT_NORMAL_FLATNESS); elsewhere the triangle keeps a random orientation (TS v1's rule). Randomly oriented,
# triangles of 2.23x the point spacing make a layer as thick as they are wide; compositing favours its front and
# pruning by blending weight keeps the front, so a wall ended where the front of that layer was: on the synthetic
# room (walls 3.4-4.6 m from the cameras) the soup's walls sat 14 cm in front of the truth after 300 steps and 35 cm
# at the switch (docs/benchmarks.md, issue 49)
POINT_NORMAL_NEIGHBOURS = 12
POINT_NORMAL_FLATNESS = 0.3
DEFAULT_RANDOM_POINTS = 10_000
# 'auto' seeds a soup, not a Delaunay tetrahedralisation, on captures whose content reaches this many times farther
# than the cameras (a room seen from inside, an unbounded real scene: bonsai 1.37-1.76 depending on the SfM run's
# outlying points, a synthetic room 2.7; fox 1.25, lego and other object captures about 1): the tetrahedra of such
# point sets span the space around the cameras, and on a CPU schedule their thousands of junk faces in front of the
# walls had to be pruned away before the walls could show (a 3-minute room trial: test PSNR 14.6 dB with Delaunay vs
# 20.3 dB with the soup after ~130 / ~380 steps). 1.5 sent bonsai to Delaunay after a re-run of its SfM (1.37): the
# ratio of a 2-98% box is not a sharp measure, and the gap between fox and bonsai is narrow (`--init` decides).
UNBOUNDED_CONTENT_RATIO = 1.3
HULL_RESOLUTION = 128  # voxels along the longest side of the box carved by the silhouettes
HULL_MAX_VIEWS = 100  # silhouettes used for carving (evenly spread over the training views)
QHULL_OPTIONS = "Qbb Qc Qz Q12"  # scipy's defaults for 3-D Delaunay
QHULL_JOGGLE_OPTIONS = "QJ Qbb"  # retry: joggled input always yields simplices


@dataclass
class InitReport:
    """What an initialisation did, in numbers and words (print `summary()`)."""

    method: str
    input_points: int
    vertices: int
    faces: int
    nonfinite_removed: int = 0
    duplicates_removed: int = 0
    subsampled_from: int | None = None
    jittered: bool = False
    fallback: str | None = None
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        s = f"{self.method}: {self.input_points} points -> {self.vertices} vertices, {self.faces} faces"
        extra = []
        if self.nonfinite_removed:
            extra.append(f"{self.nonfinite_removed} non-finite points dropped")
        if self.duplicates_removed:
            extra.append(f"{self.duplicates_removed} duplicate points merged")
        if self.subsampled_from is not None:
            extra.append(f"subsampled from {self.subsampled_from}")
        if self.jittered:
            extra.append("jittered (flat or degenerate set)")
        if self.fallback:
            extra.append(f"fell back: {self.fallback}")
        return s + (f" ({'; '.join(extra + self.notes)})" if extra or self.notes else "")


def _clean(points, colors, report: InitReport, max_points: int | None, rng: np.random.Generator):
    """Drop non-finite rows, merge duplicates (first colour kept), subsample to max_points. Returns the points, their
    colours and the input rows they came from."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    rows = np.arange(len(pts))
    cols = np.full((len(pts), 3), 0.5) if colors is None else np.asarray(colors, dtype=np.float64).reshape(-1, 3)
    if len(cols) != len(pts):
        raise ValueError(f"points [{len(pts)},3] and colors [{len(cols)},3] differ in length")
    ok = np.isfinite(pts).all(1) & np.isfinite(cols).all(1)
    report.nonfinite_removed = int((~ok).sum())
    pts, cols, rows = pts[ok], np.clip(cols[ok], 0.0, 1.0), rows[ok]
    if len(pts):
        diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
        tol = DEDUP_RELATIVE_TOL * diag if diag > 0 else 1.0
        keys = np.round((pts - pts.min(0)) / tol).astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        first.sort()
        report.duplicates_removed = len(pts) - len(first)
        pts, cols, rows = pts[first], cols[first], rows[first]
    if max_points is not None and len(pts) > max_points:
        report.subsampled_from = len(pts)
        keep = np.sort(rng.choice(len(pts), size=max_points, replace=False))
        pts, cols, rows = pts[keep], cols[keep], rows[keep]
    return pts, cols, rows


def _is_flat(pts: np.ndarray) -> bool:
    if len(pts) < 4:
        return True
    sv = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
    return bool(sv[0] == 0 or sv[-1] / sv[0] < FLAT_RELATIVE_TOL)


def tetra_faces(simplices: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Unique faces [F,3] of tetrahedra [T,4]; each oriented away from the tetrahedron it was first seen in
    (hull faces therefore point outwards)."""
    tets = np.asarray(simplices, dtype=np.int64)
    opposite_order = [(1, 2, 3, 0), (0, 3, 2, 1), (0, 1, 3, 2), (0, 2, 1, 3)]
    faces = np.concatenate([tets[:, list(o[:3])] for o in opposite_order])
    opp = np.concatenate([tets[:, o[3]] for o in opposite_order])
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    faces, opp = faces[first], opp[first]
    a, b, c = pts[faces[:, 0]], pts[faces[:, 1]], pts[faces[:, 2]]
    n = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", n, pts[opp] - a) > 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces


def init_delaunay(
    points,
    colors=None,
    opacity: float = TSPLUS_OPACITY,
    sh_degree: int = 3,
    max_points: int | None = None,
    seed: int = 0,
) -> tuple[TriangleScene, InitReport]:
    """Triangle Splatting+ initialisation: 3-D Delaunay of the (deduplicated) points, every unique tetrahedron
    face a triangle, vertex colour = point colour, opacity `opacity`, SH bands above 0 zero.

    Flat (coplanar / collinear) sets are jittered by JITTER_RELATIVE x their extent; if Qhull still fails the
    input is joggled (Qhull 'QJ'); fewer than 4 usable points fall back to a soup (init_soup). The report says
    which happened. points: [P,3]; colors: [P,3] in [0,1] (grey when None).
    """
    rng = np.random.default_rng(seed)
    report = InitReport("delaunay", input_points=int(np.asarray(points).reshape(-1, 3).shape[0]), vertices=0, faces=0)
    pts, cols, _ = _clean(points, colors, report, max_points, rng)
    if len(pts) < 4:
        scene, sub = init_soup(pts, cols, seed=seed, opacity=opacity, sh_degree=sh_degree)
        sub.method = "delaunay"
        sub.input_points = report.input_points
        sub.nonfinite_removed, sub.duplicates_removed = report.nonfinite_removed, report.duplicates_removed
        sub.fallback = f"soup ({len(pts)} distinct points are too few for a tetrahedralisation)"
        return scene, sub
    from scipy.spatial import Delaunay, QhullError

    diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    work = pts
    if _is_flat(pts):
        work = pts + rng.normal(scale=JITTER_RELATIVE * diag, size=pts.shape)
        report.jittered = True
    try:
        tri = Delaunay(work, qhull_options=QHULL_OPTIONS)
    except QhullError:
        tri = Delaunay(work, qhull_options=QHULL_JOGGLE_OPTIONS)
        report.jittered = True
        report.notes.append("Qhull needed joggled input (QJ)")
    faces = tetra_faces(tri.simplices, work)
    used = np.unique(faces)
    if len(used) < len(pts):
        report.notes.append(f"{len(pts) - len(used)} points in no tetrahedron were dropped")
        remap = np.full(len(pts), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        faces, pts, cols = remap[faces], pts[used], cols[used]
    scene = TriangleScene.from_rgb(
        pts.astype(np.float32), faces.astype(np.int32), cols.astype(np.float32), opacity, sh_degree
    )
    report.vertices, report.faces = scene.num_vertices, scene.num_faces
    return scene, report


def _random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """n uniformly random rotation matrices [n,3,3] (from random unit quaternions)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


def _tangent_rotations(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rotations [n,3,3] taking the template plane z = 0 to the plane with the given unit normals, with a random
    in-plane angle."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where((np.abs(n[:, 0]) < 0.9)[:, None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    a = np.cross(n, helper)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(n, a)
    theta = rng.random(len(n))[:, None] * 2 * np.pi
    t1 = np.cos(theta) * a + np.sin(theta) * b
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)  # columns: template x, y, z -> t1, t2, normal


def point_normals(points: np.ndarray, k: int = POINT_NORMAL_NEIGHBOURS,
                  flatness: float = POINT_NORMAL_FLATNESS) -> np.ndarray:
    """Unit normals [P,3] of a point set from the covariance of each point's k nearest points (itself included):
    the eigenvector of the smallest eigenvalue, where the neighbourhood is flat (sqrt of smallest / middle
    eigenvalue below `flatness`); NaN rows elsewhere (too few points, a line, a blob). Sign arbitrary."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.full(pts.shape, np.nan)
    if len(pts) < 4:
        return out
    k = min(int(k), len(pts))
    _, idx = cKDTree(pts).query(pts, k=k)
    nb = pts[idx] - pts[idx].mean(axis=1, keepdims=True)
    w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb) / k)  # ascending eigenvalues
    flat = np.sqrt(np.maximum(w[:, 0], 0.0)) < flatness * np.sqrt(np.maximum(w[:, 1], 0.0))
    out[flat] = v[flat, :, 0]
    return out


def soup_sizes(pts: np.ndarray, factor: float = SOUP_SIZE_FACTOR) -> np.ndarray:
    """Per-point triangle circumradius: `factor` x RMS distance to the SOUP_NEIGHBOURS nearest others."""
    from scipy.spatial import cKDTree

    n = len(pts)
    diag = float(np.linalg.norm(pts.max(0) - pts.min(0))) if n else 0.0
    floor = MIN_SOUP_RELATIVE_SIZE * diag if diag > 0 else 1e-3
    if n < 2:
        return np.full(n, floor)
    k = min(SOUP_NEIGHBOURS, n - 1)
    d, _ = cKDTree(pts).query(pts, k=k + 1)
    rms = np.sqrt(np.mean(d[:, 1:] ** 2, axis=1))
    return np.maximum(factor * rms, floor)


def init_soup(
    points,
    colors=None,
    rng: np.random.Generator | None = None,
    seed: int = 0,
    opacity: float = TSPLUS_OPACITY,
    sh_degree: int = 3,
    max_points: int | None = None,
    size_factor: float = SOUP_SIZE_FACTOR,
    normals=None,
) -> tuple[TriangleScene, InitReport]:
    """MeshSplatting / TS v1 soup: one randomly oriented equilateral triangle per point (3 private vertices),
    centred on the point, circumradius size_factor (2.23) x the RMS distance to its 3 nearest neighbours.
    With `normals` [P,3], each triangle lies in the plane through its point with that normal instead."""
    rng = rng if rng is not None else np.random.default_rng(seed)
    report = InitReport("soup", input_points=int(np.asarray(points).reshape(-1, 3).shape[0]), vertices=0, faces=0)
    pts, cols, rows = _clean(points, colors, report, max_points, rng)
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        if len(normals) != report.input_points:
            raise ValueError(f"normals [{len(normals)},3] and points [{report.input_points},3] differ in length")
        normals = normals[rows]
        bad = ~(np.isfinite(normals).all(1) & (np.linalg.norm(normals, axis=1) > 0))
        normals[bad] = rng.normal(size=(int(bad.sum()), 3))  # unusable normal: a random orientation
    n = len(pts)
    if n == 0:
        raise ValueError("cannot initialise triangles from an empty point set (no finite points)")
    ang = np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3])
    template = np.stack([np.cos(ang), np.sin(ang), np.zeros(3)], axis=1)  # unit circumradius, plane z = 0
    R = _random_rotations(n, rng) if normals is None else _tangent_rotations(normals, rng)
    verts = pts[:, None, :] + soup_sizes(pts, size_factor)[:, None, None] * np.einsum("nij,kj->nki", R, template)
    faces = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    scene = TriangleScene.from_rgb(
        verts.reshape(-1, 3).astype(np.float32),
        faces,
        np.repeat(cols, 3, axis=0).astype(np.float32),
        opacity,
        sh_degree,
    )
    report.vertices, report.faces = scene.num_vertices, scene.num_faces
    return scene, report


def init_random(
    bounds_min,
    bounds_max,
    n: int = DEFAULT_RANDOM_POINTS,
    seed: int = 0,
    opacity: float = TSPLUS_OPACITY,
    sh_degree: int = 3,
    size_factor: float = SOUP_SIZE_FACTOR,
) -> tuple[TriangleScene, InitReport]:
    """Synthetic scenes without points: n uniform random points in the box, random colours, each turned into a
    small random triangle (init_soup, circumradius size_factor x the RMS distance to 3 neighbours)."""
    lo = np.asarray(bounds_min, dtype=np.float64).reshape(3)
    hi = np.asarray(bounds_max, dtype=np.float64).reshape(3)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
        raise ValueError(f"random initialisation needs a finite box with max > min, got {lo} .. {hi}")
    if int(n) < 1:
        raise ValueError(f"random initialisation needs n >= 1 points, got {n}")
    rng = np.random.default_rng(seed)
    pts = lo + rng.random((int(n), 3)) * (hi - lo)
    cols = rng.random((int(n), 3))
    scene, report = init_soup(pts, cols, rng=rng, opacity=opacity, sh_degree=sh_degree, size_factor=size_factor)
    report.method = "random"
    report.notes.append(f"uniform in [{', '.join(f'{v:.3g}' for v in lo)}] .. [{', '.join(f'{v:.3g}' for v in hi)}]")
    return scene, report


def init_hull(
    data,
    n: int = DEFAULT_RANDOM_POINTS,
    seed: int = 0,
    opacity: float = TSPLUS_OPACITY,
    sh_degree: int = 3,
    size_factor: float = SOUP_SIZE_FACTOR,
    resolution: int = HULL_RESOLUTION,
) -> tuple[TriangleScene, InitReport]:
    """Captures with alpha masks and no points: carve the visual hull of the training silhouettes inside
    `data.bounds`, then one triangle per point sampled on its surface, lying in the surface's tangent plane, with the
    mean colour the training images show there. Raises ValueError when no training image has alpha or the carving
    leaves (almost) nothing, which means the masks and the poses disagree."""
    from trisplat.scene import hull as vh

    if int(n) < 1:
        raise ValueError(f"hull initialisation needs n >= 1 points, got {n}")
    train = np.asarray(data.train_indices)
    if len(train) > HULL_MAX_VIEWS:
        train = train[np.linspace(0, len(train) - 1, HULL_MAX_VIEWS).round().astype(int)]
    cams = [data.cameras[int(i)] for i in train]
    masks = [data.load_alpha(int(i)) for i in train]
    used = sum(m is not None for m in masks)
    if used == 0:
        raise ValueError("hull initialisation needs images with an alpha channel; this capture's training images "
                         "have none (use --init random or delaunay)")
    bounds = _content_box(data)
    grid = vh.carve(cams, masks, bounds, resolution)
    kept = int(grid.occupied.sum())
    if kept < vh.MIN_KEPT_VOXELS:
        raise ValueError(f"the visual hull of {used} silhouettes keeps only {kept} of {grid.occupied.size} voxels: "
                         "the alpha masks and the camera poses disagree (wrong poses, or masks of another scene)")
    rng = np.random.default_rng(seed)
    pts, normals = vh.surface_samples(grid, int(n), rng)
    images = [data.load_image(int(i)) if m is not None else None for i, m in zip(train, masks)]
    cols = vh.mean_colors(cams, images, masks, pts)
    scene, report = init_soup(pts, cols, rng=rng, opacity=opacity, sh_degree=sh_degree, size_factor=size_factor,
                              normals=normals)
    report.method = "hull"
    report.notes.append(f"visual hull of {grid.views} silhouettes: {kept} of {grid.occupied.size} voxels "
                        f"({resolution} along the longest side)")
    return scene, report


def _content_box(data) -> np.ndarray:
    if data.bounds is not None:
        return np.asarray(data.bounds, dtype=np.float64)
    c = np.stack([cam.center for cam in data.cameras])
    return np.stack([c.min(0), c.max(0)])


def initial_scene(
    data,
    method: str = "auto",
    sh_degree: int = 3,
    seed: int = 0,
    opacity: float = TSPLUS_OPACITY,
    max_points: int | None = None,
    random_points: int = DEFAULT_RANDOM_POINTS,
    random_size_factor: float = SOUP_SIZE_FACTOR,
    soup_planes: bool = False,
) -> tuple[TriangleScene, InitReport]:
    """Initial triangles for a SceneData: 'auto' = Delaunay of its points (a soup on them when the content reaches
    UNBOUNDED_CONTENT_RATIO x farther than the cameras and the photos have no alpha: a scene seen from inside or
    all around); without points, the visual hull of the silhouettes when the training images have alpha, else
    random points in `data.bounds`; or force 'delaunay' | 'soup' | 'hull' | 'random'. soup_planes: a soup on
    sparse points lies in their local planes (`point_normals`) instead of at random angles."""
    if method not in ("auto", "delaunay", "soup", "hull", "random"):
        raise ValueError(f"unknown initialisation method {method!r} (auto, delaunay, soup, hull, random)")
    has_points = data.points is not None and len(data.points) > 0
    if method == "delaunay" and not has_points:
        raise ValueError(f"initialisation 'delaunay' needs points, but this {data.format} capture has none "
                         "(use --init soup, hull or random)")
    has_alpha = len(data.train_indices) > 0 and data.load_alpha(int(data.train_indices[0])) is not None
    if method == "soup" and not has_points:
        # MeshSplatting's soup on any capture: one triangle per point of the visual hull's surface (alpha), else
        # per random point in the box; both initialisations are soups already
        scene, report = (init_hull(data, random_points, seed, opacity, sh_degree, random_size_factor) if has_alpha
                         else init_random(*_content_box(data), random_points, seed, opacity, sh_degree,
                                          random_size_factor))
        report.notes.append(f"soup: this {data.format} capture has no sparse points, so the soup was seeded on "
                            f"{'the visual hull' if has_alpha else 'random points in the scene box'}")
        report.method = "soup"
        return scene, report
    auto_note = None
    if method == "auto":
        unbounded = not has_alpha and data.bounds_radius > UNBOUNDED_CONTENT_RATIO * max(data.scene_radius, 1e-9)
        if has_points and unbounded:
            method = "soup"
            auto_note = (f"soup: the content reaches {data.bounds_radius / max(data.scene_radius, 1e-9):.2f}x farther "
                         "than the cameras (an unbounded scene)")
        elif has_points:
            method = "delaunay"
        elif has_alpha:
            method = "hull"
        else:
            method = "random"
    if method == "hull":
        return init_hull(data, random_points, seed, opacity, sh_degree, random_size_factor)
    if method == "delaunay":
        return init_delaunay(data.points, data.point_colors, opacity, sh_degree, max_points, seed)
    if method == "soup":
        normals = point_normals(data.points) if soup_planes else None
        scene, report = init_soup(data.points, data.point_colors, seed=seed, opacity=opacity, sh_degree=sh_degree,
                                  max_points=max_points, normals=normals)
        if normals is not None:
            report.notes.append(f"{int(np.isfinite(normals[:, 0]).sum())} of {len(normals)} sparse points flat "
                                "enough to lay their triangle in their local plane")
        if auto_note:
            report.notes.append(auto_note)
        return scene, report
    bounds = _content_box(data)
    return init_random(bounds[0], bounds[1], random_points, seed, opacity, sh_degree, random_size_factor)
