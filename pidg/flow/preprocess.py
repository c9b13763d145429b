"""Forward and backward optical flow between consecutive training frames, cached on disk next to the dataset.

Cache layout (format 1), one folder per estimator and resolution::

    <dataset>/<FlowConfig.cache_dir>/<estimator>_<W>x<H>/
        index.json                          what is there, in pair order (see below)
        <frame0>__<frame1>.npz              one file per consecutive pair of training frames

Frame names have every character outside ``[A-Za-z0-9._-]`` replaced by ``_`` (``train/0002`` ->
``train_0002``). Each ``.npz`` holds

* ``forward`` [H, W, 2] float32: flow t -> t+1 in pixels, on frame t's pixel grid (dx, dy);
* ``backward`` [H, W, 2] float32: flow t+1 -> t on frame t+1's grid;
* ``valid_forward`` / ``valid_backward`` [H, W] bool: the forward-backward consistency masks
  (:func:`pidg.flow.optical_flow.forward_backward_consistency`), False where occluded or mismatched;
* ``hash``: the pair's key, sha1 of both images' sha1 (pixels and size) and of the estimator settings
  (name, parameters, OpenCV version, consistency thresholds, format version).

The masks and the hash are deflated; the float32 flows are stored uncompressed (they hardly compress, see
:func:`_write_npz`). ``np.load`` reads the files as usual.

``index.json`` holds ``format``, ``estimator``, ``settings``, ``width``, ``height``, ``dataset`` and ``pairs``: a list
in time order of ``{"file", "frame0", "frame1", "time0", "time1", "image_sha1_0", "image_sha1_1", "hash"}``.

Re-running is incremental: a pair whose file holds the same ``hash`` is read back, any other is recomputed and
written atomically (a temporary file, then ``os.replace``), so an interrupted run never leaves a half-written pair.
``.npz`` files no pair refers to any more are deleted.

In memory (:class:`FlowCache`) flows are kept as float16 [K, H, W, 2] (half the memory; the rounding error,
< 0.05 px below 100 px of motion, is far below an estimator's error) and converted to float32 on access.
"""
from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import re
import tempfile
import time
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from pidg.data import load_scene
from pidg.data.scene import DataConfig, DatasetError, Frame, SceneData
from pidg.flow.config import FlowConfig
from pidg.flow.optical_flow import (
    FlowEstimator,
    forward_backward_consistency,
    make_estimator,
)

logger = logging.getLogger(__name__)

CACHE_FORMAT = 1
INDEX_FILE = "index.json"
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]")


@dataclass(eq=False)
class FlowPair:
    """Optical flow between training frames k (time t) and k + 1 (time t+1): ``forward`` and ``backward`` float32
    [H, W, 2] (px), read from the stored flows (the cache's float16) on first use, since a training step whose flow
    target is cached needs the pair's frames only (two conversions were 1.2 ms of such a step); bool masks. A
    :meth:`reversed` pair runs from frame k + 1 back to frame k."""

    index: int
    frame0: Frame
    frame1: Frame
    stored_forward: Tensor  # [H, W, 2] t -> t+1 on frame0's pixels, any float dtype
    stored_backward: Tensor  # [H, W, 2] t+1 -> t on frame1's pixels, any float dtype
    valid_forward: Tensor  # [H, W] bool
    valid_backward: Tensor  # [H, W] bool

    @functools.cached_property
    def forward(self) -> Tensor:
        """[H, W, 2] float32 flow t -> t+1 on frame0's pixels."""
        return self.stored_forward.float()

    @functools.cached_property
    def backward(self) -> Tensor:
        """[H, W, 2] float32 flow t+1 -> t on frame1's pixels."""
        return self.stored_backward.float()

    @property
    def dt(self) -> float:
        """Time step t+1 - t in the scene's normalised time (what velocities are integrated over; < 0 for a
        :meth:`reversed` pair)."""
        return self.frame1.time - self.frame0.time

    def moving_coverage(self) -> float | None:
        """Share of frame t's moving pixels (its motion mask) on which the forward flow passed the forward-backward
        check (``valid_forward``); None when the frame has no mask or nothing in it moves. What
        ``FlowConfig.min_pair_coverage`` and ``FlowConfig.weigh_by_coverage`` judge a pair by."""
        mask = self.frame0.mask
        if mask is None:
            return None
        moving = mask.to(self.valid_forward.device)
        count = int(moving.sum())
        return int((self.valid_forward & moving).sum()) / count if count else None

    def reversed(self) -> "FlowPair":
        """The same pair run backwards in time: frame t+1 first, its backward flow as the pair's forward one (on
        frame t+1's pixels), so every consumer of a pair reads it unchanged and integrates over dt < 0."""
        return FlowPair(
            self.index, self.frame1, self.frame0, self.stored_backward, self.stored_forward, self.valid_backward,
            self.valid_forward,
        )


class FlowCache:
    """Flows of all consecutive training-frame pairs, loaded once into memory (float16 flows, bool masks)."""

    def __init__(
        self, directory: Path, frames: list[Frame], forward: Tensor, backward: Tensor, valid_forward: Tensor,
        valid_backward: Tensor, computed: int = 0, reused: int = 0,
    ) -> None:
        self.directory = directory
        self.frames = frames  # training frames sorted by time; pair k is (frames[k], frames[k + 1])
        self.forward, self.backward = forward, backward
        self.valid_forward, self.valid_backward = valid_forward, valid_backward
        self.computed, self.reused = computed, reused
        self._position_of_id = {id(f): k for k, f in enumerate(frames)}
        self._position_of_name = {f.name: k for k, f in enumerate(frames)}

    def __len__(self) -> int:
        return max(0, len(self.frames) - 1)

    def pair(self, k: int) -> FlowPair:
        if not 0 <= k < len(self):
            raise IndexError(f"flow pair {k} out of range (0..{len(self) - 1})")
        return FlowPair(
            k, self.frames[k], self.frames[k + 1], self.forward[k], self.backward[k],
            self.valid_forward[k], self.valid_backward[k],
        )

    def _position(self, frame: Frame) -> int | None:
        """``frame``'s place in :attr:`frames` (matched by identity, else by name); None if it is not there."""
        return self._position_of_id.get(id(frame), self._position_of_name.get(frame.name))

    def pair_starting_at(self, frame: Frame) -> FlowPair | None:
        """The pair whose first frame is ``frame``; None for the last frame."""
        k = self._position(frame)
        return None if k is None or k >= len(self) else self.pair(k)

    def pair_back_from(self, frame: Frame) -> FlowPair | None:
        """The pair that ends at ``frame``, reversed (:meth:`FlowPair.reversed`: from ``frame`` back to the training
        frame before it); None for the first frame."""
        k = self._position(frame)
        return None if k is None or k == 0 else self.pair(k - 1).reversed()

    def to(self, device: torch.device | str, frames: list[Frame] | None = None) -> "FlowCache":
        """The cache with its flows on ``device`` and, given ``frames`` (the same scene's frames moved there, as
        ``SceneData.to`` makes them), pairs made of those frames (matched by name)."""
        if frames is not None:
            by_name = {f.name: f for f in frames}
            missing = [f.name for f in self.frames if f.name not in by_name]
            if missing:
                raise ValueError(f"FlowCache.to: frames {missing[:3]} of the cache are not among the given frames")
            frames = [by_name[f.name] for f in self.frames]
        return FlowCache(
            self.directory, frames if frames is not None else self.frames, self.forward.to(device), self.backward.to(device),
            self.valid_forward.to(device), self.valid_backward.to(device), self.computed, self.reused,
        )

    def memory_bytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.forward, self.backward, self.valid_forward, self.valid_backward))


# ---------------------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------------------
def sorted_training_frames(scene: SceneData) -> list[Frame]:
    """Training frames in time order (ties keep file order): consecutive entries are the flow pairs."""
    return sorted(scene.train, key=lambda f: f.time)


def safe_name(name: str) -> str:
    return _UNSAFE.sub("_", name) or "frame"


def pair_file_name(frame0: Frame, frame1: Frame) -> str:
    return f"{safe_name(frame0.name)}__{safe_name(frame1.name)}.npz"


def image_sha1(frame: Frame) -> str:
    array = np.ascontiguousarray(frame.image_u8.numpy())
    digest = hashlib.sha1(f"{array.shape}".encode())
    digest.update(array.tobytes())
    return digest.hexdigest()


def cache_directory(scene: SceneData, config: FlowConfig, width: int, height: int, cache_root: Path | None) -> Path:
    """``cache_root`` (default: ``<dataset>/<config.cache_dir>``) / ``<estimator>_<W>x<H>``."""
    if cache_root is None:
        if not Path(scene.root).is_dir():
            raise ValueError(
                f"scene {scene.name!r} has no dataset folder ({scene.root}) to cache flows next to; pass cache_root"
            )
        cache_root = Path(scene.root) / config.cache_dir
    return Path(cache_root) / f"{config.estimator}_{width}x{height}"


def _check_sizes(frames: list[Frame]) -> tuple[int, int]:
    """(W, H) shared by every frame and its camera; DatasetError naming the first frame that differs."""
    w, h = frames[0].width, frames[0].height
    for f in frames:
        where = f.path or f.name
        if (f.width, f.height) != (w, h):
            raise DatasetError(
                where, f"frame {f.name!r} is {f.width}x{f.height} but training frame {frames[0].name!r} is {w}x{h}; "
                "optical flow needs all training frames at one size (check DataConfig.downscale)"
            )
        if (f.camera.width, f.camera.height) != (w, h):
            raise DatasetError(
                where, f"frame {f.name!r}: image is {w}x{h} but its camera renders {f.camera.width}x{f.camera.height}"
            )
    return w, h


def _write_npz(fh: BinaryIO, arrays: dict[str, np.ndarray]) -> None:
    """An ``.npz`` (zip of ``.npy``) that deflates only what compresses: masks and strings, not float flows.

    Why: float32 flow noise barely compresses (zlib: -18 % size at 480x270) but deflating it took ~50x longer
    than the flow estimation itself; ``np.load`` reads the mixed archive like any ``.npz``.
    """
    with zipfile.ZipFile(fh, "w") as archive:
        for name, array in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy")
            info.compress_type = zipfile.ZIP_STORED if array.dtype.kind == "f" else zipfile.ZIP_DEFLATED
            with archive.open(info, "w", force_zip64=True) as entry:
                np.lib.format.write_array(entry, array, allow_pickle=False)


def _write_npz_atomic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            _write_npz(fh, arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _write_json_atomic(path: Path, data: Any) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(data, fh, indent=1)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


_ARRAYS = ("forward", "backward", "valid_forward", "valid_backward")


def _read_pair(path: Path, key: str, width: int, height: int) -> dict[str, np.ndarray] | None:
    """The pair's arrays if ``path`` holds them for ``key`` at this size, else None (to recompute)."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as data:
            if str(data["hash"]) != key:
                return None
            arrays = {name: data[name] for name in _ARRAYS}
    except (OSError, ValueError, KeyError, EOFError) as err:  # unreadable or foreign file: recompute it
        logger.warning("flow cache: cannot read %s (%s); recomputing", path, err)
        return None
    shapes_ok = all(arrays[n].shape == (height, width, 2) for n in _ARRAYS[:2]) and all(
        arrays[n].shape == (height, width) for n in _ARRAYS[2:]
    )
    return arrays if shapes_ok else None


def _compute_pair(
    estimator: FlowEstimator, image0: np.ndarray, image1: np.ndarray, config: FlowConfig
) -> dict[str, np.ndarray]:
    forward = estimator(image0, image1)
    backward = estimator(image1, image0)
    f, b = torch.from_numpy(forward), torch.from_numpy(backward)
    a, beta = config.consistency_alpha, config.consistency_beta
    return {
        "forward": forward,
        "backward": backward,
        "valid_forward": forward_backward_consistency(f, b, a, beta).numpy(),
        "valid_backward": forward_backward_consistency(b, f, a, beta).numpy(),
    }


# ---------------------------------------------------------------------------------------------------------------
# entry points
# ---------------------------------------------------------------------------------------------------------------
def preprocess_flow(
    scene: SceneData, config: FlowConfig, cache_root: Path | None = None, progress: bool = True
) -> FlowCache:
    """Compute (or reuse) the flows of every consecutive pair of training frames and load them into memory.

    Flows are computed on the frames as loaded, i.e. composited on the scene background and at the training
    resolution the DataConfig asked for. See the module docstring for the cache layout.
    """
    frames = sorted_training_frames(scene)
    if len(frames) < 2:
        raise ValueError(f"optical flow needs at least two training frames, {scene.name!r} has {len(frames)}")
    width, height = _check_sizes(frames)
    directory = cache_directory(scene, config, width, height, cache_root)
    directory.mkdir(parents=True, exist_ok=True)
    estimator = make_estimator(config)
    settings = {
        "estimator": estimator.name, **estimator.settings, "consistency_alpha": config.consistency_alpha,
        "consistency_beta": config.consistency_beta, "format": CACHE_FORMAT,
    }
    settings_sha1 = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()
    image_hashes = [image_sha1(f) for f in frames]

    k_pairs = len(frames) - 1
    forward = torch.empty(k_pairs, height, width, 2, dtype=torch.float16)
    backward = torch.empty_like(forward)
    valid_forward = torch.empty(k_pairs, height, width, dtype=torch.bool)
    valid_backward = torch.empty_like(valid_forward)
    entries, computed = [], 0
    bar = tqdm(range(k_pairs), desc=f"optical flow ({estimator.name})", unit="pair", disable=not progress, leave=False)
    for k in bar:
        f0, f1 = frames[k], frames[k + 1]
        name = pair_file_name(f0, f1)
        key = hashlib.sha1(f"{image_hashes[k]}:{image_hashes[k + 1]}:{settings_sha1}".encode()).hexdigest()
        arrays = _read_pair(directory / name, key, width, height)
        if arrays is None:
            arrays = _compute_pair(estimator, f0.image_u8.numpy(), f1.image_u8.numpy(), config)
            _write_npz_atomic(directory / name, {**arrays, "hash": np.array(key)})
            computed += 1
        forward[k] = torch.from_numpy(arrays["forward"])
        backward[k] = torch.from_numpy(arrays["backward"])
        valid_forward[k] = torch.from_numpy(arrays["valid_forward"])
        valid_backward[k] = torch.from_numpy(arrays["valid_backward"])
        entries.append({
            "file": name, "frame0": f0.name, "frame1": f1.name, "time0": f0.time, "time1": f1.time,
            "image_sha1_0": image_hashes[k], "image_sha1_1": image_hashes[k + 1], "hash": key,
        })
    bar.close()

    referenced = {e["file"] for e in entries}
    for stale in directory.glob("*.npz"):
        if stale.name not in referenced:
            stale.unlink()
    index = {
        "format": CACHE_FORMAT, "estimator": estimator.name, "settings": settings, "width": width, "height": height,
        "dataset": str(scene.root), "pairs": entries,
    }
    _write_json_atomic(directory / INDEX_FILE, index)
    logger.info("optical flow: %d pairs in %s (%d computed, %d reused)", k_pairs, directory, computed, k_pairs - computed)
    return FlowCache(directory, frames, forward, backward, valid_forward, valid_backward, computed, k_pairs - computed)


def flow_summary(cache: FlowCache) -> dict[str, Any]:
    """Facts about a loaded cache for logs and the CLI."""
    mag = cache.forward.float().norm(dim=-1)
    return {
        "cache_dir": str(cache.directory),
        "pairs": len(cache),
        "computed": cache.computed,
        "reused": cache.reused,
        "width": int(cache.forward.shape[2]),
        "height": int(cache.forward.shape[1]),
        "valid_forward_fraction": float(cache.valid_forward.float().mean()),
        "valid_backward_fraction": float(cache.valid_backward.float().mean()),
        "median_forward_px": float(mag.median()),
        "p99_forward_px": float(torch.quantile(mag.flatten()[:: max(1, mag.numel() // 1_000_000)], 0.99)),
        "memory_mb": cache.memory_bytes() / 2**20,
    }


def median_view_change(frames: list[Frame]) -> float:
    """Median angle in degrees between the viewing directions of consecutive ``frames`` (0 for fewer than two): for
    the training frames in time order (:func:`sorted_training_frames`), how far the camera turns within a flow pair."""
    if len(frames) < 2:
        return 0.0
    directions = torch.stack([f.camera.viewing_direction.double().cpu() for f in frames])
    cosines = (directions[1:] * directions[:-1]).sum(dim=-1).clamp(-1.0, 1.0)
    return float(torch.rad2deg(torch.acos(cosines)).median())


def check_flow_viewpoints(scene: SceneData, config: FlowConfig) -> None:
    """Refuse the flow loss on data whose consecutive training views jump (``FlowConfig.max_view_change``)."""
    change = median_view_change(sorted_training_frames(scene))
    if change > config.max_view_change:
        raise ValueError(
            f"--flow lpfm: {scene.root}'s consecutive training views turn by {change:.0f} degrees at the median (more "
            f"than --flow.max_view_change {config.max_view_change:g}): their optical flow is not the scene's motion "
            "(D-NeRF-style captures jump between viewpoints; the paper trains them without LPFM): use --flow none"
        )


def open_flow_cache(scene: SceneData, config: FlowConfig, fallback_dir: Path, progress: bool = True) -> FlowCache:
    """The scene's flow cache, computed where missing: next to the dataset, or in ``fallback_dir`` (e.g. the run
    folder) when the dataset folder is missing or read-only. Flows are estimated from the images on the CPU; the
    cache comes back on the scene's device, its pairs made of the scene's own frames."""
    root = Path(scene.root)
    cache_root = None
    if not (root.is_dir() and os.access(root, os.W_OK)):
        cache_root = Path(fallback_dir)
        logger.info("dataset folder %s is not writable: caching optical flow in %s", root, cache_root)
    cache = preprocess_flow(scene.to("cpu"), config, cache_root, progress=progress)
    device = scene.background.device
    return cache if device.type == "cpu" else cache.to(device, scene.train)


def run_preprocess(data_config: DataConfig, flow_config: FlowConfig, cache_root: Path | None = None) -> dict[str, Any]:
    """Load the training split of a dataset, compute its flow cache, and return a summary dict (for the CLI)."""
    start = time.perf_counter()
    scene = load_scene(replace(data_config, splits=("train",)))
    loaded = time.perf_counter()
    cache = preprocess_flow(scene, flow_config, cache_root, progress=data_config.progress)
    done = time.perf_counter()
    return {
        "dataset": str(scene.root),
        "estimator": flow_config.estimator,
        **flow_summary(cache),
        "seconds_load": round(loaded - start, 3),
        "seconds_flow": round(done - loaded, 3),
    }
