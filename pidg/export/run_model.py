"""Opening a trained run for tools that only need its scene model (the exporter, the viewer), with one-line errors.

A run folder is what ``pidg train`` (or ``pidg demo``) wrote: ``RUN/checkpoint.pt`` holds the scene model, and
``RUN/config.json`` says which dataset it was trained on (only the viewer uses that, for the training cameras).
Times are dataset times: 0 is the first frame of the video, 1 the last.
"""
from __future__ import annotations

import math
from pathlib import Path

from pidg.checkpoint import CHECKPOINT_FILE
from pidg.device import Device, rasterizer_for, resolve_device
from pidg.models.dynamic_gaussians import DynamicGaussians


def check_run_folder(run_dir: Path | str) -> Path:
    """``run_dir`` as a Path when it holds a pidg run (a checkpoint), else a FileNotFoundError naming the problem."""
    run_dir = Path(run_dir)
    if not run_dir.exists():
        raise FileNotFoundError(f"{run_dir}: no such folder (give the run folder that pidg train or pidg demo wrote)")
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: not a folder (give the run folder that pidg train or pidg demo wrote, not a file in it)")
    if not (run_dir / CHECKPOINT_FILE).is_file():
        raise FileNotFoundError(
            f"{run_dir}: not a pidg run folder (no {CHECKPOINT_FILE} in it; give the folder that pidg train or pidg demo "
            "wrote, e.g. outputs/demo/run)"
        )
    return run_dir


def open_run_model(run_dir: Path | str, device: Device | str = "auto") -> DynamicGaussians:
    """The scene model of a run on ``device`` (auto: CUDA when there is one), rendering with the rasterizer that
    device has (the numba kernel on a CPU, gsplat on CUDA; an error naming the fix when it is missing)."""
    run_dir = check_run_folder(run_dir)
    where = resolve_device(device)
    rasterizer_for("auto", where)  # gsplat missing on CUDA: say so before loading anything
    model = DynamicGaussians.from_run(run_dir, where)
    model.backend = "auto"
    return model


def check_time(t: float, what: str = "--time") -> float:
    """``t`` as a float when it is a dataset time in [0, 1], else a ValueError naming ``what`` and the range."""
    t = float(t)
    if not (math.isfinite(t) and 0.0 <= t <= 1.0):
        raise ValueError(f"{what} {t:g}: outside [0, 1] (dataset time: 0 is the first frame of the video, 1 the last)")
    return t
