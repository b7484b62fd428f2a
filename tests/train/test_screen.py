"""The per-face screen size (longest projected edge, pixels) of the pruning and densification rules: the Numba kernel
against its torch twin, including faces behind the near plane and faces off screen."""
import numpy as np
import torch

from trisplat.strategy.screen import projected_edge_px, projected_edge_px_torch


def test_kernel_matches_the_torch_twin():
    rng = np.random.default_rng(0)
    pos = torch.tensor(rng.uniform(-3, 3, (3000, 3)), dtype=torch.float32)
    faces = torch.tensor(rng.integers(0, 3000, (5000, 3)), dtype=torch.int64)
    a = 0.4
    w2c = torch.eye(4)
    w2c[:3, :3] = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], dtype=torch.float32)
    w2c[:3, 3] = torch.tensor([0.2, -0.1, 2.5])
    K = torch.tensor([[120.0, 0, 80], [0, 110.0, 60], [0, 0, 1]])
    for size in ((160, 120), (None, None)):
        got = projected_edge_px(pos, faces, w2c, K, 0.05, *size)
        want = projected_edge_px_torch(pos, faces, w2c, K, 0.05, *size)
        assert got.dtype == torch.float32 and got.shape == (5000,)
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-3)
        # every case is present: behind the near plane, off screen (with the size given), on screen
        assert (want == 0).sum() > 100 and (want > 0).sum() > 100
    assert (projected_edge_px_torch(pos, faces, w2c, K, 0.05, 160, 120) == 0).sum() > \
        (projected_edge_px_torch(pos, faces, w2c, K, 0.05) == 0).sum()
