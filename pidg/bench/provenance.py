"""Where and from what a benchmark figure was measured: the source commit and the machine.

Absolute times only compare on the same processor: the numba kernels are compiled for the host CPU, and the same
code ran the issue-15 OpenSplat case 3x slower on a host compiled for ``znver1`` (AVX2 split over 128-bit units)
than on the processor of earlier figures. Every bench therefore records the CPU model, the target LLVM compiled
the kernels for and the widest vector instruction set it could use, beside the thread counts.
"""
from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Any

import llvmlite.binding as llvm
import numba
import torch

#: The vector instruction sets the compiled kernels can use, widest first (LLVM feature names).
VECTOR_ISAS = ("avx512f", "avx2", "avx", "sse4.2", "neon")


def git_commit(src: Path | None = None) -> str | None:
    """The commit of the pidg source tree at ``src`` (default: this package's checkout), with ``+dirty`` when it has
    uncommitted changes; None outside git, and None when the enclosing repository does not track this tree (a copy
    of the package inside some other checkout would otherwise report that checkout's commit)."""
    src = Path(__file__).resolve().parents[2] if src is None else src
    try:
        subprocess.run(["git", "ls-files", "--error-unmatch", "pidg/__init__.py"], cwd=src, capture_output=True,
                       timeout=10, check=True)
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=src, capture_output=True, text=True, timeout=10, check=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "."], cwd=src,
                               capture_output=True, text=True, timeout=10, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


def cpu_model() -> str:
    """The processor's marketing name (``/proc/cpuinfo`` on Linux, else what the platform reports)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def vector_isa(features: str) -> str | None:
    """The widest of :data:`VECTOR_ISAS` enabled in an LLVM feature string (``+avx2,-avx512f,...``)."""
    enabled = {f[1:] for f in features.split(",") if f.startswith("+")}
    return next((isa for isa in VECTOR_ISAS if isa in enabled), None)


def machine() -> dict[str, Any]:
    """Where a figure was computed: host, OS, Python, torch, CPUs (model, compile target, vector width, threads),
    GPU, and OpenMP's wait settings."""
    return {
        "host": platform.node(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpus": os.cpu_count(),
        "cpu_model": cpu_model(),
        "cpu_target": llvm.get_host_cpu_name(),  # what numba compiles the kernels for
        "vector_isa": vector_isa(llvm.get_host_cpu_features().flatten()),
        "torch_threads": torch.get_num_threads(),
        "numba_threads": numba.get_num_threads(),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        # how idle OpenMP threads wait (pidg._env): a kernel launch costs ~4 us or ~100 us by these
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "gomp_spincount": os.environ.get("GOMP_SPINCOUNT"),
    }


def machine_line(here: dict[str, Any], commit: str | None) -> str:
    """One line for a bench's log (``here`` from :func:`machine`, ``commit`` from :func:`git_commit`, read once by
    the caller, which also stores it): enough to tell whether two logs' absolute times can be compared."""
    return (f"machine: {here['cpu_model']} (kernels compiled for {here['cpu_target']}, {here['vector_isa']}), "
            f"{here['cpus']} CPUs, torch threads {here['torch_threads']}, numba threads {here['numba_threads']}, "
            f"GPU {here['gpu']}; OpenMP wait {here['omp_wait_policy']}, spin {here['gomp_spincount']}; commit {commit}")
