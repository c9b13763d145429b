"""Reader for HyperNeRF / Nerfies captures (the format of google/nerfies, also used by google/hypernerf).

Layout::

    dataset.json     {"count", "num_exemplars", "ids": [...], "train_ids": [...], "val_ids": [...]}
    scene.json       {"scale", "center": [3], "near", "far"}
    metadata.json    {id: {"warp_id", "appearance_id", "camera_id"[, "time_id"]}}
    camera/<id>.json one camera per item (see camera_from_nerfies_json)
    rgb/{1x,2x,4x}/<id>.png   the frames at full, half and quarter resolution
    points.npy       optional [P, 3] points in the capture's (unscaled) coordinates

Splits (``DataConfig.hypernerf_split``):

* ``"vrig"`` -- the validation-rig scenes were filmed with two phones on a rig; ``train_ids`` are the left
  camera's frames and ``val_ids`` the right camera's. Train on ``train_ids``, evaluate on ``val_ids`` (returned as
  the ``"test"`` split), exactly as HyperNeRF's ``NerfiesDataSource`` and the Gaussian-splatting follow-ups do.
* ``"interp"`` -- the interpolation scenes come from a single camera; HyperNeRF's ``InterpDataSource`` takes
  every ``interval``-th item of ``ids`` for training and, for evaluation, the frame midway between two consecutive
  training frames (index ``(a + b) // 2``), so test frames are unseen times between seen ones. The published
  configs use ``interval = 4`` (``DataConfig.hypernerf_interp_interval``); ``interval = 2`` holds out every other
  frame. (The 3DGS-family readers write this as ``ids[::4]`` / ``ids[2::4]``, the same frames except that their
  last test frame may lie after the last training frame; here, as in HyperNeRF, every test frame is bracketed.)

Time: ``metadata.json``'s ``time_id`` (``warp_id`` for older captures without it, as HyperNeRF's
``get_time_id`` falls back), normalised to [0, 1] by the minimum and maximum over all items in ``ids`` -- not only
the loaded ones, so a frame's time does not depend on the split or on ``max_frames``.

Coordinates: camera positions and points are recentred and scaled by ``scene.json`` (``(x - center) * scale``),
as HyperNeRF does; ``near``/``far`` are already in those coordinates and are reported as ``SceneData.near_far``.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pidg.data.io import (
    FrameSpec,
    as_float,
    as_matrix,
    as_vector,
    camera_or_error,
    fit_camera_to_image,
    load_frames,
    read_json,
    require,
    select_subset,
)
from pidg.data.ply import check_points
from pidg.data.scene import DataConfig, DatasetError, PointCloud, SceneData, compute_bounds
from pidg.render.camera import Camera

logger = logging.getLogger(__name__)


def is_hypernerf_dataset(root: Path) -> bool:
    return (root / "dataset.json").is_file()


def camera_from_nerfies_json(
    data: Mapping[str, Any],
    path: Path,
    scene_center: tuple[float, float, float] = (0.0, 0.0, 0.0),
    scene_scale: float = 1.0,
    image_scale: float = 1.0,
) -> Camera:
    """A Camera from one Nerfies ``camera/<id>.json``.

    Nerfies cameras are already OpenCV-like (x right, y down, z forward; pixel centres at integer + 0.5):
    ``orientation`` is the world-to-camera rotation (its rows are the camera axes in world coordinates),
    ``position`` the camera centre. So w2c = [R | -R p] with p = (position - scene_center) * scene_scale.
    Intrinsics: fx = focal_length, fy = focal_length * pixel_aspect_ratio, (cx, cy) = principal_point, for an
    image of ``image_size`` = (width, height); all divided by ``image_scale`` for the rgb/{image_scale}x folder,
    the size rounded as Nerfies' ``Camera.scale`` does.

    Ignored, because ``Camera`` is a pure pinhole: ``skew`` (0 in the published captures) and the radial and
    tangential distortion (small for phone video; the 3DGS-family methods ignore it too). Frames are not undistorted.
    """
    where = "camera"
    rot = as_matrix(require(data, "orientation", path, where), 3, 3, path, "'orientation'")
    pos = as_vector(require(data, "position", path, where), 3, path, "'position'")
    focal = as_float(require(data, "focal_length", path, where), path, "'focal_length'")
    aspect = as_float(data.get("pixel_aspect_ratio", 1.0), path, "'pixel_aspect_ratio'")
    pp = as_vector(require(data, "principal_point", path, where), 2, path, "'principal_point'")
    size = as_vector(require(data, "image_size", path, where), 2, path, "'image_size'")
    if (size <= 0).any():
        raise DatasetError(path, f"'image_size' must be positive, got {size.tolist()}")
    skew = as_float(data.get("skew", 0.0), path, "'skew'")
    if abs(skew) > 1e-6:
        logger.debug("%s: ignoring skew %g", path, skew)

    center = torch.tensor(scene_center, dtype=torch.float64)
    position = (pos - center) * scene_scale
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ position
    s = 1.0 / image_scale
    width, height = int(round(float(size[0]) * s)), int(round(float(size[1]) * s))
    return camera_or_error(
        lambda: Camera(
            w2c.to(torch.float32), focal * s, focal * aspect * s, float(pp[0]) * s, float(pp[1]) * s, width, height
        ),
        path,
        "camera",
    )


def _ids(value: Any, path: Path, key: str) -> list[str]:
    if not isinstance(value, list) or not value:
        raise DatasetError(path, f"'{key}' must be a non-empty list of item ids")
    return [str(v) for v in value]


def split_ids(
    dataset: Mapping[str, Any], path: Path, split: str, interval: int
) -> tuple[list[str], list[str], list[str]]:
    """(all ids, train ids, test ids) for the "vrig" or "interp" protocol (see the module docstring)."""
    if split == "vrig":
        train = _ids(require(dataset, "train_ids", path), path, "train_ids")
        val_ids = require(dataset, "val_ids", path)
        if val_ids == []:  # single-camera captures (the "interp" scenes) list no held-out views
            raise DatasetError(path, "'val_ids' is empty: not a validation-rig capture; use hypernerf_split='interp'")
        test = _ids(val_ids, path, "val_ids")
        all_ids = _ids(dataset["ids"], path, "ids") if "ids" in dataset else train + test
        return all_ids, train, test
    all_ids = _ids(require(dataset, "ids", path), path, "ids")
    if interval > len(all_ids) - 1:
        raise DatasetError(
            path, f"'interp' split with interval {interval} needs more than {interval} ids, got {len(all_ids)}"
        )
    train_idx = list(range(0, len(all_ids), interval))
    test_idx = [(a + b) // 2 for a, b in zip(train_idx[:-1], train_idx[1:])]
    return all_ids, [all_ids[i] for i in train_idx], [all_ids[i] for i in test_idx]


def _time_ids(metadata: Any, ids: list[str], path: Path) -> tuple[dict[str, float], str]:
    """Raw time ids per item and which key they came from."""
    if not isinstance(metadata, Mapping):
        raise DatasetError(path, "expected a JSON object mapping item ids to metadata")
    out: dict[str, float] = {}
    keys = set()
    for item in ids:
        entry = require(metadata, item, path)
        key = "time_id" if isinstance(entry, Mapping) and "time_id" in entry else "warp_id"
        out[item] = as_float(require(entry, key, path, f"item {item!r}"), path, f"item {item!r} '{key}'")
        keys.add(key)
    return out, "/".join(sorted(keys))


def read_hypernerf(config: DataConfig) -> SceneData:
    """Read a HyperNeRF / Nerfies capture (see the module docstring)."""
    root = config.root
    if config.time_source != "json":
        raise DatasetError(
            root / "metadata.json", "HyperNeRF times come from metadata.json; time_source must be 'json'"
        )
    dataset_path = root / "dataset.json"
    bad = [s for s in config.splits if s not in ("train", "test")]
    if bad:
        raise DatasetError(
            dataset_path, f"HyperNeRF data has splits 'train' and 'test' (the held-out val_ids), not {bad}"
        )

    all_ids, train_ids, test_ids = split_ids(
        read_json(dataset_path), dataset_path, config.hypernerf_split, config.hypernerf_interp_interval
    )
    scene_path = root / "scene.json"
    scene = read_json(scene_path)
    center_t = as_vector(require(scene, "center", scene_path), 3, scene_path, "'center'")
    center = (float(center_t[0]), float(center_t[1]), float(center_t[2]))
    scale = as_float(require(scene, "scale", scene_path), scene_path, "'scale'")
    near = as_float(require(scene, "near", scene_path), scene_path, "'near'")
    far = as_float(require(scene, "far", scene_path), scene_path, "'far'")
    if scale <= 0 or not 0 <= near < far:
        raise DatasetError(scene_path, f"need scale > 0 and 0 <= near < far, got scale={scale}, near={near}, far={far}")

    metadata_path = root / "metadata.json"
    raw_times, time_key = _time_ids(
        read_json(metadata_path), list(dict.fromkeys(all_ids + train_ids + test_ids)), metadata_path
    )
    tmin, tmax = min(raw_times[i] for i in all_ids), max(raw_times[i] for i in all_ids)
    if tmax <= tmin:
        raise DatasetError(metadata_path, f"all items have {time_key} {tmin}; cannot normalise time")
    time_source = f"metadata.json:{time_key}"
    logger.info("%s: frame times from %s", root.name, time_source)

    image_scale = config.hypernerf_image_scale
    rgb_dir = root / "rgb" / f"{image_scale}x"
    if not rgb_dir.is_dir():
        found = sorted(p.name for p in (root / "rgb").iterdir()) if (root / "rgb").is_dir() else []
        raise DatasetError(rgb_dir, f"image folder not found (rgb/ has {found}); set hypernerf_image_scale")

    def camera(item: str) -> Camera:
        path = root / "camera" / f"{item}.json"
        return camera_from_nerfies_json(read_json(path), path, center, scale, image_scale)

    wanted = {"train": train_ids, "test": test_ids}
    resample = config.resample_for("hypernerf")
    splits = {}
    train_cameras = {item: camera(item) for item in train_ids}  # all of them: the bounds use every training view
    for split in config.splits:
        items = [wanted[split][i] for i in select_subset(len(wanted[split]), config.max_frames)]
        specs = []
        for item in items:
            cam = train_cameras[item] if item in train_cameras else camera(item)
            image_path = rgb_dir / f"{item}.png"
            t = (raw_times[item] - tmin) / (tmax - tmin)
            if not 0.0 <= t <= 1.0:  # a test item outside the range of `ids`
                raise DatasetError(
                    metadata_path, f"item {item!r}: {time_key} {raw_times[item]} is outside the range of 'ids'"
                )
            specs.append(
                FrameSpec(item, image_path, t, lambda w, h, c=cam, p=image_path: fit_camera_to_image(c, w, h, p))
            )
        splits[split] = load_frames(specs, config, desc=f"{root.name}/{split}", resample=resample)

    points = _read_points(root / "points.npy", center, scale)
    centers = torch.stack([c.camera_center for c in train_cameras.values()])
    return SceneData(
        root=root,
        kind="hypernerf",
        splits=splits,
        background=torch.tensor(config.background_rgb, dtype=torch.float32),
        bounds=compute_bounds(centers, points),
        time_source=time_source,
        points3d=points,
        near_far=(near, far),
        info={
            "split": config.hypernerf_split,
            "image_scale": image_scale,
            "interp_interval": config.hypernerf_interp_interval if config.hypernerf_split == "interp" else None,
        },
    )


def _read_points(path: Path, center: tuple[float, float, float], scale: float) -> PointCloud | None:
    if not path.is_file():
        return None
    try:
        xyz = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:  # EOFError: an empty file
        raise DatasetError(path, f"cannot read points: {e}") from None
    if not isinstance(xyz, np.ndarray):  # an .npz archive under the .npy name
        xyz.close()
        raise DatasetError(path, "cannot read points: expected one .npy array, found an .npz archive")
    real = np.issubdtype(xyz.dtype, np.floating) or np.issubdtype(xyz.dtype, np.integer)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not real:
        raise DatasetError(path, f"expected a [P, 3] array of real numbers, got {xyz.dtype} {xyz.shape}")
    check_points(path, xyz)  # in the file's own coordinates, the ones a reader of the message can look up
    xyz = (xyz.astype(np.float64) - np.asarray(center)) * scale
    return PointCloud(torch.from_numpy(xyz.astype(np.float32)))
