"""Which image pairs to match: all of them (small sets), or a sequential window plus loop-closure pairs found by
image retrieval with a visual vocabulary built from the capture's own SIFT descriptors (no vocabulary file)."""
from __future__ import annotations

import warnings

import numpy as np
from scipy.cluster.vq import kmeans2, vq

Pair = tuple[int, int]  # indices into the ordered image list, i < j


def exhaustive_pairs(n: int) -> list[Pair]:
    """Every pair of n images: n (n - 1) / 2."""
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def sequential_pairs(n: int, overlap: int = 10, quadratic: bool = True) -> list[Pair]:
    """Each image with its `overlap` successors, plus (quadratic) the successors at distances 2^k beyond that, as
    COLMAP's sequential matcher does: consecutive video frames overlap most."""
    pairs = set()
    for i in range(n):
        for d in range(1, overlap + 1):
            if i + d < n:
                pairs.add((i, i + d))
        if quadratic:
            d = 2 ** int(np.ceil(np.log2(overlap + 1)))
            while i + d < n:
                pairs.add((i, i + d))
                d *= 2
    return sorted(pairs)


def retrieval_similarity(descriptors: list[np.ndarray], words: int = 256, sample: int = 50_000, iters: int = 8,
                         seed: int = 0) -> np.ndarray:
    """Cosine similarity [n,n] of tf-idf bag-of-words vectors, one per image.

    descriptors: per image, SIFT descriptors [Ni,128] (any dtype). The vocabulary (`words` k-means centres) is built
    from at most `sample` descriptors drawn evenly from all images, so no pre-trained vocabulary is needed.
    """
    rng = np.random.default_rng(seed)
    n = len(descriptors)
    feats = [np.asarray(d, dtype=np.float32) for d in descriptors]
    per_image = max(1, sample // max(n, 1))
    pool = [f[rng.choice(len(f), size=min(per_image, len(f)), replace=False)] for f in feats if len(f)]
    if not pool:
        return np.zeros((n, n))
    pool = np.concatenate(pool)
    k = int(min(words, max(2, len(pool) // 20)))
    # the vocabulary: k-means of the pooled descriptors (scipy's Lloyd iterations, seeded with random distinct
    # descriptors: scipy's k-means++ seeding costs O(k^2 n), minutes here); an empty cluster keeps its seed (it then
    # simply collects no words)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*clusters is empty.*")
        centres, _ = kmeans2(pool, k, iter=iters, minit="points", seed=rng, missing="warn")
    hist = np.zeros((n, k))
    for i, f in enumerate(feats):
        if len(f):
            hist[i] = np.bincount(vq(f, centres.astype(f.dtype), check_finite=False)[0], minlength=k)
    df = (hist > 0).sum(0)
    idf = np.log((n + 1) / (df + 1))
    tfidf = hist / np.maximum(hist.sum(1, keepdims=True), 1) * idf
    tfidf /= np.maximum(np.linalg.norm(tfidf, axis=1, keepdims=True), 1e-12)
    return tfidf @ tfidf.T


def loop_pairs(similarity: np.ndarray, neighbours: int = 5, min_distance: int = 10) -> list[Pair]:
    """For each image, its `neighbours` most similar images at least `min_distance` positions away in the sequence
    (candidate loop closures: a place seen again later)."""
    n = len(similarity)
    pairs = set()
    idx = np.arange(n)
    for i in range(n):
        far = np.abs(idx - i) >= max(min_distance, 1)
        cand = idx[far]
        if len(cand) == 0:
            continue
        best = cand[np.argsort(-similarity[i, cand], kind="stable")[:neighbours]]
        for j in best:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)
