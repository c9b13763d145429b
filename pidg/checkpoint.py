"""Atomic checkpoints: a run never leaves a half-written file, and resuming restores every random state.

A run folder holds ``config.json`` (the resolved run config) and ``checkpoint.pt`` (a dict with ``format``, the scene
model under ``"model"`` and, for training, everything else a resumed run needs).
"""
from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch


CHECKPOINT_FILE = "checkpoint.pt"  # the last good state: a failure never writes here
FAILED_CHECKPOINT_FILE = "checkpoint.failed.pt"  # the state a failed run stopped in, kept for debugging
CONFIG_FILE = "config.json"


def atomic_torch_save(obj: Any, path: Path) -> Path:
    """Write ``obj`` with torch.save to a temporary file in the same folder, fsync it, then rename over ``path``.

    The rename is atomic on POSIX and Windows, so a crash leaves either the old checkpoint or the new one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Delete the temporary files of atomic saves that a killed process left in ``folder``; returns them."""
    stale = [p for p in Path(folder).glob(".*.tmp") if p.is_file()] if Path(folder).is_dir() else []
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def load_checkpoint(path: Path) -> dict:
    """Load a checkpoint written by ``atomic_torch_save``, with a clear error for missing or corrupt files."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # noqa: BLE001 - re-raised with the file name
        raise RuntimeError(f"{path}: not a readable pidg checkpoint ({type(err).__name__}: {err})") from err


def random_states() -> dict:
    """Every random generator a training step may touch (the CUDA ones too, where there are)."""
    states = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def restore_random_states(states: dict) -> None:
    """Restore :func:`random_states`; CUDA states only where CUDA is (a CUDA run may resume on a CPU)."""
    torch.set_rng_state(states["torch"])
    np.random.set_state(states["numpy"])
    random.setstate(states["python"])
    if "cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["cuda"])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
