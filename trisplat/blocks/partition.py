"""Cut a scene into blocks: cells of its ground plane, each with an overlap margin and the views that see it.

The ground plane is the plane through the origin of the normalised frame perpendicular to the capture's up direction
(trisplat.io.capture_up). Its two axes are the principal directions of the sparse points (or the camera centres when
there are none) projected onto it, the first along the scene's longest extent (a street's axis). The plane is cut
into nu x nv cells (nu x nv = the number of blocks, the factorisation whose cells are closest to square), at
quantiles of the points: first along u, then each column along v, so every cell holds about the same share of the
content. The outer cells reach to infinity: every camera and every point lies in exactly one cell.

A block is its cell grown by `margin` (a fraction of the cell's size, on its inner sides), VastGaussian's
"expanded cell". Its views, as in VastGaussian's visibility-based camera selection: every view whose camera centre
lies in the expanded cell, and every view in which the expanded cell's points are at least `visibility` of the
points the view sees (projected into its image, in front of it; no occlusion test). A view some block would
otherwise miss goes to the block whose points it sees most. Test views are assigned by the same rule.

Everything here is in the capture's normalised frame (SceneData).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

DEFAULT_MARGIN = 0.2  # VastGaussian grows its cells by 20 %
DEFAULT_VISIBILITY = 0.25  # VastGaussian's visibility threshold
AUTO_VIEWS_PER_BLOCK = 200  # --blocks auto: about this many training views per block


@dataclass
class Block:
    """One block. cell: float [2,2] (lo, hi) along the ground axes (u, v), +-inf on the outer sides; expanded:
    the cell grown by the margin; box: float [2,3] the axis-aligned box (normalised frame) of the expanded cell,
    its outer sides bounded by the content and its height by the points; train / test: camera indices (into
    SceneData.cameras); points: sparse points in the expanded cell; estimates: memory (MiB) and time (s)."""

    index: int
    cell: list
    expanded: list
    box: list
    train: list[int]
    test: list[int]
    points: int
    by_centre: int = 0
    by_visibility: int = 0
    estimates: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"block_{self.index:02d}"


@dataclass
class Plan:
    """The partition of a scene. up: float [3]; axes: float [2,3] the ground axes (u, v); grid: (nu, nv)."""

    blocks: list[Block]
    up: list
    axes: list
    grid: tuple[int, int]
    margin: float
    visibility: float

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> Plan:
        blocks = [Block(**b) for b in d["blocks"]]
        return Plan(blocks, d["up"], d["axes"], tuple(d["grid"]), float(d["margin"]), float(d["visibility"]))

    def ground(self, x: np.ndarray) -> np.ndarray:
        """[N,2] ground-plane coordinates (u, v) of points [N,3] (normalised frame)."""
        return np.asarray(x, dtype=np.float64) @ np.asarray(self.axes, dtype=np.float64).T

    def cell_of(self, x: np.ndarray) -> np.ndarray:
        """int [N]: the block whose cell holds each point [N,3] (cells tile the plane: exactly one each)."""
        uv = self.ground(x)
        out = np.full(len(uv), -1, np.int64)
        for b in self.blocks:
            out[in_rect(uv, b.cell)] = b.index
        return out


def in_rect(uv: np.ndarray, rect) -> np.ndarray:
    """bool [N]: lo <= (u, v) < hi (half-open, so neighbouring cells never share a point)."""
    r = np.asarray(rect, dtype=np.float64)
    return np.all((uv >= r[0]) & (uv < r[1]), axis=1)


def ground_axes(up: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """[2,3] orthonormal axes of the plane perpendicular to `up`: the principal directions of `samples` [N,3]
    projected onto it (the first along their largest spread)."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    flat = samples - np.outer(samples @ up, up)
    flat = flat - flat.mean(0)
    a = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 1e-6:
        a = np.cross(up, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    cov = np.cov(np.stack([flat @ a, flat @ b]))
    w, v = np.linalg.eigh(cov)
    e = v[:, int(np.argmax(w))]
    u_axis = e[0] * a + e[1] * b
    u_axis /= np.linalg.norm(u_axis)
    if u_axis[int(np.argmax(np.abs(u_axis)))] < 0:  # a canonical sign: cells numbered along +x for a street along x
        u_axis = -u_axis
    return np.stack([u_axis, np.cross(up, u_axis)])


def grid_for(n: int, extent_u: float, extent_v: float) -> tuple[int, int]:
    """(nu, nv) with nu x nv = n whose cells are closest to square for a content of extent_u x extent_v."""
    best, best_cost = (n, 1), math.inf
    for nv in range(1, n + 1):
        if n % nv:
            continue
        nu = n // nv
        cost = abs(math.log(max(extent_u / nu, 1e-12) / max(extent_v / nv, 1e-12)))
        if cost < best_cost:
            best, best_cost = (nu, nv), cost
    return best


def _cuts(values: np.ndarray, k: int) -> np.ndarray:
    """k + 1 edges along one axis (-inf, k - 1 quantile cuts, +inf)."""
    inner = np.quantile(values, np.arange(1, k) / k) if k > 1 and len(values) else np.zeros(0)
    return np.concatenate([[-np.inf], inner, [np.inf]])


def _visible(cam, pts: np.ndarray) -> np.ndarray:
    """bool [N]: points in front of the camera that project into its image."""
    w2c = np.asarray(cam.world_to_camera, dtype=np.float64)
    xc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = xc[:, 2]
    ok = z > 1e-6
    uvw = xc @ np.asarray(cam.K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        px, py = uvw[:, 0] / z, uvw[:, 1] / z
    return ok & (px >= 0) & (px < cam.width) & (py >= 0) & (py < cam.height)


def resolve_count(blocks: str | int, n_train: int) -> int:
    """The number of blocks: an integer >= 1, or 'auto' (about AUTO_VIEWS_PER_BLOCK training views per block)."""
    if isinstance(blocks, str) and blocks.strip().lower() == "auto":
        return max(1, int(round(n_train / AUTO_VIEWS_PER_BLOCK)))
    try:
        n = int(blocks)
    except (TypeError, ValueError):
        raise ValueError(f"--blocks must be 'auto' or a whole number >= 1, got {blocks!r}") from None
    if n < 1:
        raise ValueError(f"--blocks must be 'auto' or a whole number >= 1, got {n}")
    return n


def partition(data, n_blocks: int, margin: float = DEFAULT_MARGIN, visibility: float = DEFAULT_VISIBILITY,
              up: np.ndarray | None = None) -> Plan:
    """The blocks of a loaded capture (SceneData) for `n_blocks` cells (see the module's docstring)."""
    if not 0.0 <= margin < 1.0:
        raise ValueError(f"--block-margin must be in [0, 1), got {margin}")
    if not 0.0 < visibility <= 1.0:
        raise ValueError(f"--block-visibility must be in (0, 1], got {visibility}")
    if up is None:
        from trisplat.io import capture_up

        up = capture_up(data)
    up = np.asarray(up if up is not None else (0.0, 0.0, 1.0), dtype=np.float64)
    up = up / np.linalg.norm(up)
    centres = np.stack([np.asarray(c.center, dtype=np.float64) for c in data.cameras])
    pts = np.asarray(data.points, dtype=np.float64) if data.points is not None and len(data.points) else None
    content = pts if pts is not None else centres
    axes = ground_axes(up, content)
    uv = content @ axes.T
    cuv = centres @ axes.T
    ext = uv.max(0) - uv.min(0)
    nu, nv = grid_for(n_blocks, float(ext[0]), float(ext[1]))
    cells = []
    ucut = _cuts(uv[:, 0], nu)
    for i in range(nu):
        col = uv[(uv[:, 0] >= ucut[i]) & (uv[:, 0] < ucut[i + 1])]
        vcut = _cuts(col[:, 1] if len(col) else uv[:, 1], nv)
        for j in range(nv):
            cells.append(np.array([[ucut[i], vcut[j]], [ucut[i + 1], vcut[j + 1]]]))
    # content extent on the ground and along up: bounds the outer cells' boxes
    lo_uv = np.minimum(uv.min(0), cuv.min(0))
    hi_uv = np.maximum(uv.max(0), cuv.max(0))
    h = content @ up
    h_lo, h_hi = float(h.min()), float(h.max())
    if data.bounds is not None:
        hb = np.asarray(data.bounds, dtype=np.float64)
        corners = np.array([[x, y, z] for x in hb[:, 0] for y in hb[:, 1] for z in hb[:, 2]]) @ up
        h_lo, h_hi = min(h_lo, float(corners.min())), max(h_hi, float(corners.max()))
    pad = 0.02 * max(float(np.max(hi_uv - lo_uv)), h_hi - h_lo, 1e-9)
    blocks: list[Block] = []
    vis_all = {}
    for n, cell in enumerate(cells):
        finite_lo = np.where(np.isfinite(cell[0]), cell[0], lo_uv)
        finite_hi = np.where(np.isfinite(cell[1]), cell[1], hi_uv)
        size = np.maximum(finite_hi - finite_lo, 1e-9)
        grow = margin * size
        expanded = np.array([np.where(np.isfinite(cell[0]), cell[0] - grow, -np.inf),
                             np.where(np.isfinite(cell[1]), cell[1] + grow, np.inf)])
        ex_lo = np.maximum(np.where(np.isfinite(expanded[0]), expanded[0], lo_uv - pad), lo_uv - pad)
        ex_hi = np.minimum(np.where(np.isfinite(expanded[1]), expanded[1], hi_uv + pad), hi_uv + pad)
        corners = np.array([a * ex_u + b * ex_v + c * up for ex_u in (ex_lo[0], ex_hi[0])
                            for ex_v in (ex_lo[1], ex_hi[1]) for c in (h_lo - pad, h_hi + pad)
                            for a, b in [(axes[0], axes[1])]])
        box = np.stack([corners.min(0), corners.max(0)])
        in_block = in_rect(uv, expanded) if pts is not None else np.zeros(0, bool)
        blocks.append(Block(index=n, cell=cell.tolist(), expanded=expanded.tolist(), box=box.tolist(), train=[], test=[],
                            points=int(in_block.sum())))
        vis_all[n] = in_block
    train = [int(i) for i in data.train_indices]
    test = [int(i) for i in data.test_indices]
    for split, indices in (("train", train), ("test", test)):
        for i in indices:
            cam = data.cameras[i]
            centre_uv = cuv[i][None]
            seen = _visible(cam, pts) if pts is not None else None
            counts = {b.index: int((seen & vis_all[b.index]).sum()) if seen is not None else 0 for b in blocks}
            total = int(seen.sum()) if seen is not None else 0
            chosen = []
            for b in blocks:
                by_centre = bool(in_rect(centre_uv, b.expanded)[0])
                by_vis = total > 0 and counts[b.index] >= max(1, visibility * total)
                if by_centre or by_vis:
                    chosen.append(b)
                    if split == "train":
                        b.by_centre += int(by_centre)
                        b.by_visibility += int(by_vis and not by_centre)
            if not chosen:  # seen by no block's rule: the block whose points it sees most (or whose cell holds it)
                best = max(blocks, key=lambda b: (counts[b.index], bool(in_rect(centre_uv, b.cell)[0])))
                chosen = [best]
            for b in chosen:
                getattr(b, split).append(i)
    for b in blocks:
        if not b.train:
            raise ValueError(f"block {b.index} (cell u in [{b.cell[0][0]:.3g}, {b.cell[1][0]:.3g}), v in "
                             f"[{b.cell[0][1]:.3g}, {b.cell[1][1]:.3g}) of the normalised frame) has no training view: "
                             "use fewer blocks (--blocks) or a larger margin (--block-margin)")
    return Plan(blocks, up.tolist(), axes.tolist(), (nu, nv), float(margin), float(visibility))


# ------------------------------------------------------------------------------------------------ estimates
# Calibrated on this project's 2-core machine (docs/benchmarks.md, "Partitioned training on Ray"): the resident set
# of one block's process is a fixed part (Python, torch, Numba, Ray's worker) plus the image cache, the triangle
# table and the fusion grid of its switch (measured 723-753 MiB for the street's blocks, estimated 740); its CPU
# time is a fixed part (process start, imports, loading, final scoring and files) plus steps x (a per-step part +
# the pixels of a step): the street's blocks, 300 steps at 96x64, took 21-26 s of CPU (estimated 23.5).
BASE_MEMORY_MB = 700.0
BYTES_PER_VERTEX = 400.0  # positions, SH (degree 3), Adam moments, gradients, renderer buffers
FUSION_BYTES_PER_VOXEL = 12.0
TASK_FIXED_S = 10.0
STEP_BASE_S = 0.03
SECONDS_PER_MEGAPIXEL_STEP = 2.5  # one training step over 1e6 pixels, one core (soft renderer forward + backward)


def estimate_block(block: Block, data, cfg, memory_budget_mb: float = 1024.0) -> dict:
    """Estimates for one block: faces (the configuration's caps, an upper bound), peak memory (MiB) and the CPU
    time of its task (s, one core)."""
    cams = [data.cameras[i] for i in block.train]
    px = float(np.mean([c.width * c.height for c in cams]))
    images_mb = min(len(cams) * px * 3 * 4 / 2**20, memory_budget_mb)
    side = max(max(c.width, c.height) for c in cams)
    res = int(min(cfg.surface_resolution, max(2 * side, 32)))
    box = np.asarray(block.box)
    ext = np.maximum(box[1] - box[0], 1e-9)
    voxels = float(np.prod(np.maximum(1, np.ceil(ext / ext.max() * res))))
    voxels = min(voxels, 48_000_000)
    faces = int(min(cfg.surface_max_faces, max(2 * cfg.max_vertices, 1)))
    mem = BASE_MEMORY_MB + images_mb + cfg.max_vertices * BYTES_PER_VERTEX / 2**20 + voxels * FUSION_BYTES_PER_VOXEL / 2**20
    per_step = STEP_BASE_S + px / 1e6 * SECONDS_PER_MEGAPIXEL_STEP
    seconds = TASK_FIXED_S + (cfg.steps * per_step if not cfg.minutes else 60.0 * cfg.minutes)
    return {"max_faces": faces, "max_vertices": int(cfg.max_vertices), "fusion_voxels": int(voxels),
            "memory_mb": round(mem), "train_s": round(seconds, 1)}


def plan_lines(plan: Plan, data, cfg) -> list[str]:
    """The dry run's table: one line per block (cell, views, points, estimates) and a total."""
    lines = [f"{len(plan.blocks)} blocks ({plan.grid[0]} x {plan.grid[1]} cells of the ground plane), margin "
             f"{100 * plan.margin:.0f}% of a cell, a view joins a block that holds its camera or holds >= "
             f"{100 * plan.visibility:.0f}% of the points it sees"]
    lines.append(f"{'block':<9}{'cell u':>22}{'cell v':>22}{'train':>7}{'test':>6}{'points':>8}"
                 f"{'faces<=':>9}{'mem MiB':>9}{'CPU s':>9}")
    fmt = lambda a, b: f"[{a:.3g}, {b:.3g})"
    n_train = len(data.train_indices)
    for b in plan.blocks:
        est = b.estimates or estimate_block(b, data, cfg)
        b.estimates = est
        lines.append(f"{b.name:<9}{fmt(b.cell[0][0], b.cell[1][0]):>22}{fmt(b.cell[0][1], b.cell[1][1]):>22}"
                     f"{len(b.train):>7}{len(b.test):>6}{b.points:>8}{est['max_faces']:>9}{est['memory_mb']:>9}"
                     f"{est['train_s']:>9.0f}")
    views = sum(len(b.train) for b in plan.blocks)
    lines.append(f"training views: {n_train} in the capture, {views} over all blocks ({views / max(n_train, 1):.2f} "
                 f"per view: the overlap); peak memory of the largest block "
                 f"{max(b.estimates['memory_mb'] for b in plan.blocks)} MiB; the block tasks "
                 f"{sum(b.estimates['train_s'] for b in plan.blocks):.0f} s of one core in all")
    return lines
