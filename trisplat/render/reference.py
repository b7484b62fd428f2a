"""Dense pure-PyTorch triangle splatting (ALGORITHM.md section 2, the spec in code): the test oracle, slow.

Every (pixel, face) pair of a pixel block is evaluated densely and autograd provides every gradient. It is
written for reading, not speed; the Numba kernels (kernels.py) must agree with it in value and gradient.

One view. Inputs are already validated (see inputs.py) and colours are per-vertex RGB (SH evaluated by the caller).
"""
from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from trisplat.render.types import RenderOptions, RenderOutput


def _cross2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """z component of the 2D cross product a x b, over the last axis."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def project_faces(positions, faces, world_to_camera, K, opts: RenderOptions):
    """Item 1 and 2: camera-frame triangles, screen triangles, culling, edge lines, incentre normaliser.

    Returns tri_cam [F,3,3], uv [F,3,2], keep [F] bool, normal [F,3] (camera-facing unit, camera frame), edge
    normals n [F,3,2], offsets d [F,3], phi_s [F] (phi at the incentre = -inradius) and area2 [F] (signed twice
    the screen area). keep drops faces with a vertex nearer than opts.near, faces entirely beyond opts.far,
    degenerate (area < opts.min_area_px) and grazing (|cos| < opts.grazing_cos) faces.
    """
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    cam = positions @ R.T + t  # [V,3]
    tri_cam = cam[faces]  # [F,3,3]
    x, y, z = tri_cam[..., 0], tri_cam[..., 1], tri_cam[..., 2]
    zs = torch.where(z > 0, z, torch.ones_like(z))  # culled faces get harmless numbers
    u = (K[0, 0] * x + K[0, 1] * y) / zs + K[0, 2]
    v = (K[1, 0] * x + K[1, 1] * y) / zs + K[1, 2]
    uv = torch.stack([u, v], dim=-1)  # [F,3,2]

    # Face normal in the camera frame, turned towards the camera (the camera sits at the origin).
    nrm = torch.cross(tri_cam[:, 1] - tri_cam[:, 0], tri_cam[:, 2] - tri_cam[:, 0], dim=-1)
    nrm_len = nrm.norm(dim=-1)
    nrm = nrm / nrm_len.clamp_min(1e-30)[:, None]
    facing = torch.where((nrm * tri_cam[:, 0]).sum(-1) > 0, -1.0, 1.0).to(nrm.dtype)
    nrm = nrm * facing[:, None]

    area2 = _cross2(uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0])  # signed twice the screen area
    with torch.no_grad():
        centroid = tri_cam.mean(1)
        cos_view = (nrm * centroid).sum(-1).abs() / centroid.norm(dim=-1).clamp_min(1e-30)
        keep = (z >= opts.near).all(1) & ~(z > opts.far).all(1)
        keep &= area2.abs() * 0.5 >= opts.min_area_px
        keep &= (cos_view >= opts.grazing_cos) & (nrm_len > 0)

    # Edge k runs from vertex k to vertex k+1; its outward unit normal makes L_k < 0 inside.
    e = uv.roll(-1, dims=1) - uv  # [F,3,2]
    length = e.norm(dim=-1).clamp_min(1e-30)  # [F,3]
    sgn = torch.where(area2 >= 0, 1.0, -1.0).to(uv.dtype)[:, None]
    n = torch.stack([e[..., 1], -e[..., 0]], dim=-1) / length[..., None] * sgn[..., None]
    d = -(n * uv).sum(-1)  # [F,3]
    # Incentre: vertices weighted by the length of the opposite edge (edge k+1 is opposite vertex k).
    w_opp = length.roll(-1, dims=1)
    s = (w_opp[..., None] * uv).sum(1) / w_opp.sum(1, keepdim=True)  # [F,2]
    phi_s = (n[:, 0] * s).sum(-1) + d[:, 0]  # equal for all three edges: minus the inradius
    return tri_cam, uv, keep, nrm, n, d, phi_s, area2


def _block(p, n, d, phi_s, uv, area2, zc, cols, nrm, o, sigma: float, opts: RenderOptions):
    """Dense evaluation of one pixel block: p [P,2] pixel centres; per-face tensors already ordered front to back.

    Returns (features [P, 8] = rgb, depth, normal, T_final) and weights [Fb,P].
    """
    L = (n[:, None, :, :] * p[None, :, None, :]).sum(-1) + d[:, None, :]  # [Fb,P,3]
    phi = L.max(dim=-1).values
    ratio = phi / phi_s[:, None]  # 1 at the incentre, 0 on the edges, < 0 outside
    inside = ratio > 0
    window = torch.where(inside, torch.where(inside, ratio, torch.ones_like(ratio)) ** sigma, torch.zeros_like(ratio))
    a = (o[:, None] * window).clamp(max=opts.alpha_max)
    a = torch.where(a >= opts.alpha_min, a, torch.zeros_like(a))
    # Screen-space barycentrics from sub-triangle areas.
    rel = uv[:, None, :, :] - p[None, :, None, :]  # [Fb,P,3,2] vertex - pixel
    b = torch.stack(
        [_cross2(rel[:, :, 1], rel[:, :, 2]), _cross2(rel[:, :, 2], rel[:, :, 0]), _cross2(rel[:, :, 0], rel[:, :, 1])],
        dim=-1,
    ) / area2[:, None, None]  # [Fb,P,3]
    zinv_v = 1.0 / zc  # [Fb,3]
    bz = b * zinv_v[:, None, :]
    zinv = bz.sum(-1).clamp_min(1e-30)
    depth = 1.0 / zinv  # the plane's view depth along this pixel's ray
    wts = bz / zinv[..., None] if opts.perspective_correct else b
    color = (wts[..., None] * cols[:, None, :, :]).sum(-2)  # [Fb,P,3]

    # Front-to-back compositing with the early stop at T < transmittance_min.
    with torch.no_grad():
        T_try = torch.cumprod(torch.cat([torch.ones_like(a[:1]), 1.0 - a[:-1]]), dim=0)
        included = T_try >= opts.transmittance_min
    a = a * included
    one_minus = 1.0 - a
    T = torch.cumprod(torch.cat([torch.ones_like(a[:1]), one_minus[:-1]]), dim=0)  # exclusive product
    w = a * T  # [Fb,P]
    T_final = torch.prod(one_minus, dim=0) if a.shape[0] else torch.ones_like(p[:, 0])
    rgb = (w[..., None] * color).sum(0)
    dep = (w * depth).sum(0)
    nor = (w[..., None] * nrm[:, None, :]).sum(0)
    return torch.cat([rgb, dep[:, None], nor, T_final[:, None]], dim=-1), w


def render_reference(positions, faces, vertex_rgb, opacities, sigma: float, world_to_camera, K, width: int,
                     height: int, background, opts: RenderOptions) -> RenderOutput:
    """One view, densely. positions [V,3], faces long [F,3], vertex_rgb [V,3], opacities [V], background [3].

    world_to_camera [4,4] and K [3,3] are tensors of the positions' dtype. Images are [H,W,...].
    pairs_evaluated counts every (pixel, face) pair of the dense blocks; faces_visible counts the faces kept by the
    culling above (off-screen ones included, unlike the kernels, which count faces overlapping a tile).
    """
    dtype, dev = positions.dtype, positions.device
    faces = faces.long()
    F = faces.shape[0]
    tri_cam, uv, keep, nrm, n, d, phi_s, area2 = project_faces(positions, faces, world_to_camera, K, opts)
    o_v = opacities[faces]  # [F,3]
    o = o_v.min(dim=1).values if opts.opacity_mode == "min" else o_v.mean(dim=1)
    cols = vertex_rgb[faces]  # [F,3,3]
    zc = tri_cam[..., 2]

    # Item 6: one global order by centroid view depth = the order inside every tile (ties: lower face index first).
    with torch.no_grad():
        key = zc.mean(1)
        order = torch.argsort(key, stable=True)
        order = order[keep[order]]
        lo = uv[order].amin(1)
        hi = uv[order].amax(1)

    bs = int(opts.reference_block)
    rgb = torch.zeros(height, width, 3, dtype=dtype, device=dev)
    alpha = torch.zeros(height, width, dtype=dtype, device=dev)
    depth = torch.zeros(height, width, dtype=dtype, device=dev)
    normal = torch.zeros(height, width, 3, dtype=dtype, device=dev)
    rows = []
    max_weight = torch.zeros(F, dtype=dtype, device=dev)
    face_id = torch.full((height, width), -1, dtype=torch.int64, device=dev)
    pairs = 0
    bg = background.to(dtype)
    for y0 in range(0, height, bs):
        row = []
        for x0 in range(0, width, bs):
            y1, x1 = min(y0 + bs, height), min(x0 + bs, width)
            ys, xs = torch.meshgrid(torch.arange(y0, y1, device=dev, dtype=dtype) + 0.5,
                                    torch.arange(x0, x1, device=dev, dtype=dtype) + 0.5, indexing="ij")
            p = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)
            with torch.no_grad():  # faces whose screen bounding box touches this block's pixel centres
                sel = (hi[:, 0] >= x0 + 0.5) & (lo[:, 0] <= x1 - 0.5) & (hi[:, 1] >= y0 + 0.5) & (lo[:, 1] <= y1 - 0.5)
                idx = order[sel]
            pairs += int(idx.numel()) * p.shape[0]
            args = (p, n[idx], d[idx], phi_s[idx], uv[idx], area2[idx], zc[idx], cols[idx], nrm[idx], o[idx])
            fn = lambda *a: _block(*a, sigma=sigma, opts=opts)  # noqa: E731
            if torch.is_grad_enabled() and any(t.requires_grad for t in args):
                feats, w = checkpoint(fn, *args, use_reentrant=False)
            else:
                feats, w = fn(*args)
            hb, wb = y1 - y0, x1 - x0
            T_final = feats[:, 7]
            row.append(torch.cat([feats[:, :3] + T_final[:, None] * bg, (1.0 - T_final)[:, None], feats[:, 3:7]],
                                 dim=-1).reshape(hb, wb, 8))
            with torch.no_grad():
                if idx.numel():
                    max_weight[idx] = torch.maximum(max_weight[idx], w.max(dim=1).values)
                    passed = torch.cumsum(w, dim=0) > 0.5
                    has = passed.any(0)
                    first = passed.float().argmax(0)
                    fid = torch.where(has, idx[first], torch.full_like(first, -1))
                    face_id[y0:y1, x0:x1] = fid.reshape(hb, wb)
        rows.append(torch.cat(row, dim=1))
    img = torch.cat(rows, dim=0)
    rgb, alpha, depth, normal = img[..., :3], img[..., 3], img[..., 4], img[..., 5:8]
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, normal=normal, max_weight=max_weight, face_id=face_id,
                        pairs_evaluated=pairs, faces_visible=int(keep.sum()))
