"""Per-image exposure and white balance: a small affine colour transform per training photo, learned with the scene.

Real photos differ in exposure and white balance (auto exposure, a cloud, a phone's tone mapping); one scene
cannot match all of them, and without a per-photo correction the triangles absorb the differences (floaters, wrong
colours). Each photo i gets rgb' = (I + A_i) rgb + b_i (A_i [3,3], b_i [3], both starting at zero) applied to the
render before the loss. The scene itself stays in the common colour of the photos: evaluation, test renders and
exported files use the uncorrected render (a held-out photo has no learned correction), as NeRF-W and the 3DGS
appearance variants report.

A finished run keeps its corrections in RUN/exposure.json. Evaluation adds a second, clearly named score from them:
each held-out photo's render with the correction its neighbours in the capture's photo order had
(`neighbour_correction`). Auto exposure drifts along a capture (bonsai's learned gains go from about 0.9 to 1.15 along
the sequence, and a per-channel gain fitted to each test photo alone agrees), so the plain score measures the scene
and the photo's exposure together; the matched one uses no pixel of the held-out photo.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from trisplat.io.atomic import atomic_write_text

FILE = "exposure.json"

PARAMS_PER_IMAGE = 12  # A (3x3, row-major) then b (3)
# A correction no camera makes: I + A scaling some colour direction by less than MIN_GAIN or more than MAX_GAIN
# (1.6 stops), or one colour direction more than MAX_GAIN_RATIO times another (a white balance shift far beyond a
# camera's). The correction is then explaining away a photo the scene cannot show: a wrong pose (bonsai's photos at
# a mirror position learned a red gain of 0.0 and a blue gain of 0.45), a person walking through, a different scene.
# Measured with the lazy Adam below on every training photo of bonsai (147) and fox (43): singular values 0.75-1.57,
# ratios with median 1.26 (bonsai) and 1.12 (fox), at most 1.60 and 1.43, a continuous tail: the last photo of bonsai's
# sequence (DSCF5856, an ordinary photo whose floor few other views see) reached 1.60. A white balance shift of one
# stop between two colour directions (ratio 2) is beyond them; the mirror-position photos were beyond it (2.1, 0.0).
MIN_GAIN, MAX_GAIN, MAX_GAIN_RATIO = 1 / 3, 3.0, 2.0


class Exposure:
    """Affine colour corrections for `n_images` photos (indexed like SceneData.cameras), with their own Adam."""

    def __init__(self, n_images: int, lr: float, values: torch.Tensor | None = None, train_indices=None):
        init = torch.zeros(n_images, PARAMS_PER_IMAGE) if values is None else values.detach().clone().float()
        if init.shape != (n_images, PARAMS_PER_IMAGE):
            raise ValueError(f"exposure parameters must be [{n_images},{PARAMS_PER_IMAGE}], got {tuple(init.shape)}")
        self.params = torch.nn.Parameter(init)
        self.lr = float(lr)
        # Lazy (sparse) Adam: a training step sees one photo, so only that photo's row has a gradient. Dense Adam
        # would keep moving every other row on its stale momentum after each visit (beta1 0.9: the momentum lasts
        # ~10 steps), in whatever direction the last visit pointed: on bonsai (147 photos, each seen
        # every ~147 steps) the final corrections fitted 4 of 7 sampled training photos worse than no correction at
        # all (one: 25.6 dB against the render, 20.8 with its correction). SparseAdam updates a row and its moments
        # only when the row has a gradient.
        self.optimizer = torch.optim.SparseAdam([self.params], lr=self.lr, eps=1e-15)
        self.train = torch.arange(n_images) if train_indices is None else torch.as_tensor(train_indices).long()

    def apply(self, rgb: torch.Tensor, index: int) -> torch.Tensor:
        """rgb [H,W,3] as photo `index` would show it."""
        return affine(rgb, self.params[index])

    def step(self, scale: float = 1.0) -> None:
        for group in self.optimizer.param_groups:
            group["lr"] = self.lr * scale
        grad = self.params.grad
        if grad is None:
            return
        if not grad.is_sparse:  # the rows some photo's loss reached (sparse_dim 1: whole rows)
            self.params.grad = grad.to_sparse(1)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        # the gauge: a colour change common to every photo belongs to the scene, not to the corrections (else the
        # scene drifts while the corrections make up for it, and the uncorrected test renders pay for it)
        with torch.no_grad():
            self.params[self.train] -= self.params[self.train].mean(0)

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def state(self) -> torch.Tensor:
        return self.params.detach().clone()

    def save(self, run_dir: Path, names: list[str]) -> None:
        """RUN/exposure.json: every photo's correction (rows of photos no step saw stay zero) and the training
        photos' indices, in the capture's photo order (`names`)."""
        record = {"model": "rgb' = (I + A) rgb + b on the render's colour in [0,1]; params = A (3x3, row-major), b",
                  "photos": list(names), "train": self.train.tolist(), "params": self.params.detach().tolist()}
        atomic_write_text(Path(run_dir) / FILE, json.dumps(record))

    def misfits(self) -> list[tuple[int, float, float]]:
        """Training photos whose correction no camera makes (see MIN_GAIN): (index, smallest and largest singular
        value of I + A), worst first."""
        idx = self.train
        if not len(idx):
            return []
        A = torch.eye(3) + self.params.detach()[idx, :9].reshape(-1, 3, 3).float()
        sv = torch.linalg.svdvals(A)
        lo, hi = sv[:, -1], sv[:, 0]
        bad = (lo < MIN_GAIN) | (hi > MAX_GAIN) | (hi > MAX_GAIN_RATIO * lo.clamp_min(1e-6))
        out = [(int(idx[k]), float(lo[k]), float(hi[k])) for k in torch.nonzero(bad).flatten().tolist()]
        return sorted(out, key=lambda x: x[2] / max(x[1], 1e-6), reverse=True)

    def summary(self) -> dict:
        """The largest correction learned: gain (diagonal of I + A) farthest from 1, largest |offset|."""
        p = self.params.detach()
        if not len(p):
            return {"max_gain_change": 0.0, "max_offset": 0.0}
        diag = p[:, [0, 4, 8]]
        return {"max_gain_change": float(diag.abs().max()), "max_offset": float(p[:, 9:].abs().max())}


def load_saved(run_dir: Path, n_photos: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(params [n_photos,12], training photo indices) from RUN/exposure.json, or None when the run learned none."""
    path = Path(run_dir) / FILE
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
        params = np.asarray(record["params"], dtype=np.float64)
        train = np.asarray(record["train"], dtype=np.int64)
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: malformed colour corrections ({exc})") from exc
    if params.shape != (n_photos, PARAMS_PER_IMAGE) or not len(train) or train.min() < 0 or train.max() >= n_photos:
        raise ValueError(f"{path}: colour corrections for {len(params)} photos (training indices up to "
                         f"{train.max(initial=-1)}), but the capture has {n_photos}: was it loaded with other options?")
    return params, train


def neighbour_correction(params: np.ndarray, train: np.ndarray, index: int) -> np.ndarray:
    """The correction [12] photo `index` most likely needs: its own for a training photo; for a held-out one,
    interpolated linearly by position in the photo order between the training photos just before and after it (the
    nearest one at either end of the capture). Reads no pixel of the photo itself."""
    train = np.sort(np.asarray(train, dtype=np.int64))
    if index in train:
        return params[index]
    before, after = train[train < index], train[train > index]
    if not len(before):
        return params[after[0]]
    if not len(after):
        return params[before[-1]]
    a, b = before[-1], after[0]
    t = (index - a) / (b - a)
    return (1.0 - t) * params[a] + t * params[b]


def affine(rgb: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """rgb [...,3] through the correction p [12]: (I + A) rgb + b, in rgb's dtype."""
    A = torch.eye(3, dtype=rgb.dtype) + p[:9].reshape(3, 3).to(rgb.dtype)
    return rgb @ A.T + p[9:].to(rgb.dtype)


def apply_correction(rgb: np.ndarray, p: np.ndarray) -> np.ndarray:
    """rgb [...,3] in [0,1] with correction p [12] applied (`affine`), clipped to [0,1] as a display shows it."""
    out = affine(torch.as_tensor(np.asarray(rgb, dtype=np.float64)), torch.as_tensor(np.asarray(p, dtype=np.float64)))
    return out.clamp(0.0, 1.0).numpy()
