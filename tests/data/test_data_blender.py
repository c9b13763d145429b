"""Blender / D-NeRF / PIDG reader on tiny synthetic scenes written to tmp_path."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
import torch
from PIL import Image

import pidg  # noqa: F401
from pidg.data import DataConfig, DatasetError, load_scene, parse_downscale
from pidg.render.camera import Camera


def project(camera: Camera, point_world) -> tuple[float, float, float]:
    """Pixel (u, v) and depth of a world point, straight from the OpenCV definition."""
    w2c = camera.world_to_camera.to(torch.float64)
    p = w2c[:3, :3] @ torch.as_tensor(point_world, dtype=torch.float64) + w2c[:3, 3]
    return (
        camera.fx * p[0].item() / p[2].item() + camera.cx,
        camera.fy * p[1].item() / p[2].item() + camera.cy,
        p[2].item(),
    )


def cfg(root, **kw) -> DataConfig:
    return DataConfig(root, progress=False, **kw)


# ---------------------------------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("background", ["black", "white"])
def test_rgba_is_composited_on_background(tmp_path, synth, background):
    root = synth.make_blender(tmp_path / "s")
    scene = load_scene(cfg(root, background=background))
    assert scene.kind == "blender" and set(scene.splits) == {"train", "test"}
    assert [len(scene.train), len(scene.test)] == [3, 2]
    frame = scene.train[1]  # file 0003
    assert frame.name == "frames/0003" and frame.path == root / "frames" / "0003.png"
    assert frame.image_u8.dtype == torch.uint8 and frame.image_u8.shape == (6, 8, 3)
    image = frame.image
    assert image.dtype == torch.float32 and image.shape == (6, 8, 3)
    colour = torch.tensor([203, 103, 53]) / 255.0
    bg = 1.0 if background == "white" else 0.0
    torch.testing.assert_close(image[2, 0], colour)  # alpha 1
    torch.testing.assert_close(image[2, 5], torch.full((3,), bg))  # alpha 0
    a = 128 / 255
    expected = torch.round((colour * a + bg * (1 - a)) * 255) / 255  # stored as rounded 8-bit
    torch.testing.assert_close(image[2, 7], expected)
    torch.testing.assert_close(scene.background, torch.full((3,), bg))


def test_file_path_with_extension_and_as_is(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", ext_in_json=True)
    scene = load_scene(cfg(root))
    assert scene.train[0].path == root / "frames" / "0001.png"
    # A file without the .png extension on disk is found as written.
    (root / "frames" / "0001.png").rename(root / "frames" / "0001")
    synth.edit_json(root / "transforms_train.json", lambda d: d["frames"][0].update(file_path="frames/0001"))
    assert load_scene(cfg(root)).train[0].path == root / "frames" / "0001"


def test_camera_convention_matches_transform_matrix(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    scene = load_scene(cfg(root))
    c2w = torch.tensor(
        json.loads((root / "transforms_train.json").read_text())["frames"][2]["transform_matrix"], dtype=torch.float64
    )
    cam = scene.train[2].camera
    torch.testing.assert_close(cam.camera_center.double(), c2w[:3, 3], atol=1e-5, rtol=0)
    d = 2.5
    u, v, depth = project(cam, (c2w @ torch.tensor([0.0, 0.0, -d, 1.0], dtype=torch.float64))[:3])
    assert depth == pytest.approx(d, abs=1e-5)
    assert (u, v) == (pytest.approx(cam.width / 2, abs=1e-4), pytest.approx(cam.height / 2, abs=1e-4))
    # GL x right / y up: a point right of and above the axis lands right of and above the image centre.
    u, v, _ = project(cam, (c2w @ torch.tensor([0.3, 0.2, -d, 1.0], dtype=torch.float64))[:3])
    assert u > cam.cx and v < cam.cy


def test_non_square_images_use_square_pixels_unless_fov_y_given(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", width=16, height=8, fov_x=1.0)
    cam = load_scene(cfg(root)).train[0].camera
    fx = 8 / math.tan(0.5)
    assert (cam.width, cam.height, cam.cx, cam.cy) == (16, 8, 8.0, 4.0)
    assert cam.fx == pytest.approx(fx) and cam.fy == pytest.approx(fx)
    assert cam.fov_x == pytest.approx(1.0)
    assert cam.fov_y == pytest.approx(2 * math.atan(4 / fx))  # vertical FoV follows from the aspect
    # A point on the edge of the horizontal field of view projects to the image's right border.
    c2w = torch.tensor(
        json.loads((root / "transforms_train.json").read_text())["frames"][0]["transform_matrix"], dtype=torch.float64
    )
    u, v, _ = project(cam, (c2w @ torch.tensor([math.tan(0.5), 0.0, -1.0, 1.0], dtype=torch.float64))[:3])
    assert (u, v) == (pytest.approx(16.0, abs=1e-4), pytest.approx(4.0, abs=1e-4))

    synth.edit_json(root / "transforms_train.json", lambda d: d.update(camera_angle_y=0.6))
    cam = load_scene(cfg(root)).train[0].camera
    assert cam.fy == pytest.approx(4 / math.tan(0.3)) and cam.fov_y == pytest.approx(0.6)


def test_explicit_intrinsics_for_a_larger_original_image(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", width=8, height=6)

    def edit(d):
        del d["camera_angle_x"]
        d.update(fl_x=20.0, fl_y=22.0, cx=7.0, cy=5.0, w=16, h=12)  # intrinsics of a 2x larger original

    synth.edit_json(root / "transforms_train.json", edit)
    cam = load_scene(cfg(root)).train[0].camera
    assert (cam.width, cam.height) == (8, 6)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((10.0, 11.0, 3.5, 2.5))


def test_aspect_mismatch_between_json_size_and_image_is_an_error(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", width=8, height=6)
    synth.edit_json(root / "transforms_train.json", lambda d: d.update(w=16, h=16))
    with pytest.raises(DatasetError, match="another aspect ratio"):
        load_scene(cfg(root))


def test_time_from_frame_number_spans_all_splits(tmp_path, synth, caplog):
    root = synth.make_blender(tmp_path / "s", n_train=3, n_test=2)  # files 1,3,5 train / 2,4 test
    with caplog.at_level(logging.WARNING, logger="pidg.data"):
        scene = load_scene(cfg(root))
    assert scene.time_source == "json"
    assert scene.times("test").tolist() == [0.0, 1.0]  # per-split normalisation in the json (the quirk)
    assert "frame_number" in caplog.text  # the reader points at the disagreement
    scene = load_scene(cfg(root, time_source="frame_number"))
    assert scene.time_source == "frame_number"
    assert scene.times("train").tolist() == pytest.approx([0.0, 0.5, 1.0])
    assert scene.times("test").tolist() == pytest.approx([0.25, 0.75])


def test_frame_number_time_needs_unique_numbers(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    # D-NeRF style: every split numbers its own files from 0, so numbers are not times.
    (root / "other").mkdir()
    for k in (2, 4):
        (root / "frames" / f"{k:04d}.png").rename(root / "other" / f"{k - 1:04d}.png")
    synth.edit_json(
        root / "transforms_test.json",
        lambda d: [f.update(file_path=f"other/{i * 2 + 1:04d}") for i, f in enumerate(d["frames"])],
    )
    assert load_scene(cfg(root)).time_source == "json"
    with pytest.raises(DatasetError, match="frame numbers do not identify"):
        load_scene(cfg(root, time_source="frame_number"))


def test_missing_time_is_an_error_unless_allowed(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", n_train=3)
    synth.edit_json(root / "transforms_train.json", lambda d: [f.pop("time") for f in d["frames"]])
    with pytest.raises(DatasetError, match=r"transforms_train.json: frame 0 .*missing key 'time'"):
        load_scene(cfg(root))
    scene = load_scene(cfg(root, allow_missing_time=True))
    assert scene.time_source == "index" and scene.times("train").tolist() == [0.0, 0.5, 1.0]


def test_masks_points_and_bounds(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", masks=True, points=True)
    scene = load_scene(cfg(root))
    mask = scene.train[0].mask
    assert mask is not None and mask.dtype == torch.bool and mask.shape == (6, 8)
    assert mask[:3].all() and not mask[3:].any()
    assert scene.info["layout"] == "pidg"
    assert scene.points3d is not None and len(scene.points3d) == 50 and scene.points3d.rgb is not None
    assert float(scene.points3d.rgb.min()) >= 0 and float(scene.points3d.rgb.max()) <= 1
    torch.testing.assert_close(scene.bounds.points_min, scene.points3d.xyz.min(0).values)
    centers = torch.stack([f.camera.camera_center for f in scene.train]).double()
    torch.testing.assert_close(scene.bounds.center.double(), centers.mean(0), atol=1e-5, rtol=0)
    radius = 1.1 * (centers - centers.mean(0)).norm(dim=1).max().item()
    assert scene.bounds.radius == pytest.approx(radius, rel=1e-5) and scene.bounds.extent == scene.bounds.radius
    assert load_scene(cfg(root, load_masks=False)).train[0].mask is None


def test_downscale_by_factor_and_to_size(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", width=16, height=12, masks=True)
    full = load_scene(cfg(root)).train[0]
    half = load_scene(cfg(root, downscale=2)).train[0]
    assert half.image_u8.shape == (6, 8, 3) and half.mask.shape == (6, 8) and half.mask.dtype == torch.bool
    assert half.mask[:3].all() and not half.mask[3:].any()
    assert (half.camera.fx, half.camera.cx, half.camera.cy) == pytest.approx((full.camera.fx / 2, 4.0, 3.0))
    # Flat regions survive the Lanczos filter unchanged.
    torch.testing.assert_close(half.image[2, 0], full.image[2, 0])
    sized = load_scene(cfg(root, downscale=(10, 5))).train[0]
    assert sized.image_u8.shape == (5, 10, 3)
    assert (sized.camera.width, sized.camera.height) == (10, 5)
    assert sized.camera.fx == pytest.approx(full.camera.fx * 10 / 16)
    assert sized.camera.fy == pytest.approx(full.camera.fy * 5 / 12)
    assert parse_downscale("400x400") == (400, 400) and parse_downscale("2") == 2.0
    with pytest.raises(ValueError):
        parse_downscale("big")


def test_max_frames_keeps_times_and_bounds(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", n_train=7, n_test=3)
    full = load_scene(cfg(root, time_source="frame_number"))
    sub = load_scene(cfg(root, time_source="frame_number", max_frames=3))
    assert [f.name for f in sub.train] == [full.train[i].name for i in (0, 3, 6)]
    assert sub.times("train").tolist() == [full.train[i].time for i in (0, 3, 6)]
    torch.testing.assert_close(sub.bounds.center, full.bounds.center)
    assert len(load_scene(cfg(root, max_frames=1)).train) == 1


def test_config_validation():
    with pytest.raises(ValueError, match="background"):
        DataConfig("x", background="grey")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="splits"):
        DataConfig("x", splits=("training",))
    with pytest.raises(ValueError, match="downscale"):
        DataConfig("x", downscale=0)
    with pytest.raises(ValueError, match="even"):
        DataConfig("x", hypernerf_interp_interval=3)
    assert issubclass(DatasetError, ValueError)


# ---------------------------------------------------------------------------------------------------------------
# bad input: every problem is a DatasetError naming the file
# ---------------------------------------------------------------------------------------------------------------
def test_missing_image(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    (root / "frames" / "0003.png").unlink()
    with pytest.raises(
        DatasetError, match=r"0003\.png: image file not found \(frame 1 \('frames/0003'\) of transforms_train.json"
    ):
        load_scene(cfg(root))


def test_unreadable_image(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    (root / "frames" / "0003.png").write_bytes(b"not a png at all")
    with pytest.raises(DatasetError, match=r"0003\.png: cannot read image"):
        load_scene(cfg(root))


def test_malformed_json_reports_line_and_column(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    path = root / "transforms_test.json"
    path.write_text('{\n  "camera_angle_x": 0.5,\n  "frames": [,]\n}')
    with pytest.raises(DatasetError, match=r"transforms_test.json: malformed JSON at line 3, column 14"):
        load_scene(cfg(root))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda d: d["frames"][1].pop("transform_matrix"),
            r"frame 1 \('frames/0003'\): missing key 'transform_matrix'",
        ),
        (lambda d: d["frames"][0].pop("file_path"), r"frame 0: missing key 'file_path'"),
        (lambda d: d.pop("frames"), r"missing key 'frames'"),
        (lambda d: d.pop("camera_angle_x"), r"frame 0 .*no intrinsics"),
        (lambda d: d["frames"][2].update(time=1.5), r"frame 2 .*time 1.5 is outside \[0, 1\]"),
        (lambda d: d["frames"][2].update(time=float("nan")), r"frame 2 .*'time' is nan"),
        (lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(0, 2.0), r"frame 1 .*not a rotation"),
        (lambda d: d["frames"][1]["transform_matrix"][1].__setitem__(3, float("nan")), r"frame 1 .*NaN"),
        (lambda d: d["frames"][1].update(transform_matrix=[[1, 0, 0], [0, 1, 0]]), r"frame 1 .*must be 4x4"),
        (lambda d: d.update(camera_angle_x=-1), r"'camera_angle_x' must be positive"),
    ],
)
def test_bad_train_json(tmp_path, synth, edit, message):
    root = synth.make_blender(tmp_path / "s")
    synth.edit_json(root / "transforms_train.json", edit)
    with pytest.raises(DatasetError, match=r"transforms_train\.json: " + message):
        load_scene(cfg(root))


def test_frames_of_different_sizes(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    Image.fromarray(synth.rgba_pattern(10, 6, 0)).save(root / "frames" / "0005.png")
    # Keep the aspect check out of the way: this camera comes from the fov, so only the size check can fire.
    with pytest.raises(DatasetError, match=r"0005\.png: image is 10x6 but the split's first frame .* is 8x6"):
        load_scene(cfg(root))


def test_mask_problems(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", masks=True)
    Image.fromarray(np.zeros((3, 4), np.uint8)).save(root / "mask" / "0003.png")
    with pytest.raises(DatasetError, match=r"0003\.png: mask is 4x3 but its image is 8x6"):
        load_scene(cfg(root))
    (root / "mask" / "0003.png").unlink()
    with pytest.raises(DatasetError, match=r"0003\.png: mask file not found"):
        load_scene(cfg(root))


def test_missing_split_and_unknown_folder(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    with pytest.raises(DatasetError, match=r"transforms_val.json: split 'val' was requested"):
        load_scene(cfg(root, splits=("train", "val")))
    assert set(load_scene(cfg(root, splits=("test",))).splits) == {"test"}
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="not a known dataset"):
        load_scene(cfg(tmp_path / "empty"))
    with pytest.raises(DatasetError, match="dataset folder not found"):
        load_scene(cfg(tmp_path / "nowhere"))


def test_depth_maps_are_loaded_resized_and_checked(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", width=16, height=12)
    (root / "depth").mkdir()
    for k in (1, 3, 5):
        depth = np.full((12, 16), 2.0, np.float32)
        depth[:, 8:] = 5.0
        depth[0, 0] = np.nan  # unknown
        np.save(root / "depth" / f"{k:04d}.npy", depth)
    scene = load_scene(cfg(root, downscale=(8, 6)))
    d = scene.train[0].depth
    assert d is not None and d.shape == (6, 8) and d.dtype == torch.float32
    assert set(d.unique().tolist()) <= {0.0, 2.0, 5.0} and d[:, :4].max() == 2.0 and d[:, 4:].min() == 5.0
    assert scene.test[0].depth is None  # no depth file for the test frames: the model's depth is used
    np.save(root / "depth" / "0003.npy", np.zeros((5, 5), np.float32))
    with pytest.raises(DatasetError, match=r"0003\.npy.*depth map is 5x5"):
        load_scene(cfg(root))
    np.save(root / "depth" / "0003.npy", -np.ones((12, 16), np.float32))
    with pytest.raises(DatasetError, match="negative"):
        load_scene(cfg(root))
