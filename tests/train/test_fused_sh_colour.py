"""Vertex colours from the two SH parameters (trisplat.train.fused_sh_colour) against their torch twin (SH of the
joined table): value and the gradients of sh_dc, sh_rest and the directions, for every number of bases, with
clamped colours and a zero direction, at any thread count; and the trainer's render with them equals the render of
the joined table."""
from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from trisplat.train.fused_sh_colour import sh_colours, sh_colours_torch


def _inputs(K: int, dtype=torch.float64, n: int = 97):
    g = torch.Generator().manual_seed(K)
    dc = torch.randn(n, 1, 3, generator=g, dtype=dtype)
    rest = 0.5 * torch.randn(n, 15, 3, generator=g, dtype=dtype)
    dirs = torch.randn(n, 3, generator=g, dtype=dtype)
    dirs[5] = 0.0  # the clamped normalisation
    dc[7], rest[7] = -3.0, 0.0  # colours clamped at 0: no gradient through them
    return dc, rest, dirs, torch.randn(n, 3, generator=g, dtype=dtype)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("K", [1, 4, 9, 16])
def test_value_and_gradients_match_the_joined_table(K, threads):
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        dc, rest, dirs, w = _inputs(K)
        a = [t.clone().requires_grad_(True) for t in (dc, rest, dirs)]
        b = [t.clone().requires_grad_(True) for t in (dc, rest, dirs)]
        ca, cb = sh_colours(*a, K), sh_colours_torch(*b, K)
        torch.testing.assert_close(ca, cb, rtol=1e-12, atol=1e-12)
        assert float(ca[7].detach().abs().max()) == 0.0
        (ca * w).sum().backward()
        (cb * w).sum().backward()
        for x, y in zip(a, b):  # (torch leaves no gradient where there is none: the directions at K = 1)
            torch.testing.assert_close(x.grad, torch.zeros_like(x) if y.grad is None else y.grad, rtol=1e-10,
                                       atol=1e-12)
        assert float(a[1].grad[:, K - 1:].abs().sum()) == 0.0
        assert float(a[0].grad[7].abs().max()) == 0.0
    finally:
        numba.set_num_threads(before)


def test_float32_and_more_bases_than_kept():
    dc, rest, dirs, w = (t.float() for t in _inputs(16))
    rest = rest[:, :3].contiguous()  # degree 1 parameters asked for 16 bases: all 4 of them
    a = [t.clone().requires_grad_(True) for t in (dc, rest, dirs)]
    b = [t.clone().requires_grad_(True) for t in (dc, rest, dirs)]
    ca, cb = sh_colours(*a, 16), sh_colours_torch(*b, 16)
    assert ca.dtype == torch.float32
    torch.testing.assert_close(ca, cb, rtol=1e-5, atol=1e-6)
    (ca * w).sum().backward()
    (cb * w).sum().backward()
    for x, y in zip(a, b):
        torch.testing.assert_close(x.grad, y.grad, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("linear_light", [False, True])
def test_a_render_from_the_colours_equals_the_render_of_the_joined_table(linear_light):
    """What the trainer renders (the colours, then the renderer) against the renderer's own SH evaluation of the
    joined table: the same image and the same gradients of both SH parameters and the positions."""
    from trisplat.render import rasterize
    from trisplat.render.rasterize import camera_center

    g = torch.Generator().manual_seed(4)
    pos = torch.randn(30, 3, generator=g) * 0.5 + torch.tensor([0.0, 0.0, 3.0])
    faces = torch.randint(0, 30, (20, 3), generator=g, dtype=torch.int32)
    dc, rest = torch.randn(30, 1, 3, generator=g), 0.3 * torch.randn(30, 15, 3, generator=g)
    op = torch.full((30,), 0.8)
    w2c, K = torch.eye(4), torch.tensor([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    grads, images = [], []
    for joined in (False, True):
        p, d, r = (t.clone().requires_grad_(True) for t in (pos, dc, rest))
        colours = torch.cat([d, r], 1)[:, :9] if joined else sh_colours(d, r, p - camera_center(w2c), 9)
        out = rasterize(p, faces, colours, op, 0.5, w2c, K, 32, 24, background=torch.tensor([0.2, 0.3, 0.4]),
                        linear_light=linear_light)
        (out.rgb * torch.linspace(0, 1, out.rgb.numel()).reshape(out.rgb.shape)).sum().backward()
        images.append(out.rgb.detach())
        grads.append((p.grad, d.grad, r.grad))
    assert float(images[0].std()) > 0
    torch.testing.assert_close(images[0], images[1], rtol=1e-6, atol=1e-6)
    for a, b in zip(*grads):
        assert float(b.abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("threads", [1, 2])
def test_only_the_vertices_asked_for_are_evaluated(threads):
    """only=mask: the masked rows' colours and gradients are the full evaluation's, bit for bit; the other rows get
    colour 0 and zero gradients (a mask in blocks and scattered, so both the selection and the clearing are hit)."""
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        dc, rest, dirs, w = _inputs(16, n=301)
        mask = np.zeros(301, np.uint8)
        mask[40:90] = 1
        mask[::7] = 1
        sel = mask.astype(bool)
        a = [t.clone().requires_grad_(True) for t in (dc, rest, dirs)]
        b = [t.clone().requires_grad_(True) for t in (dc, rest, dirs)]
        ca, cb = sh_colours(*a, 16, only=mask), sh_colours(*b, 16)
        assert torch.equal(ca[sel], cb[sel]) and float(ca[~sel].abs().max()) == 0.0
        (ca * w).sum().backward()
        (cb * torch.where(torch.as_tensor(sel)[:, None], w, 0.0)).sum().backward()  # what reads only the mask
        for x, y in zip(a, b):
            assert torch.equal(x.grad[sel], y.grad[sel])
            assert float(x.grad[~sel].abs().max()) == 0.0
        empty = [t.clone().requires_grad_(True) for t in (dc, rest, dirs)]
        c0 = sh_colours(*empty, 16, only=np.zeros(301, np.uint8))
        assert float(c0.abs().max()) == 0.0
        (c0 * w).sum().backward()
        assert all(float(t.grad.abs().max()) == 0.0 for t in empty)
    finally:
        numba.set_num_threads(before)


@pytest.mark.parametrize("seed", range(4))
def test_vertices_in_view_hold_every_vertex_the_render_reads(seed):
    """The render reads the colours and opacities of the faces setup_faces keeps (ntiles > 0): vertices_in_view marks
    all of their vertices (random scenes with faces off-screen, behind the camera, across the near plane, huge), and
    leaves out some, so it is no mask of everything. A render with every other colour and opacity scrambled is the
    same render, with the same gradients."""
    from tests.render.render_scenes import random_scene
    from trisplat.render import kernels as kn
    from trisplat.render import rasterize
    from trisplat.render.rasterize import vertices_in_view

    pos, faces, col, op, w2c, K = random_scene(seed, n_faces=60, dtype=torch.float32)
    W, H = 40, 32
    mask = vertices_in_view(pos, faces, w2c, K, W, H, near=0.01)
    F = len(faces)
    theta = np.empty((F, kn.N_THETA), np.float32)
    rect, key = np.empty((F, 4), np.int32), np.zeros(F, np.float32)
    argmin, ntiles = np.empty(F, np.int8), np.empty(F, np.int64)
    kn.setup_faces(pos.numpy(), faces.numpy(), w2c.double().numpy(), K.double().numpy(), col.numpy(), op.numpy(),
                   True, 0.01, 1e10, 0.0, 0.0, W, H, 8, theta, rect, key, argmin, ntiles)
    read = np.unique(faces.numpy()[ntiles > 0].ravel())
    assert mask[read].all()
    assert 0 < mask.sum() < len(mask)
    off = torch.as_tensor(mask == 0)
    outs = []
    for scramble in (False, True):
        c, o = col.clone(), op.clone()
        if scramble:
            c[off], o[off] = 0.123, 0.456
        c.requires_grad_(True)
        out = rasterize(pos, faces, c, o, 0.7, w2c, K, W, H)
        (out.rgb * torch.linspace(0, 1, out.rgb.numel()).reshape(out.rgb.shape)).sum().backward()
        outs.append((out.rgb.detach(), c.grad))
    assert torch.equal(outs[0][0], outs[1][0]) and torch.equal(outs[0][1], outs[1][1])
    assert float(outs[0][1][off].abs().max()) == 0.0
