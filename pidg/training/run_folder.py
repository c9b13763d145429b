"""A run folder's life: claiming one for a new run, and what a resumed run may change.

A new run never writes into a folder that holds another run unless told to (``--overwrite``), and checks that it
can write there before any training, so that no work is lost at the first checkpoint. A resumed run starts from
the saved config; options given with ``--resume`` that change the data or the model are refused with the
differences listed (the checkpoint was trained on them), and the others (a longer schedule, other learning rates,
another device) apply and are recorded in ``config.json``. A run records its dataset by an absolute path, so that
whatever reads the run later finds the data from any working folder.
"""
from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path
from typing import Any

from pidg.checkpoint import CHECKPOINT_FILE, CONFIG_FILE, FAILED_CHECKPOINT_FILE
from pidg.config_tools import apply_overrides, config_differences
from pidg.training.config import TrainConfig

RUN_FILES = (CHECKPOINT_FILE, FAILED_CHECKPOINT_FILE, CONFIG_FILE, "train_summary.json")
RUN_FOLDERS = ("tensorboard", "eval_*", "render_*")  # not flow_cache: a cache keyed by content, safe to reuse
#: options a resumed run cannot change: what the checkpoint was trained on and the shape of its model
FROZEN_SECTIONS = ("data.", "gaussians.", "deformation.", "material.")
CHANGEABLE = ("data.progress", "data.num_workers", "gaussians.sh_degree_interval")
FROZEN_FIELDS = ("physics.time_scale",)  # the unit of the model's velocities


class RunFolderInUse(FileExistsError):
    """The folder holds another run; the message says how to go on."""


def run_contents(folder: Path) -> list[Path]:
    """The files and folders of a pidg run in ``folder``."""
    folder = Path(folder)
    found = [folder / name for name in RUN_FILES if (folder / name).exists()]
    return found + sorted(p for pattern in RUN_FOLDERS for p in folder.glob(pattern) if p.is_dir())


def claim_run_folder(folder: Path, overwrite: bool = False) -> Path:
    """Make ``folder`` ready for a new run: refuse one holding a run unless ``overwrite`` (which deletes that run),
    create it, and check now that it can be written."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"{folder}: the run folder (--output.dir) is a file")
    existing = run_contents(folder)
    if existing and not overwrite:
        raise RunFolderInUse(
            f"{folder}: already holds a run ({', '.join(p.name for p in existing)}); continue it with --resume, replace "
            "it with --overwrite, or choose another --output.dir"
        )
    for path in existing:
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / ".pidg-write-check"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise PermissionError(f"{folder}: cannot write the run folder ({err.strerror or err})") from None
    return folder


def _frozen(name: str) -> bool:
    return name in FROZEN_FIELDS or (name.startswith(FROZEN_SECTIONS) and name not in CHANGEABLE)


def resume_config(saved: TrainConfig, overrides: dict[str, str]) -> tuple[TrainConfig, list[tuple[str, Any, Any]]]:
    """The config a resumed run continues with: the saved one with ``overrides`` applied, and the changes it makes.

    Raises ValueError listing every change of the data or the model (see the module docstring)."""
    new = apply_overrides(saved, overrides)
    if Path(str(new.data.path)).resolve() == Path(str(saved.data.path)).resolve():
        new = replace(new, data=replace(new.data, path=saved.data.path))  # the same folder, named from here
    changes = config_differences(saved, new)
    refused = [f"{name} {old} -> {value}" for name, old, value in changes if _frozen(name)]
    if new.needs_material_field and not saved.needs_material_field:
        refused.append("a material field (physics or flow on): the run was trained without one")
    if new.optim.lambda_tracks > 0 and saved.optim.lambda_tracks == 0:
        refused.append("a tracks term (optim.lambda_tracks): the run kept no tracks to hold")
    if refused:
        raise ValueError(
            "--resume cannot change the data or the model the checkpoint was trained on: " + "; ".join(refused)
            + " (start a new run with another --output.dir for these)"
        )
    return new, changes


def with_absolute_data_path(config: TrainConfig) -> TrainConfig:
    """``config`` with its dataset named by an absolute path, as a run records it in config.json: eval, render, the
    viewer and ``--resume`` then find the data from any working folder (a relative path named it from the folder
    the training started in). An empty path (a scene built in memory) stays as it is."""
    path = str(config.data.path)
    if not path or Path(path).is_absolute():
        return config
    return replace(config, data=replace(config.data, path=str(Path(path).resolve())))
