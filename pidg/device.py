"""Where a run computes: resolving ``--device auto|cpu|cuda`` and saying, never guessing, what runs there.

A CUDA machine trains on the GPU with gsplat's rasterizer, the torch hash grid and the torch SSIM; a CPU trains
with pidg's numba kernels. Nothing falls back to the CPU silently: asking for CUDA without one, or for the gsplat
rasterizer without gsplat, is an error that names the fix.
"""
from __future__ import annotations

import contextlib
import fcntl
import functools
import importlib.util
import resource
import tempfile
from pathlib import Path
from typing import Literal

import torch

Device = Literal["auto", "cpu", "cuda"]
GSPLAT_HINT = "pip install gsplat (the CUDA rasterizer; see README), or --backend torch for the slow reference compositor"


class DeviceUnavailable(RuntimeError):
    """The requested device or a backend it needs is not available; the message says how to get it."""


def cuda_available() -> bool:
    return torch.cuda.is_available()


def gsplat_installed() -> bool:
    """Whether the gsplat package can be imported (without importing it: that compiles or loads CUDA code)."""
    return importlib.util.find_spec("gsplat") is not None


GSPLAT_BUILD_LOCK = Path(tempfile.gettempdir()) / "pidg-gsplat-build.lock"


@contextlib.contextmanager
def _exclusive(path: Path):
    """An inter-process lock (flock) held for the block: gsplat's first use deletes and rebuilds its build folder,
    so two processes building at once (test workers, parallel runs) break each other's build."""
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@functools.cache
def gsplat_load_error(device: torch.device) -> str | None:
    """Why gsplat cannot render on ``device`` (None when it can), found by rendering one Gaussian through its
    documented ``rasterization`` while holding :data:`GSPLAT_BUILD_LOCK`. gsplat compiles its CUDA code on first use
    (about a minute on 16 cores); a build that fails (compiler, CUDA toolkit) would otherwise surface as an
    ImportError at the first training step."""
    try:
        with _exclusive(GSPLAT_BUILD_LOCK):
            _render_one_gaussian(device)
    except Exception as err:  # noqa: BLE001  (any failure of the third-party build is reported, with its type)
        return f"{type(err).__name__}: {str(err).strip().splitlines()[-1] if str(err).strip() else 'no message'}"
    return None


def _render_one_gaussian(device: torch.device) -> None:
    from gsplat import rasterization

    one = torch.ones(1, device=device)
    rasterization(
        means=torch.tensor([[0.0, 0.0, 2.0]], device=device), quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device),
        scales=one.expand(1, 3) * 0.1, opacities=one * 0.5, colors=one.expand(1, 3), viewmats=torch.eye(4, device=device)[None],
        Ks=torch.tensor([[[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]]], device=device), width=8, height=8,
    )


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
        error = gsplat_load_error(device)
        if error is not None:
            raise DeviceUnavailable(
                f"gsplat is installed but cannot render on {device} ({error}): see gsplat's install notes for its CUDA "
                "build, or use --backend torch for the slow reference compositor"
            )
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
