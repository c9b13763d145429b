"""Dataset readers: a dataset folder in, a :class:`SceneData` (cameras, times, images, masks, points) out.

``load_scene(DataConfig(path=...))`` recognises the format from the folder's contents:

* ``transforms_train.json`` (or any ``transforms_{train,val,test}.json``): D-NeRF / BlenderNeRF / PIDG scenes,
  read by :mod:`pidg.data.blender`;
* ``dataset.json``: HyperNeRF / Nerfies captures, read by :mod:`pidg.data.hypernerf`.
"""

from __future__ import annotations

from pathlib import Path

from pidg.data.blender import blender_layout, is_blender_dataset, read_blender
from pidg.data.hypernerf import camera_from_nerfies_json, is_hypernerf_dataset, read_hypernerf
from pidg.data.ply import read_ply_points, write_ply_points
from pidg.data.scene import (
    DataConfig,
    DatasetError,
    Frame,
    PointCloud,
    SceneBounds,
    SceneData,
    compute_bounds,
    parse_downscale,
)

__all__ = [
    "DataConfig",
    "DatasetError",
    "Frame",
    "PointCloud",
    "SceneBounds",
    "SceneData",
    "camera_from_nerfies_json",
    "compute_bounds",
    "dataset_layout",
    "detect_format",
    "load_scene",
    "parse_downscale",
    "read_blender",
    "read_hypernerf",
    "read_ply_points",
    "write_ply_points",
]


def detect_format(root: Path | str) -> str:
    """ "blender" or "hypernerf", from the files in ``root``; DatasetError if it is neither."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(root, "dataset folder not found")
    if is_blender_dataset(root):
        return "blender"
    if is_hypernerf_dataset(root):
        return "hypernerf"
    raise DatasetError(
        root,
        "not a known dataset: expected transforms_train.json (D-NeRF / BlenderNeRF / PIDG) "
        "or dataset.json (HyperNeRF / Nerfies)",
    )


def dataset_layout(root: Path | str) -> str:
    """What kind of scene a folder holds: "dnerf" (synthetic, 360-degree views), "pidg" (PIDG / BlenderNeRF
    physics scenes with masks or a point cloud, monocular orbit) or "hypernerf" (real captures)."""
    return "hypernerf" if detect_format(root) == "hypernerf" else blender_layout(Path(root))


def load_scene(config: DataConfig) -> SceneData:
    """Load the dataset at ``config.path`` with the reader its contents call for."""
    reader = {"blender": read_blender, "hypernerf": read_hypernerf}[detect_format(config.root)]
    scene = reader(config)
    return scene if config.train_until is None else scene.split_in_time(config.train_until)
