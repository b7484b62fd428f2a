"""Real spherical harmonics up to degree 3 (the 3DGS band order and constants), evaluated per vertex."""
from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """(degree + 1)^2 coefficients per colour channel."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    return (degree + 1) ** 2


def sh_degree_from_bases(k: int) -> int:
    for d in range(4):
        if (d + 1) ** 2 == k:
            return d
    raise ValueError(f"{k} SH coefficients per channel is not (d+1)^2 for d in 0..3")


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient whose evaluation (C0 * dc + 0.5) gives `rgb`."""
    return (rgb - 0.5) / C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    return (C0 * dc + 0.5).clamp(min=0.0)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """The real SH basis Y_k(dir) for bands 0..degree: [N,(degree+1)^2] (dirs [N,3], normalised here)."""
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d[..., 0:1], d[..., 1:2], d[..., 2:3]
    cols = [torch.full_like(x, C0)]
    if degree >= 1:
        cols += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        cols += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
        if degree >= 3:
            cols += [
                C3[0] * y * (3 * xx - yy),
                C3[1] * xy * z,
                C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                C3[4] * x * (4 * zz - xx - yy),
                C3[5] * z * (xx - yy),
                C3[6] * x * (xx - 3 * yy),
            ]
    return torch.cat(cols, dim=-1)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """Colour from SH: sum_k sh[..., k, :] * Y_k(dir) + 0.5, clamped >= 0.

    sh: [N,K,3] coefficients, K = (d+1)^2; dirs: [N,3] view directions (camera centre -> vertex; normalised
    here); degree: evaluate only bands 0..degree (default: all K). Returns [N,3]. CPU float tensors go through the
    fused Numba kernels (trisplat.scene.sh_kernels), anything else through eval_sh_torch; both are exact and
    differentiable w.r.t. sh and dirs, and agree to rounding (tested).
    """
    K = sh.shape[-2]
    deg = sh_degree_from_bases(K) if degree is None else min(degree, sh_degree_from_bases(K))
    if (sh.ndim == 3 and dirs.ndim == 2 and sh.device.type == "cpu" and dirs.device.type == "cpu"
            and sh.dtype in (torch.float32, torch.float64) and dirs.is_floating_point()):
        from trisplat.scene.sh_kernels import FusedSH

        return FusedSH.apply(sh, dirs, num_sh_bases(deg))
    return eval_sh_torch(sh, dirs, deg)


def eval_sh_torch(sh: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """eval_sh in plain torch ops (any device; the readable oracle of the fused kernels)."""
    K = sh.shape[-2]
    deg = sh_degree_from_bases(K) if degree is None else min(degree, sh_degree_from_bases(K))
    basis = sh_basis(dirs, deg)
    # one product and one sum: their backward is two products, not one zero-filled [N,K,3] tensor per
    # coefficient (and an einsum's batched 1xK @ Kx3 matmuls are slower on a CPU)
    out = (basis.unsqueeze(-1) * sh[..., : basis.shape[-1], :]).sum(-2)
    return (out + 0.5).clamp(min=0.0)
