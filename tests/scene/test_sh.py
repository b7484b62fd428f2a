"""The SH basis: orthonormal on the sphere, the 3DGS signs, gradients, and band truncation."""
import math

import torch

from trisplat.scene.sh import C0, C1, eval_sh, eval_sh_torch, sh_basis


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
    assert torch.autograd.gradcheck(lambda a, b: eval_sh_torch(a, b), (sh, d))


def test_fused_sh_matches_the_torch_oracle_values_and_gradients():
    """The Numba kernels against eval_sh_torch: every degree, clamped channels, float32 and float64, and gradients
    to coefficients and (unnormalised) directions; gradcheck on the fused path itself."""
    from trisplat.scene.sh_kernels import FusedSH

    g = torch.Generator().manual_seed(2)
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-5)):
        for deg in range(4):
            sh = (0.8 * torch.randn(300, 16, 3, generator=g, dtype=dtype)).requires_grad_()
            d = (3 * torch.randn(300, 3, generator=g, dtype=dtype)).requires_grad_()
            w = torch.randn(300, 3, generator=g, dtype=dtype)
            fused = FusedSH.apply(sh, d, (deg + 1) ** 2)
            ref = eval_sh_torch(sh, d, deg)
            assert (ref == 0).any()  # some channels are clamped
            torch.testing.assert_close(fused, ref, atol=tol, rtol=tol)
            gs_f, gd_f = torch.autograd.grad((fused * w).sum(), (sh, d))
            gs_r, gd_r = torch.autograd.grad((ref * w).sum(), (sh, d), allow_unused=True)
            gd_r = torch.zeros_like(d) if gd_r is None else gd_r  # degree 0 does not depend on the direction
            torch.testing.assert_close(gs_f, gs_r, atol=tol, rtol=tol)
            torch.testing.assert_close(gd_f, gd_r, atol=10 * tol, rtol=10 * tol)
            assert (gs_f[:, (deg + 1) ** 2:] == 0).all()
    sh = (0.3 * torch.randn(5, 16, 3, generator=g, dtype=torch.float64)).requires_grad_()
    d = torch.randn(5, 3, generator=g, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: FusedSH.apply(a, b, 16), (sh, d))
