"""The only code that edits topology: vertex/face rows, Adam moments and running statistics stay aligned.

Two index spaces: vertices (parameters `positions`, `sh_dc`, `sh_rest`, `opacity_logit` and their Adam moments,
plus vertex statistics) and faces (`faces` rows plus face statistics). Compacting vertices remaps faces.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from trisplat.scene.model import TriangleScene

VERTEX_PARAMS = ("positions", "sh_dc", "sh_rest", "opacity_logit")
FACE_STATS = ("max_weight", "max_weight_prev", "max_screen_px", "max_screen_px_prev", "colour_grad", "colour_grad_n")


@dataclass
class TrainableScene:
    """A TriangleScene split into optimisable parameter tensors, with its Adam optimizer and statistics.

    params: name -> Parameter with V rows (names in VERTEX_PARAMS; sh_rest may have 0 columns for degree 0).
    faces: int64 [F,3]. face_stats: name -> [F] tensors (running maxima between strategy events; for a connected
    surface also colour_grad / colour_grad_n, the summed colour-gradient norm of the face's vertices and the number
    of steps it was seen, which pick the faces to refine).
    """

    params: dict[str, torch.nn.Parameter]
    optimizer: torch.optim.Adam
    faces: torch.Tensor
    opacity_floor: float = 0.0
    linear_light: bool = False  # TriangleScene.linear_light
    face_stats: dict[str, torch.Tensor] = field(default_factory=dict)

    @property
    def num_vertices(self) -> int:
        return int(self.params["positions"].shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def sh(self) -> torch.Tensor:
        return torch.cat([self.params["sh_dc"], self.params["sh_rest"]], dim=1)

    def opacities(self) -> torch.Tensor:
        return self.opacity_floor + (1.0 - self.opacity_floor) * torch.sigmoid(self.params["opacity_logit"])

    def to_scene(self) -> TriangleScene:
        return TriangleScene(
            positions=self.params["positions"].detach().clone(),
            sh=self.sh().detach().clone(),
            opacity_logit=self.params["opacity_logit"].detach().clone(),
            faces=self.faces.to(torch.int32).clone(),
            opacity_floor=self.opacity_floor,
            linear_light=self.linear_light,
        )

    def reset_face_stats(self) -> None:
        F = self.num_faces
        self.face_stats = {name: torch.zeros(F, device=self.faces.device) for name in FACE_STATS}

    def face_stat(self, name: str) -> torch.Tensor:
        """Running maximum of statistic `name` over the current and the previous epoch of training views, so
        that every face has been seen from every view before it is judged (short runs prune more often than
        they cycle through the views)."""
        return torch.maximum(self.face_stats[name], self.face_stats[name + "_prev"])

    def roll_face_stats(self) -> None:
        """Start a new epoch of views: the current maxima become the previous ones."""
        for name in ("max_weight", "max_screen_px"):
            self.face_stats[name + "_prev"] = self.face_stats[name]
            self.face_stats[name] = torch.zeros_like(self.face_stats[name])


def make_adam(groups: list[dict]) -> torch.optim.Adam:
    """Adam with eps 1e-15 (Triangle Splatting+), one group per vertex parameter. The fused implementation (one
    kernel per parameter; ~12 ms vs ~32-55 ms for the per-op one at 125k vertices with SH degree 3, 2 threads, timed
    ad hoc) does the same maths. Devices without a fused Adam get the per-op one."""
    fused = all(p.device.type in ("cpu", "cuda") for g in groups for p in g["params"])
    return torch.optim.Adam(groups, eps=1e-15, fused=fused or None)


def make_trainable(scene: TriangleScene, lrs: dict[str, float]) -> TrainableScene:
    """Parameters and an Adam optimizer (eps 1e-15, one group per parameter named after it)."""
    sh = scene.sh.detach()
    params = {
        "positions": torch.nn.Parameter(scene.positions.detach().clone()),
        "sh_dc": torch.nn.Parameter(sh[:, :1].clone()),
        "sh_rest": torch.nn.Parameter(sh[:, 1:].clone()),
        "opacity_logit": torch.nn.Parameter(scene.opacity_logit.detach().clone()),
    }
    groups = [{"params": [params[n]], "lr": lrs.get(n, 0.0), "name": n} for n in VERTEX_PARAMS]
    opt = make_adam(groups)
    ts = TrainableScene(params=params, optimizer=opt, faces=scene.faces.to(torch.int64).clone(),
                        opacity_floor=scene.opacity_floor, linear_light=scene.linear_light)
    ts.reset_face_stats()
    return ts


def _replace_param(ts: TrainableScene, name: str, new_value: torch.Tensor, moment_fn) -> None:
    """Swap parameter `name` for `new_value`, mapping its Adam moments with moment_fn(old_moment) -> new_moment."""
    old = ts.params[name]
    new = torch.nn.Parameter(new_value.detach().contiguous())
    for group in ts.optimizer.param_groups:
        if group["params"][0] is old:
            group["params"][0] = new
            break
    state = ts.optimizer.state.pop(old, None)
    if state:
        ts.optimizer.state[new] = {
            k: (moment_fn(v) if k in ("exp_avg", "exp_avg_sq") else v) for k, v in state.items()
        }
    ts.params[name] = new


def index_vertices(ts: TrainableScene, index: torch.Tensor) -> None:
    """Keep vertex rows `index` (int64, in their new order) everywhere; faces must reference only kept vertices."""
    index = index.to(torch.int64)
    remap = torch.full((ts.num_vertices,), -1, dtype=torch.int64, device=index.device)
    remap[index] = torch.arange(index.numel(), device=index.device)
    new_faces = remap[ts.faces]
    if (new_faces < 0).any():
        raise ValueError("index_vertices: a face references a vertex that is being removed")
    for name in VERTEX_PARAMS:
        _replace_param(ts, name, ts.params[name].detach()[index], lambda m: m[index])
    ts.faces = new_faces


def append_vertices(ts: TrainableScene, values: dict[str, torch.Tensor]) -> torch.Tensor:
    """Append rows (one tensor per vertex parameter); new rows start with zero Adam moments.
    Returns the indices of the new vertices."""
    n_new = values["positions"].shape[0]
    start = ts.num_vertices
    for name in VERTEX_PARAMS:
        old = ts.params[name].detach()
        _replace_param(ts, name, torch.cat([old, values[name].to(old)], 0),
                       lambda m: torch.cat([m, torch.zeros((n_new,) + m.shape[1:], dtype=m.dtype, device=m.device)], 0))
    return torch.arange(start, start + n_new, device=ts.faces.device)


def keep_faces(ts: TrainableScene, mask: torch.Tensor) -> None:
    """Keep faces where mask is True (face statistics follow)."""
    ts.faces = ts.faces[mask]
    ts.face_stats = {k: v[mask] for k, v in ts.face_stats.items()}


def set_faces(ts: TrainableScene, faces: torch.Tensor) -> None:
    """Replace the whole face table (e.g. by a restricted Delaunay mesh); face statistics restart at zero."""
    faces = faces.to(torch.int64).to(ts.faces.device)
    if faces.numel() and (faces.min() < 0 or faces.max() >= ts.num_vertices):
        raise ValueError("set_faces: face index out of range")
    ts.faces = faces
    ts.reset_face_stats()


def replace_scene(ts: TrainableScene, scene: TriangleScene) -> None:
    """Replace every vertex and face row by those of `scene` (e.g. the connected surface of the stage-2 switch):
    new parameters with zero Adam moments (learning rates kept), the scene's faces and opacity floor, face
    statistics restarting at zero."""
    sh = scene.sh.detach()
    values = {"positions": scene.positions, "sh_dc": sh[:, :1], "sh_rest": sh[:, 1:],
              "opacity_logit": scene.opacity_logit}
    for name in VERTEX_PARAMS:
        old = ts.params[name]
        new = torch.nn.Parameter(values[name].detach().to(old).contiguous().clone())
        for group in ts.optimizer.param_groups:
            if group["params"][0] is old:
                group["params"][0] = new
        ts.optimizer.state.pop(old, None)
        ts.params[name] = new
    ts.faces = scene.faces.to(torch.int64).to(ts.faces.device).clone()
    ts.opacity_floor = float(scene.opacity_floor)
    ts.linear_light = bool(scene.linear_light)
    ts.reset_face_stats()


def remove_orphan_vertices(ts: TrainableScene) -> int:
    """Drop vertices no face references; returns how many were removed."""
    used = torch.zeros(ts.num_vertices, dtype=torch.bool, device=ts.faces.device)
    used[ts.faces.reshape(-1)] = True
    n_removed = int((~used).sum())
    if n_removed:
        index_vertices(ts, torch.nonzero(used).squeeze(1))
    return n_removed


def subdivide_faces(ts: TrainableScene, face_index: torch.Tensor) -> int:
    """Midpoint-subdivide the selected faces into 4; an edge shared by two selected faces gets ONE midpoint.

    Midpoint attributes are the average of the edge's two vertices; new rows have zero Adam moments; parents are
    removed and children inherit their parent's face statistics. Unselected neighbours keep their edge, which
    leaves T-junctions (the "semi-connected" mesh of Triangle Splatting+). Returns the number of new vertices.
    """
    face_index = torch.unique(face_index.to(torch.int64))
    if face_index.numel() == 0:
        return 0
    sel = ts.faces[face_index]  # [S,3]
    edges = torch.stack([sel[:, [0, 1]], sel[:, [1, 2]], sel[:, [2, 0]]], dim=1)  # [S,3,2]
    edges_sorted = torch.sort(edges, dim=-1).values.reshape(-1, 2)
    uniq, inverse = torch.unique(edges_sorted, dim=0, return_inverse=True)
    a, b = uniq[:, 0], uniq[:, 1]
    values = {name: 0.5 * (ts.params[name].detach()[a] + ts.params[name].detach()[b]) for name in VERTEX_PARAMS}
    new_ids = append_vertices(ts, values)
    mid = new_ids[inverse].reshape(-1, 3)  # midpoint of edge (0,1), (1,2), (2,0) per selected face
    v0, v1, v2 = sel[:, 0], sel[:, 1], sel[:, 2]
    m01, m12, m20 = mid[:, 0], mid[:, 1], mid[:, 2]
    children = torch.cat([
        torch.stack([v0, m01, m20], 1),
        torch.stack([m01, v1, m12], 1),
        torch.stack([m20, m12, v2], 1),
        torch.stack([m01, m12, m20], 1),
    ], 0)  # same winding as the parent
    keep = torch.ones(ts.num_faces, dtype=torch.bool, device=ts.faces.device)
    keep[face_index] = False
    child_stats = {k: v[face_index].repeat(4) for k, v in ts.face_stats.items()}
    ts.faces = torch.cat([ts.faces[keep], children], 0)
    ts.face_stats = {k: torch.cat([v[keep], child_stats[k]], 0) for k, v in ts.face_stats.items()}
    return int(uniq.shape[0])


def refine_faces(ts: TrainableScene, face_index: torch.Tensor) -> int:
    """Conforming (red-green) refinement of a connected mesh: the selected faces are split into 4 at their edge
    midpoints, and so is every face that would get two split edges; a face with one split edge is bisected into 2
    through that edge's midpoint. Every edge midpoint is one vertex shared by the faces on both sides, so the mesh
    stays welded: no T-junctions, no cracks, an edge shared by two faces before is shared by two faces after.

    Midpoint attributes are the average of the edge's two vertices; new rows have zero Adam moments; children keep
    their parent's winding and face statistics. Returns the number of new vertices.
    """
    face_index = torch.unique(face_index.to(torch.int64))
    if face_index.numel() == 0:
        return 0
    faces = ts.faces
    edges = torch.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], dim=1)  # [F,3,2]
    uniq, face_edge = torch.unique(torch.sort(edges, dim=-1).values.reshape(-1, 2), dim=0, return_inverse=True)
    face_edge = face_edge.reshape(-1, 3)  # [F,3] edge id of each face's edges (v0v1, v1v2, v2v0)
    marked = torch.zeros(len(uniq), dtype=torch.bool, device=faces.device)
    marked[face_edge[face_index].reshape(-1)] = True
    while True:  # closure: a face with two split edges gets its third split too (it becomes a 1-to-4 face)
        count = marked[face_edge].sum(1)
        promote = count == 2
        if not bool(promote.any()):
            break
        marked[face_edge[promote].reshape(-1)] = True
    split = torch.nonzero(marked).squeeze(1)
    a, b = uniq[split, 0], uniq[split, 1]
    values = {name: 0.5 * (ts.params[name].detach()[a] + ts.params[name].detach()[b]) for name in VERTEX_PARAMS}
    mid_of_edge = torch.full((len(uniq),), -1, dtype=torch.int64, device=faces.device)
    mid_of_edge[split] = append_vertices(ts, values)
    mid = mid_of_edge[face_edge]  # [F,3] midpoint of each face edge, -1 where not split
    count = marked[face_edge].sum(1)
    four, two = count == 3, count == 1
    v0, v1, v2 = faces[four, 0], faces[four, 1], faces[four, 2]
    m01, m12, m20 = mid[four, 0], mid[four, 1], mid[four, 2]
    children = [torch.stack([v0, m01, m20], 1), torch.stack([m01, v1, m12], 1), torch.stack([m20, m12, v2], 1),
                torch.stack([m01, m12, m20], 1)]
    parents = [torch.nonzero(four).squeeze(1)] * 4
    idx2 = torch.nonzero(two).squeeze(1)
    k = torch.argmax((mid[idx2] >= 0).to(torch.int64), dim=1)  # the split edge: (v_k, v_k+1)
    f2 = faces[idx2]
    r = torch.arange(len(idx2), device=faces.device)
    va, vb, vc = f2[r, k], f2[r, (k + 1) % 3], f2[r, (k + 2) % 3]
    m = mid[idx2, k]
    children += [torch.stack([va, m, vc], 1), torch.stack([m, vb, vc], 1)]
    parents += [idx2, idx2]
    keep = count == 0
    parent = torch.cat(parents)
    ts.face_stats = {n: torch.cat([v[keep], v[parent]], 0) for n, v in ts.face_stats.items()}
    ts.faces = torch.cat([faces[keep], *children], 0)
    return int(len(split))
