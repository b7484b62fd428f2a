"""`trisplat bench losses`: the training losses' fused Numba kernels vs their torch twins (forward + backward).

Random images (the kernels' cost does not depend on content): L1 + D-SSIM on [H,W,3], and the depth-normal
consistency on a rendered-looking depth / alpha / normal triple. Both versions run in the same process, one right
after the other, so their ratio means more than either time on a shared machine.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import tyro

from trisplat.bench.common import BenchTable, median_ms


@dataclass
class LossBenchArgs:
    """Loss forward+backward time, fused kernel vs torch autograd."""

    sizes: list[int] = field(default_factory=lambda: [400, 800])
    """square image sizes (pixels)"""
    repeats: int = 10
    out: Path = Path("bench_results")
    """folder for losses.json and losses.md"""


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

    def run(f):
        def call():
            f().backward()
        return call

    return [
        ("L1 + D-SSIM", run(lambda: photometric_torch(pred, gt, 0.2)), run(lambda: losses.photometric(pred, gt, 0.2))),
        ("depth-normal consistency", run(lambda: losses.normal_consistency_torch(normal, depth, alpha, K)),
         run(lambda: losses.normal_consistency(normal, depth, alpha, K))),
    ]


def main(argv: list[str]) -> int:
    args = tyro.cli(LossBenchArgs, args=argv, prog="trisplat bench losses", description=__doc__)
    table = BenchTable("losses", ["loss", "image", "torch fwd+bwd ms", "fused fwd+bwd ms", "speed-up"])
    for size in args.sizes:
        for name, torch_fn, fused_fn in _cases(size):
            t_ms, f_ms = median_ms(torch_fn, args.repeats), median_ms(fused_fn, args.repeats)
            table.add(name, f"{size}x{size}", t_ms, f_ms, t_ms / f_ms)
            print(f"{name} {size}x{size}: torch {t_ms:.1f} ms, fused {f_ms:.1f} ms ({t_ms / f_ms:.1f}x)", flush=True)
    table.notes.append("Medians of --repeats runs after one warm-up; forward, then backward to every input that needs a "
                       "gradient (the render; depth, alpha and normal).")
    md = table.write(args.out, "trisplat bench losses " + " ".join(argv))
    print(md.read_text())
    return 0
