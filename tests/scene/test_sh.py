"""The SH basis: orthonormal on the sphere, the 3DGS signs, gradients, and band truncation."""
import math

import torch

from trisplat.scene.sh import C0, C1, eval_sh, sh_basis


def _fibonacci_sphere(n: int) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    r = torch.sqrt(1 - z * z)
    phi = math.pi * (3 - math.sqrt(5)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def test_basis_is_orthonormal_on_the_sphere():
    d = _fibonacci_sphere(40_000)
    Y = sh_basis(d, 3)
    gram = 4 * math.pi * (Y.T @ Y) / d.shape[0]  # quadrature of int Y_i Y_j over the unit sphere
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=2e-3)


def test_basis_signs_follow_3dgs_and_ignore_direction_length():
    Y = sh_basis(torch.tensor([[0.0, 0.0, 5.0], [0.0, 2.0, 0.0]], dtype=torch.float64), 1)
    assert torch.allclose(Y[0], torch.tensor([C0, 0.0, C1, 0.0], dtype=torch.float64))
    assert torch.allclose(Y[1], torch.tensor([C0, -C1, 0.0, 0.0], dtype=torch.float64))


def test_eval_sh_is_the_basis_contraction_with_offset_clamp_and_truncation():
    g = torch.Generator().manual_seed(0)
    sh = torch.randn(64, 16, 3, generator=g, dtype=torch.float64)
    d = torch.randn(64, 3, generator=g, dtype=torch.float64)
    Y = sh_basis(d, 3)
    for deg in range(4):
        k = (deg + 1) ** 2
        want = (sum(Y[:, i : i + 1] * sh[:, i] for i in range(k)) + 0.5).clamp(min=0)
        assert torch.allclose(eval_sh(sh, d, deg), want)
        assert torch.allclose(eval_sh(sh[:, :k], d), want)


def test_eval_sh_gradients_to_coefficients_and_directions():
    g = torch.Generator().manual_seed(1)
    sh = (0.3 * torch.randn(6, 16, 3, generator=g, dtype=torch.float64)).requires_grad_()
    d = torch.randn(6, 3, generator=g, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: eval_sh(a, b), (sh, d))
