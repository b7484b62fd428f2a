"""Pair selection: exhaustive, sequential windows, retrieval loop closures."""
from __future__ import annotations

import numpy as np

from trisplat.sfm.pairs import exhaustive_pairs, loop_pairs, retrieval_similarity, sequential_pairs


def test_exhaustive_and_sequential_pairs():
    assert exhaustive_pairs(4) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    p = sequential_pairs(40, overlap=3)
    assert (0, 1) in p and (0, 3) in p and (0, 4) in p and (0, 8) in p and (0, 16) in p and (0, 32) in p
    assert (0, 5) not in p and (0, 9) not in p
    assert all(i < j < 40 for i, j in p)
    assert sequential_pairs(40, overlap=3, quadratic=False) == [(i, i + d) for i in range(40) for d in (1, 2, 3)
                                                                 if i + d < 40]


def test_retrieval_finds_the_revisited_place():
    """Images 0-29 walk through 'places' 0..29; image 29 sees place 2 again: its best distant match is image 2."""
    rng = np.random.default_rng(0)
    places = rng.normal(size=(30, 40, 128)).astype(np.float32) * 30 + 60  # 40 distinct descriptors per place
    order = list(range(29)) + [2]
    descs = [places[p] + rng.normal(size=(40, 128)).astype(np.float32) for p in order]
    sim = retrieval_similarity(descs, words=256, seed=0)
    assert sim.shape == (30, 30)
    np.testing.assert_allclose(np.diag(sim), 1.0, atol=1e-9)
    far = [j for j in range(30) if abs(j - 29) >= 5]
    assert far[int(np.argmax(sim[29, far]))] == 2
    pairs = loop_pairs(sim, neighbours=1, min_distance=5)
    assert (2, 29) in pairs
    assert all(j - i >= 5 for i, j in pairs)
