"""HyperNeRF / Nerfies reader on tiny synthetic captures (no real HyperNeRF data is available here)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import pidg  # noqa: F401
from pidg.data import DataConfig, DatasetError, camera_from_nerfies_json, load_scene


def cfg(root, **kw) -> DataConfig:
    return DataConfig(root, progress=False, **kw)


def test_vrig_trains_on_left_and_tests_on_right(tmp_path, synth):
    root = synth.make_hypernerf(tmp_path / "vrig", n=5)
    scene = load_scene(cfg(root, hypernerf_image_scale=2))
    assert scene.kind == "hypernerf" and set(scene.splits) == {"train", "test"}
    assert [f.name for f in scene.train] == [f"left_{i:06d}" for i in range(5)]
    assert [f.name for f in scene.test] == [f"right_{i:06d}" for i in range(5)]
    assert scene.time_source == "metadata.json:warp_id"
    assert scene.times("train").tolist() == pytest.approx([0, 0.25, 0.5, 0.75, 1])
    assert scene.times("test").tolist() == scene.times("train").tolist()  # the rig films both views at once
    frame = scene.test[3]
    assert frame.path == root / "rgb" / "2x" / "right_000003.png"
    assert frame.image_u8.shape == (6, 8, 3)
    assert frame.image_u8[0, 0].tolist() == [30, 20, 30]
    assert scene.near_far == (0.1, 5.0) and scene.info["image_scale"] == 2


def test_nerfies_camera_geometry(tmp_path, synth):
    root = synth.make_hypernerf(tmp_path / "vrig", n=3, center=(0.5, -0.5, 0.25), scale=0.5)
    scene = load_scene(cfg(root, hypernerf_image_scale=2))
    raw = synth.nerfies_camera((3.0, 0.3, 1.0))  # left_000001
    cam = scene.train[1].camera
    # Intrinsics: focal 20 and principal point (7, 5.5) of a 16x12 image, halved for rgb/2x.
    assert (cam.width, cam.height) == (8, 6)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((10.0, 10.0, 3.5, 2.75))
    # Position recentred and scaled by scene.json.
    expected_center = (torch.tensor(raw["position"]) - torch.tensor([0.5, -0.5, 0.25])) * 0.5
    torch.testing.assert_close(cam.camera_center, expected_center, atol=1e-5, rtol=0)
    # A point on the optical axis (third row of `orientation`) projects to the principal point, in front.
    d = 2.0
    point = (
        torch.tensor(raw["position"]) + d * torch.tensor(raw["orientation"][2]) - torch.tensor([0.5, -0.5, 0.25])
    ) * 0.5
    p = cam.world_to_camera[:3, :3] @ point + cam.world_to_camera[:3, 3]
    assert p[2].item() == pytest.approx(d * 0.5, abs=1e-5)
    assert (cam.fx * p[0] / p[2] + cam.cx).item() == pytest.approx(3.5, abs=1e-4)
    assert (cam.fy * p[1] / p[2] + cam.cy).item() == pytest.approx(2.75, abs=1e-4)
    # Camera y is down: a point displaced along orientation[1] lands lower in the image.
    q = cam.world_to_camera[:3, :3] @ (point + 0.1 * torch.tensor(raw["orientation"][1])) + cam.world_to_camera[:3, 3]
    assert (cam.fy * q[1] / q[2] + cam.cy).item() > 2.75
    # Bounds from the training cameras; points.npy recentred and scaled too.
    assert scene.points3d is not None and scene.points3d.xyz.tolist() == [[0, 0, 0], [0.5, 0, 0]]


def test_pixel_aspect_ratio_and_full_scale(tmp_path, synth):
    raw = synth.nerfies_camera((3.0, 0.0, 1.0), focal=20.0, aspect=1.1, principal_point=(8.0, 6.0))
    cam = camera_from_nerfies_json(raw, tmp_path / "c.json", image_scale=1)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == pytest.approx((20, 22, 8, 6, 16, 12))
    cam4 = camera_from_nerfies_json(raw, tmp_path / "c.json", image_scale=4)
    assert (cam4.fx, cam4.width, cam4.height) == pytest.approx((5, 4, 3))


@pytest.mark.parametrize(("interval", "train", "test"), [(4, [0, 4, 8], [2, 6]), (2, [0, 2, 4, 6, 8], [1, 3, 5, 7])])
def test_interp_holds_out_midpoints(tmp_path, synth, interval, train, test):
    root = synth.make_hypernerf(tmp_path / "interp", n=10, vrig=False, scales=(1,))
    scene = load_scene(
        cfg(
            root,
            hypernerf_split="interp",
            hypernerf_interp_interval=interval,
            hypernerf_image_scale=1,
            downscale=(8, 6),
        )
    )
    assert [f.name for f in scene.train] == [f"{i:06d}" for i in train]
    assert [f.name for f in scene.test] == [f"{i:06d}" for i in test]
    # Normalised over all ids (0..9), not only the loaded ones.
    assert scene.times("test").tolist() == pytest.approx([i / 9 for i in test])
    assert scene.train[0].image_u8.shape == (6, 8, 3) and scene.train[0].camera.fx == pytest.approx(10.0)


def test_vrig_on_a_single_camera_capture_points_to_interp(tmp_path, synth):
    root = synth.make_hypernerf(tmp_path / "interp", n=5, vrig=False, scales=(1,))
    with pytest.raises(DatasetError, match="use hypernerf_split='interp'"):
        load_scene(cfg(root, hypernerf_image_scale=1))


def test_time_id_preferred_over_warp_id(tmp_path, synth):
    root = synth.make_hypernerf(tmp_path / "vrig", n=3)
    synth.edit_json(root / "metadata.json", lambda m: [e.update(time_id=10 + 2 * e["warp_id"]) for e in m.values()])
    scene = load_scene(cfg(root, max_frames=2))
    assert scene.time_source == "metadata.json:time_id"
    assert scene.times("train").tolist() == [0.0, 1.0]


@pytest.mark.parametrize(
    ("break_it", "kwargs", "message"),
    [
        (
            lambda r, s: None,
            {"hypernerf_image_scale": 4},
            r"rgb/4x: image folder not found \(rgb/ has \['1x', '2x'\]\)",
        ),
        (lambda r, s: (r / "camera" / "right_000001.json").unlink(), {}, r"right_000001\.json: file not found"),
        (lambda r, s: (r / "rgb" / "2x" / "left_000002.png").unlink(), {}, r"left_000002\.png: image file not found"),
        (
            lambda r, s: s.edit_json(r / "metadata.json", lambda m: m["left_000001"].pop("warp_id")),
            {},
            r"metadata\.json: item 'left_000001': missing key 'warp_id'",
        ),
        (
            lambda r, s: s.edit_json(r / "dataset.json", lambda d: d.pop("val_ids")),
            {},
            r"dataset\.json: missing key 'val_ids'",
        ),
        (lambda r, s: s.edit_json(r / "scene.json", lambda d: d.pop("scale")), {}, r"scene\.json: missing key 'scale'"),
        (
            lambda r, s: (r / "dataset.json").write_text('{\n"ids": [1,\n}'),
            {},
            r"dataset\.json: malformed JSON at line 3",
        ),
        (
            lambda r, s: s.edit_json(
                r / "camera" / "left_000000.json", lambda c: c["orientation"][0].__setitem__(0, 5.0)
            ),
            {},
            r"left_000000\.json: camera: .*not a rotation",
        ),
        (
            lambda r, s: None,
            {"splits": ("train", "val")},
            r"dataset\.json: HyperNeRF data has splits 'train' and 'test'",
        ),
        (
            lambda r, s: None,
            {"time_source": "frame_number"},
            r"metadata\.json: HyperNeRF times come from metadata.json",
        ),
        (lambda r, s: np.save(r / "points.npy", np.zeros((3, 2))), {}, r"points\.npy: expected a \[P, 3\] array"),
    ],
)
def test_bad_captures(tmp_path, synth, break_it, kwargs, message):
    root = synth.make_hypernerf(tmp_path / "vrig", n=3)
    break_it(root, synth)
    with pytest.raises(DatasetError, match=message):
        load_scene(cfg(root, **kwargs))


def test_image_of_the_wrong_size(tmp_path, synth):
    from PIL import Image

    root = synth.make_hypernerf(tmp_path / "vrig", n=3)
    Image.fromarray(np.zeros((5, 8, 3), np.uint8)).save(root / "rgb" / "2x" / "left_000001.png")
    with pytest.raises(DatasetError, match=r"left_000001\.png: image is 8x5 but its camera describes 8x6"):
        load_scene(cfg(root))
