"""Where rendering runs: `--device auto|cpu|cuda` as a torch device and the renderer backend for it (the Numba kernels
on the CPU, the numba-cuda kernels on an NVIDIA GPU), with a precise reason when the GPU cannot be used."""
from __future__ import annotations

import importlib.util

import torch

DEVICE_CHOICES = ("auto", "cpu", "cuda")
GPU_HINT = ("pip install 'trisplat[gpu]' (numba-cuda) and a CUDA build of torch (trisplat installs the CPU build by "
            "default), on a machine with an NVIDIA GPU and its driver")


def cuda_unavailable() -> str | None:
    """Why the CUDA backend cannot render here, or None when it can: torch must see a CUDA device, numba-cuda must
    be installed (numba's own, older CUDA target cannot compile the kernels) and must see the GPU too."""
    if not torch.cuda.is_available():
        return ("torch sees no CUDA device (torch.cuda.is_available() is False: no NVIDIA GPU or driver here, or a "
                "CPU build of torch)")
    if importlib.util.find_spec("numba_cuda") is None:
        return "numba-cuda is not installed"
    from numba import cuda

    if not cuda.is_available():
        return "numba-cuda sees no CUDA device (numba.cuda.is_available() is False; numba.cuda.detect() says why)"
    return None


def resolve_device(name: str) -> torch.device:
    """A --device choice as a torch device: 'cpu'; 'cuda' (the numba-cuda kernels on the GPU: ValueError naming the
    reason and the fix when they cannot run here); 'auto': cuda when it can run, else cpu."""
    if name not in DEVICE_CHOICES:
        raise ValueError(f"device must be one of {DEVICE_CHOICES}, got {name!r}")
    if name == "cpu":
        return torch.device("cpu")
    reason = cuda_unavailable()
    if name == "auto":
        return torch.device("cpu" if reason else "cuda")
    if reason:
        raise ValueError(f"device 'cuda' asked for, but {reason}; nothing was run. Use --device cpu (the Numba "
                         f"kernels) or --device auto (the GPU when there is one, else the CPU); for the GPU: "
                         f"{GPU_HINT}")
    return torch.device("cuda")


def backend_for(device: torch.device | str) -> str:
    """The renderer backend for tensors on `device`: cuda (the numba-cuda kernels) on a GPU, numba (the parallel
    CPU kernels) on the CPU."""
    return "cuda" if torch.device(device).type == "cuda" else "numba"


def device_name(device: torch.device) -> str:
    """What a device is, in words, for benchmark notes ('cpu', or the GPU's name)."""
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    return str(device)
