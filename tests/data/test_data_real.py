"""The readers on the real development data in ../shared/data (skipped when it is not there).

Only a few frames, downscaled, so the whole file stays fast.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

import pidg  # noqa: F401
from pidg.data import DataConfig, load_scene

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
DNERF = DATA / "dnerf"
DRY_ICE = DATA / "pidg" / "dry_ice"

needs_dnerf = pytest.mark.skipif(not (DNERF / "lego" / "transforms_train.json").is_file(), reason="no D-NeRF data")
needs_dry_ice = pytest.mark.skipif(not (DRY_ICE / "transforms_train.json").is_file(), reason="no Dry Ice data")


@needs_dnerf
@pytest.mark.parametrize("name", ["lego", "bouncingballs"])
def test_dnerf_downscaled_subset(name):
    if not (DNERF / name / "transforms_train.json").is_file():
        pytest.skip(f"no D-NeRF {name}")
    scene = load_scene(
        DataConfig(
            DNERF / name,
            downscale=(100, 100),
            max_frames=3,
            splits=("train", "val", "test"),
            background="white",
            progress=False,
        )
    )
    assert set(scene.splits) == {"train", "val", "test"} and scene.time_source == "json"
    for split, frames in scene.splits.items():
        assert len(frames) == 3
        assert [f.time for f in frames][0] == 0.0 and frames[-1].time == 1.0  # first and last frame kept
        for f in frames:
            assert f.image_u8.shape == (100, 100, 3) and f.mask is None
            assert (f.camera.width, f.camera.height) == (100, 100)
            assert f.camera.fov_x == pytest.approx(
                json.loads((DNERF / name / f"transforms_{split}.json").read_text())["camera_angle_x"]
            )
            # The corners are transparent in D-NeRF renders, so they show the white background.
            assert f.image[0, 0].tolist() == [1.0, 1.0, 1.0]
    assert scene.points3d is None and scene.info["layout"] == "dnerf"
    assert 3.0 < scene.bounds.radius < 6.0  # cameras on a sphere of radius ~4 around the object


@needs_dnerf
def test_dnerf_camera_convention():
    """Camera centre = json translation; a point ahead of the camera (GL -z) projects to the image centre."""
    root = DNERF / "lego"
    scene = load_scene(DataConfig(root, downscale=(100, 100), max_frames=2, splits=("train",), progress=False))
    frames = json.loads((root / "transforms_train.json").read_text())["frames"]
    for loaded, raw in zip(scene.train, (frames[0], frames[-1])):
        c2w = torch.tensor(raw["transform_matrix"], dtype=torch.float64)
        cam = loaded.camera
        torch.testing.assert_close(cam.camera_center.double(), c2w[:3, 3], atol=1e-5, rtol=0)
        for offset, d in (((0.0, 0.0), 3.0), ((0.2, 0.1), 2.0)):
            point = c2w @ torch.tensor([offset[0] * d, offset[1] * d, -d, 1.0], dtype=torch.float64)
            w2c = cam.world_to_camera.double()
            p = w2c[:3, :3] @ point[:3] + w2c[:3, 3]
            assert p[2].item() == pytest.approx(d, abs=1e-4)
            u, v = cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy
            # GL x right, y up -> image column grows with x, row shrinks with y.
            assert u.item() == pytest.approx(50 + cam.fx * offset[0], abs=1e-3)
            assert v.item() == pytest.approx(50 - cam.fy * offset[1], abs=1e-3)
        # The object at the origin is in view.
        p = (
            cam.world_to_camera.double()[:3, :3] @ torch.zeros(3, dtype=torch.float64)
            + cam.world_to_camera.double()[:3, 3]
        )
        assert p[2] > 0 and 0 <= cam.fx * p[0] / p[2] + cam.cx < 100 and 0 <= cam.fy * p[1] / p[2] + cam.cy < 100


@needs_dry_ice
def test_dry_ice_masks_points_and_times():
    scene = load_scene(DataConfig(DRY_ICE, downscale=10, max_frames=3, progress=False))
    assert set(scene.splits) == {"train", "test"} and scene.info["layout"] == "pidg"
    cam = scene.train[0].camera
    assert (cam.width, cam.height, cam.cx, cam.cy) == (96, 54, 48.0, 27.0)
    assert cam.fx == pytest.approx(cam.fy)  # square pixels on a 16:9 frame
    assert cam.fov_x == pytest.approx(0.6911112070083618, rel=1e-6)
    assert cam.fov_y == pytest.approx(2 * math.atan(math.tan(0.6911112070083618 / 2) * 540 / 960), rel=1e-6)
    for frame in scene.train + scene.test:
        assert frame.mask is not None and frame.mask.shape == (54, 96) and frame.mask.dtype == torch.bool
        assert frame.mask.any() and not frame.mask.all()
    assert scene.points3d is not None and len(scene.points3d) == 100_000 and scene.points3d.rgb is not None
    assert scene.bounds.points_min is not None and (scene.bounds.points_min < scene.bounds.points_max).all()
    # The json quirk: times normalised per split; the test frames' numbers are 1, 65, 129 (every 4th file).
    assert [f.name for f in scene.test] == ["train/0001", "train/0065", "train/0129"]
    assert scene.times("test").tolist() == [0.0, 0.5, 1.0]
    assert scene.info["json_time_vs_frame_number"] > 0.5 / 129

    by_number = load_scene(DataConfig(DRY_ICE, downscale=10, max_frames=3, time_source="frame_number", progress=False))
    assert by_number.time_source == "frame_number"
    # Files 0001..0130 are used across the two splits, so t = (k - 1) / 129.
    assert by_number.times("test").tolist() == pytest.approx([0.0, 64 / 129, 128 / 129])
    assert by_number.times("train").tolist() == pytest.approx(
        [int(f.name[-4:]) / 129 - 1 / 129 for f in by_number.train]
    )
