"""`trisplat bench losses`: the training step's fused Numba kernels vs their torch twins (forward + backward).

Random inputs (the kernels' cost does not depend on content): L1 + D-SSIM on [H,W,3], the depth-normal consistency
on a rendered-looking depth / alpha / normal triple, the SH colour of V vertices at degree 3 (gradients to the
coefficients and the view directions), and on a sphere of F faces the surface's normal smoothness (forward and
backward) and the per-face screen size (forward only: a statistic, no gradient). Both versions run in the same
process, one right after the other, so their ratio means more than either time on a shared machine.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import tyro

from trisplat.commands.style import CLI_STYLE
from trisplat.bench.common import BenchTable, median_ms


@dataclass
class LossBenchArgs:
    """Loss forward+backward time, fused kernel vs torch autograd."""

    sizes: list[int] = field(default_factory=lambda: [400, 800])
    """square image sizes (pixels)"""
    sh_vertices: list[int] = field(default_factory=lambda: [20_000, 125_000])
    """vertex counts for the SH colour case (degree 3)"""
    mesh_subdivisions: list[int] = field(default_factory=lambda: [5, 7])
    """icosphere subdivisions for the normal smoothness and screen size cases (5: 20k faces, 7: 328k)"""
    repeats: int = 10
    out: Path = Path("bench_results")
    """folder for losses.json and losses.md"""


def _fwd_bwd(f):
    """A call that evaluates the scalar f() and backpropagates it."""
    def call():
        f().backward()
    return call


def _cases(size: int):
    import torch

    from trisplat.train import losses
    from trisplat.train.fused_ssim import photometric_torch

    g = torch.Generator().manual_seed(size)
    pred = torch.rand(size, size, 3, generator=g).requires_grad_()
    gt = torch.rand(size, size, 3, generator=g)
    alpha = (0.3 + 0.7 * torch.rand(size, size, generator=g)).requires_grad_()
    depth = (alpha.detach() * (2.0 + torch.rand(size, size, generator=g))).requires_grad_()
    normal = torch.nn.functional.normalize(torch.randn(size, size, 3, generator=g), dim=-1).requires_grad_()
    K = torch.tensor([[1.2 * size, 0.0, size / 2], [0.0, 1.2 * size, size / 2], [0.0, 0.0, 1.0]])
    return [
        ("L1 + D-SSIM", _fwd_bwd(lambda: photometric_torch(pred, gt, 0.2)), _fwd_bwd(lambda: losses.photometric(pred, gt, 0.2))),
        ("depth-normal consistency", _fwd_bwd(lambda: losses.normal_consistency_torch(normal, depth, alpha, K)),
         _fwd_bwd(lambda: losses.normal_consistency(normal, depth, alpha, K))),
    ]


def _sh_case(n: int):
    import torch

    from trisplat.scene.sh import eval_sh_torch
    from trisplat.scene.sh_kernels import FusedSH

    g = torch.Generator().manual_seed(n)
    sh = (0.5 * torch.randn(n, 16, 3, generator=g)).requires_grad_()
    dirs = torch.randn(n, 3, generator=g).requires_grad_()
    w = torch.rand(n, 3, generator=g)
    return (_fwd_bwd(lambda: (eval_sh_torch(sh, dirs) * w).sum()),
            _fwd_bwd(lambda: (FusedSH.apply(sh, dirs, 16) * w).sum()))


def _mesh_cases(subdivisions: int):
    import torch
    import trimesh

    from trisplat.strategy.screen import projected_edge_px, projected_edge_px_torch
    from trisplat.train import losses

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    pos = torch.tensor(m.vertices, dtype=torch.float32, requires_grad=True)
    faces = torch.tensor(m.faces, dtype=torch.int64)
    pairs = losses.face_adjacency(faces)
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    K = torch.tensor([[300.0, 0.0, 200.0], [0.0, 300.0, 133.0], [0.0, 0.0, 1.0]])

    def edge(fn):
        def call():
            with torch.no_grad():
                fn(pos.detach(), faces, w2c, K, 0.01, 400, 266)
        return call

    return len(faces), [
        ("normal smoothness", _fwd_bwd(lambda: losses.normal_smoothness_torch(pos, faces, pairs)),
         _fwd_bwd(lambda: losses.normal_smoothness(pos, faces, pairs))),
        ("screen size (forward)", edge(projected_edge_px_torch), edge(projected_edge_px)),
    ]


def main(argv: list[str]) -> int:
    args = tyro.cli(LossBenchArgs, args=argv, prog="trisplat bench losses", description=__doc__, config=CLI_STYLE)
    table = BenchTable("losses", ["kernel", "size", "torch fwd+bwd ms", "fused fwd+bwd ms", "speed-up"])
    for size in args.sizes:
        for name, torch_fn, fused_fn in _cases(size):
            t_ms, f_ms = median_ms(torch_fn, args.repeats), median_ms(fused_fn, args.repeats)
            table.add(name, f"{size}x{size}", t_ms, f_ms, t_ms / f_ms)
            print(f"{name} {size}x{size}: torch {t_ms:.1f} ms, fused {f_ms:.1f} ms ({t_ms / f_ms:.1f}x)", flush=True)
    for n in args.sh_vertices:
        torch_fn, fused_fn = _sh_case(n)
        t_ms, f_ms = median_ms(torch_fn, args.repeats), median_ms(fused_fn, args.repeats)
        table.add("SH colour, degree 3", f"{n} vertices", t_ms, f_ms, t_ms / f_ms)
        print(f"SH colour {n} vertices: torch {t_ms:.1f} ms, fused {f_ms:.1f} ms ({t_ms / f_ms:.1f}x)", flush=True)
    for sub in args.mesh_subdivisions:
        n_faces, cases = _mesh_cases(sub)
        for name, torch_fn, fused_fn in cases:
            t_ms, f_ms = median_ms(torch_fn, args.repeats), median_ms(fused_fn, args.repeats)
            table.add(name, f"{n_faces} faces", t_ms, f_ms, t_ms / f_ms)
            print(f"{name} {n_faces} faces: torch {t_ms:.1f} ms, fused {f_ms:.1f} ms ({t_ms / f_ms:.1f}x)", flush=True)
    table.notes.append("Medians of --repeats runs after one warm-up; forward, then backward to every input that needs a "
                       "gradient (the render; depth, alpha and normal; SH coefficients and view directions).")
    md = table.write(args.out, "trisplat bench losses " + " ".join(argv))
    print(md.read_text())
    return 0
