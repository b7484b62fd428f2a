"""The fused depth-normal consistency kernel against its torch twin (value and every gradient)."""
import pytest
import torch

from trisplat.train.fused_normal import normal_consistency_fused
from trisplat.train.losses import normal_consistency, normal_consistency_torch


def _inputs(seed, H, W, *, smooth=True):
    """A rendered-looking view: a tilted, bumpy surface with holes (alpha < 0.5) and random rendered normals."""
    g = torch.Generator().manual_seed(seed)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    depth = 2.0 + 0.01 * u + 0.02 * v + (0.05 * torch.sin(u / 3) * torch.cos(v / 4) if smooth else 0)
    depth = depth + 0.01 * torch.rand(H, W, generator=g, dtype=torch.float64)
    alpha = 0.3 + 0.7 * torch.rand(H, W, generator=g, dtype=torch.float64)
    alpha[H // 3: H // 2, W // 4: W // 2] = 0.2  # a hole
    depth = depth * alpha  # expected depth = alpha * surface depth
    normal = torch.nn.functional.normalize(torch.randn(H, W, 3, generator=g, dtype=torch.float64), dim=-1)
    normal = normal * alpha[..., None]
    K = torch.tensor([[1.3 * W, 0.0, W / 2 + 0.3], [0.0, 1.2 * W, H / 2 - 0.7], [0.0, 0.0, 1.0]])
    return normal, depth, alpha, K


@pytest.mark.parametrize("seed,H,W", [(0, 16, 16), (1, 23, 37), (2, 40, 31)])
def test_value_and_gradients_match_the_torch_twin(seed, H, W):
    normal, depth, alpha, K = _inputs(seed, H, W)
    ref_in = [t.clone().requires_grad_() for t in (normal, depth, alpha)]
    ref = normal_consistency_torch(*ref_in, K.double())
    ref.backward()
    new_in = [t.float().clone().requires_grad_() for t in (normal, depth, alpha)]
    out = normal_consistency_fused(*new_in, K)
    assert out is not None
    (2.5 * out).backward()  # an upstream gradient other than 1
    assert float(out.detach()) == pytest.approx(float(ref.detach()), rel=1e-5, abs=1e-6)
    for a, b, name in zip(new_in, ref_in, ("normal", "depth", "alpha")):
        scale = float(b.grad.abs().max())
        assert scale > 0, name
        err = float((a.grad.double() - 2.5 * b.grad).abs().max())
        assert err <= 1e-4 * scale, f"{name}: max error {err:.3g} vs gradient scale {scale:.3g}"


def test_dispatch_uses_the_kernel_on_cpu_float32_and_torch_otherwise():
    normal, depth, alpha, K = _inputs(3, 12, 14)
    d64 = normal_consistency(normal, depth, alpha, K.double())  # float64 -> torch path
    d32 = normal_consistency(normal.float(), depth.float(), alpha.float(), K)
    assert float(d32) == pytest.approx(float(d64), rel=1e-5)
    assert normal_consistency_fused(normal, depth, alpha, K) is None  # float64 is not the kernel's


def test_flat_surface_with_matching_normals_costs_nothing():
    H, W = 20, 24
    K = torch.tensor([[30.0, 0.0, 12.0], [0.0, 30.0, 10.0], [0.0, 0.0, 1.0]])
    depth = torch.full((H, W), 3.0)  # fronto-parallel plane: depth normal (0, 0, -1)
    alpha = torch.ones(H, W)
    normal = torch.zeros(H, W, 3)
    normal[..., 2] = -1.0
    out = normal_consistency_fused(normal.requires_grad_(), depth, alpha, K)
    assert float(out.detach()) == pytest.approx(0.0, abs=1e-6)
    normal2 = normal.detach().clone()
    normal2[..., 2] = 1.0  # facing away: the worst case, 1 - (-1) = 2
    assert float(normal_consistency_fused(normal2, depth, alpha, K)) == pytest.approx(2.0, abs=1e-6)


def test_nothing_covered_gives_zero_and_zero_gradients():
    normal, depth, alpha, K = _inputs(4, 10, 10)
    alpha = torch.full_like(alpha, 0.1).float().requires_grad_()
    normal = normal.float().requires_grad_()
    depth = depth.float().requires_grad_()
    out = normal_consistency_fused(normal, depth, alpha, K)
    out.backward()
    assert float(out.detach()) == 0.0
    assert all(float(t.grad.abs().max()) == 0.0 for t in (normal, depth, alpha))
