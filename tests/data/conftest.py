"""Builders of tiny synthetic datasets (a few pixels, a few frames) for the reader tests."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

import pidg  # noqa: F401  (before torch)

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def look_at_c2w_gl(position: tuple[float, float, float], target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL/Blender camera-to-world matrix (x right, y up, looking along -z) looking at ``target``."""
    p, t, u = (np.asarray(v, np.float64) for v in (position, target, up))
    forward = (t - p) / np.linalg.norm(t - p)
    right = np.cross(forward, u)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, cam_up, -forward, p
    return c2w


def rgba_pattern(width: int, height: int, seed: int) -> np.ndarray:
    """An RGBA frame: a per-frame colour, alpha 255 on the left half, 0 on the right, 128 in the last column."""
    rgba = np.zeros((height, width, 4), np.uint8)
    rgba[..., :3] = np.array([200, 100, 50], np.uint8) + seed
    rgba[:, : width // 2, 3] = 255
    rgba[:, -1, 3] = 128
    return rgba


def write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2))


def edit_json(path: Path, edit: Callable[[Any], Any]) -> None:
    """Apply ``edit`` to the parsed file in place (its return value is ignored) and write it back."""
    data = json.loads(path.read_text())
    edit(data)
    write_json(path, data)


def make_blender(
    root: Path,
    n_train: int = 3,
    n_test: int = 2,
    width: int = 8,
    height: int = 6,
    fov_x: float = 0.9,
    masks: bool = False,
    points: bool = False,
    ext_in_json: bool = False,
) -> Path:
    """A PIDG/BlenderNeRF-style scene: frames 'frames/0001'..., train and test interleaved in time (train takes
    the odd file numbers, test the even ones), json times normalised per split like the Dry Ice quirk."""
    root.mkdir(parents=True, exist_ok=True)
    numbers = {"train": [1 + 2 * i for i in range(n_train)], "test": [2 + 2 * i for i in range(n_test)]}
    for split, ks in numbers.items():
        frames = []
        for i, k in enumerate(ks):
            name = f"frames/{k:04d}"
            (root / "frames").mkdir(exist_ok=True)
            Image.fromarray(rgba_pattern(width, height, k)).save(root / f"{name}.png")
            if masks:
                (root / "mask").mkdir(exist_ok=True)
                m = np.zeros((height, width), np.uint8)
                m[: height // 2] = 255
                Image.fromarray(m).save(root / "mask" / f"{k:04d}.png")
            angle = 0.3 * k
            c2w = look_at_c2w_gl((4 * math.cos(angle), 4 * math.sin(angle), 1.0))
            frames.append(
                {
                    "file_path": name + (".png" if ext_in_json else ""),
                    "time": i / max(1, len(ks) - 1),
                    "transform_matrix": c2w.tolist(),
                }
            )
        write_json(root / f"transforms_{split}.json", {"camera_angle_x": fov_x, "frames": frames})
    if points:
        from pidg.data.ply import write_ply_points

        rng = np.random.default_rng(0)
        write_ply_points(root / "points3d.ply", rng.uniform(-1, 1, (50, 3)), rng.uniform(0, 1, (50, 3)))
    return root


def nerfies_camera(
    position, target=(0.0, 0.0, 0.0), image_size=(16, 12), focal=20.0, principal_point=(7.0, 5.5), aspect=1.0
) -> dict:
    """A Nerfies camera json (OpenCV-like: orientation rows = camera x right, y down, z forward in world)."""
    p, t = np.asarray(position, float), np.asarray(target, float)
    z = (t - p) / np.linalg.norm(t - p)
    x = np.cross(z, [0.0, 0.0, -1.0])  # camera y (down) points along world -z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return {
        "orientation": np.stack([x, y, z]).tolist(),
        "position": p.tolist(),
        "focal_length": focal,
        "principal_point": list(principal_point),
        "skew": 0.0,
        "pixel_aspect_ratio": aspect,
        "radial_distortion": [0.01, 0.0, 0.0],
        "tangential_distortion": [0.0, 0.0],
        "image_size": list(image_size),
    }


def make_hypernerf(
    root: Path,
    n: int = 5,
    vrig: bool = True,
    scales=(1, 2),
    image_size=(16, 12),
    center=(0.5, -0.5, 0.25),
    scale=0.5,
    points: bool = True,
) -> Path:
    """A Nerfies capture with n time steps. vrig: ids left_i (train) and right_i (val), both at time i;
    otherwise ids 000000.. of a single camera."""
    if vrig:
        train_ids = [f"left_{i:06d}" for i in range(n)]
        val_ids = [f"right_{i:06d}" for i in range(n)]
        ids = train_ids + val_ids
    else:
        ids = [f"{i:06d}" for i in range(n)]
        train_ids, val_ids = ids, []
    write_json(
        root / "dataset.json",
        {"count": len(ids), "num_exemplars": len(train_ids), "ids": ids, "train_ids": train_ids, "val_ids": val_ids},
    )
    write_json(root / "scene.json", {"scale": scale, "center": list(center), "near": 0.1, "far": 5.0})
    meta = {}
    for item in ids:
        i = int(item.split("_")[-1])
        meta[item] = {"warp_id": i, "appearance_id": i, "camera_id": int(item.startswith("right"))}
    write_json(root / "metadata.json", meta)
    w, h = image_size
    for item in ids:
        i = int(item.split("_")[-1])
        side = 0.4 if item.startswith("right") else 0.0
        write_json(root / "camera" / f"{item}.json", nerfies_camera((3.0 + side, 0.3 * i, 1.0), image_size=image_size))
        for s in scales:
            (root / "rgb" / f"{s}x").mkdir(parents=True, exist_ok=True)
            rgb = np.full((h // s, w // s, 3), (10 * i, 20, 30), np.uint8)
            Image.fromarray(rgb).save(root / "rgb" / f"{s}x" / f"{item}.png")
    if points:
        np.save(root / "points.npy", np.array([[0.5, -0.5, 0.25], [1.5, -0.5, 0.25]]))
    return root


class Synth:
    """The builders above, handed to tests through the ``synth`` fixture (robust to pytest's import mode)."""

    make_blender = staticmethod(make_blender)
    make_hypernerf = staticmethod(make_hypernerf)
    nerfies_camera = staticmethod(nerfies_camera)
    look_at_c2w_gl = staticmethod(look_at_c2w_gl)
    rgba_pattern = staticmethod(rgba_pattern)
    write_json = staticmethod(write_json)
    edit_json = staticmethod(edit_json)
    shared_data = SHARED_DATA


@pytest.fixture
def synth() -> type[Synth]:
    return Synth
