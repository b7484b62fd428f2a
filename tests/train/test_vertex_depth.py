"""The vertex-depth term (MeshSplatting): the fused Numba pass gives the torch twin's value and gradients, with many
vertices on one pixel, vertices behind the camera, outside the image, on uncovered pixels and beyond max_diff."""
import pytest
import torch

from trisplat.train.fused_vertex_depth import vertex_depth_fused
from trisplat.train.losses import vertex_depth_torch


def _case(seed=0, V=4000, H=24, W=32):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(V, 3, generator=g) * torch.tensor([2.0, 2.0, 2.0]) - torch.tensor([1.0, 1.0, -0.5])
    pos[:50, 2] = -1.0  # behind the camera
    pos[50:100, 0] = 9.0  # outside the image
    w2c = torch.eye(4)
    w2c[:3, 3] = torch.tensor([0.05, -0.02, 0.3])
    K = torch.tensor([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
    alpha = torch.rand(H, W, generator=g)
    alpha[:4] = 0.2  # uncovered rows
    depth = (0.5 + 2.0 * torch.rand(H, W, generator=g)) * alpha
    return pos, w2c, K, depth, alpha


@pytest.mark.parametrize("max_diff", [0.3, 10.0])
def test_fused_vertex_depth_matches_torch_value_and_gradients(max_diff):
    pos, w2c, K, depth, alpha = _case()
    outs = []
    for fn in (vertex_depth_torch, vertex_depth_fused):
        p, d, a = (t.clone().requires_grad_(True) for t in (pos, depth, alpha))
        loss = fn(p, w2c, K, d, a, max_diff)
        loss.backward()
        outs.append((loss.detach(), p.grad, d.grad, a.grad))
    (l0, gp0, gd0, ga0), (l1, gp1, gd1, ga1) = outs
    assert float(l0) > 0
    assert float(l1) == pytest.approx(float(l0), rel=1e-5)
    torch.testing.assert_close(gp1, gp0, rtol=1e-5, atol=1e-9)
    torch.testing.assert_close(gd1, gd0, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(ga1, ga0, rtol=1e-5, atol=1e-7)
    assert (gd0.abs() > 0).sum() < (gp0.abs().sum(1) > 0).sum()  # several vertices on some pixels


def test_no_vertex_counts_gives_zero_and_zero_gradients():
    pos, w2c, K, depth, alpha = _case()
    p = pos.clone().requires_grad_(True)
    loss = vertex_depth_fused(p, w2c, K, depth, torch.zeros_like(alpha), 0.3)
    loss.backward()
    assert float(loss) == 0.0 and float(p.grad.abs().sum()) == 0.0
