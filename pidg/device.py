"""Where a run computes: resolving ``--device auto|cpu|cuda`` and saying, never guessing, what runs there.

A CUDA machine trains on the GPU with gsplat's rasterizer, the torch hash grid and the torch SSIM; a CPU trains
with pidg's numba kernels. Nothing falls back to the CPU silently: asking for CUDA without one, or for the gsplat
rasterizer without gsplat, is an error that names the fix.
"""
from __future__ import annotations

import importlib.util
import resource
from typing import Literal

import torch

from pidg.errors import DeviceUnavailable
from pidg.render.rasterize_gsplat import require_gsplat

Device = Literal["auto", "cpu", "cuda"]
GSPLAT_HINT = "pip install gsplat (the CUDA rasterizer; see README), or --backend torch for the slow reference compositor"


def cuda_available() -> bool:
    return torch.cuda.is_available()


def gsplat_installed() -> bool:
    """Whether the gsplat package can be imported (without importing it: that compiles or loads CUDA code)."""
    return importlib.util.find_spec("gsplat") is not None


def resolve_device(device: Device | str) -> torch.device:
    """auto: the first CUDA device when there is one, else the CPU; cuda without CUDA is an error."""
    if device == "auto":
        return torch.device("cuda") if cuda_available() else torch.device("cpu")
    if device == "cpu":
        return torch.device("cpu")
    if device == "cuda":
        if not cuda_available():
            build = f"torch {torch.__version__}" + ("" if torch.version.cuda else ", built without CUDA")
            raise DeviceUnavailable(
                f"--device cuda: no CUDA device is available ({build}); use --device cpu, or install a CUDA build of "
                "torch on a machine with an NVIDIA GPU"
            )
        return torch.device("cuda")
    raise ValueError(f"--device must be auto, cpu or cuda, got {device!r}")


def rasterizer_for(backend: str, device: torch.device) -> str:
    """The rasterizer a run uses (see ``pidg.render.api``), checked against the device before any work starts."""
    resolved = ("gsplat" if device.type == "cuda" else "cpu") if backend == "auto" else backend
    if resolved == "gsplat":
        if device.type != "cuda":
            raise DeviceUnavailable("--backend gsplat renders on CUDA only: use --device cuda, or --backend cpu")
        if not gsplat_installed():
            raise DeviceUnavailable(f"--device cuda renders with gsplat, which is not installed: {GSPLAT_HINT}")
        require_gsplat(device)
    if resolved == "cpu" and device.type != "cpu":
        raise DeviceUnavailable(f"--backend cpu is the numba CPU kernel and cannot render on {device.type}: use --backend auto")
    return resolved


def describe(device: torch.device) -> str:
    """One line naming the hardware, for logs and summaries."""
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index} ({torch.cuda.get_device_name(index)}, torch {torch.__version__}, CUDA {torch.version.cuda})"
    return f"cpu ({torch.get_num_threads()} threads, torch {torch.__version__})"


def synchronize(device: torch.device) -> None:
    """Wait for queued GPU work (timings on CUDA are otherwise those of kernel launches); nothing on CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def peak_memory_mb(device: torch.device) -> dict[str, float]:
    """Peak memory so far, in MB: the process's resident memory, and on CUDA the GPU memory torch allocated."""
    out = {"peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}  # Linux reports KiB
    if device.type == "cuda":
        out["peak_gpu_memory_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    return out
