"""Malformed or unusual dataset files: each is decoded correctly or rejected with one line naming the file.

Images (16-bit, transparency, modes without a 0..255 range, all-transparent frames), the same image listed twice,
point clouds (empty, NaN, absurd coordinates) and depth maps (.npz, +inf background, which frames have one).
"""

from __future__ import annotations

import json
import logging
import struct
import zlib

import numpy as np
import pytest
import torch
from PIL import Image

import pidg  # noqa: F401
import pidg.data.io as data_io
from pidg.data import DataConfig, DatasetError, load_scene, read_ply_points, write_ply_points


def cfg(root, **kw) -> DataConfig:
    return DataConfig(root, progress=False, **kw)


def write_png16(path, samples: np.ndarray) -> None:
    """A 16-bit PNG (gray [H, W], gray+alpha [H, W, 2], RGB [H, W, 3] or RGBA [H, W, 4]) written by hand:
    PIL can write 16-bit gray only."""
    samples = samples if samples.ndim == 3 else samples[..., None]
    height, width, channels = samples.shape
    color_type = {1: 0, 2: 4, 3: 2, 4: 6}[channels]
    raw = b"".join(b"\0" + samples[y].astype(">u2").tobytes() for y in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 16, color_type, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    )


def frame_0003(scene):
    """The frame of file frames/0003.png (the second training frame of ``make_blender``)."""
    frame = scene.train[1]
    assert frame.name == "frames/0003"
    return frame.image_u8.to(torch.int64)


def ramp16(width: int = 8, height: int = 6) -> np.ndarray:
    """16-bit levels covering 0..65535, most of them above 255 (where an 8-bit conversion clips)."""
    return np.linspace(0, 65535, width * height).round().astype(np.uint16).reshape(height, width)


# ---------------------------------------------------------------------------------------------------------------
# images: 16-bit, transparency keys, modes that are not pictures, frames with nothing in them
# ---------------------------------------------------------------------------------------------------------------
def test_16bit_gray_png_is_scaled_to_8_bits(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    levels = ramp16()
    Image.fromarray(levels).save(root / "frames" / "0003.png")  # PIL writes uint16 as a 16-bit gray PNG
    image = frame_0003(load_scene(cfg(root)))
    expected = torch.from_numpy(np.rint(levels * (255 / 65535)).astype(np.int64))
    for c in range(3):  # gray to RGB
        torch.testing.assert_close(image[..., c], expected, rtol=0, atol=0)
    assert (image == 255).float().mean() < 0.05  # not clipped: only the brightest level reaches 255


def test_16bit_gray_png_from_old_pillow_mode_i(tmp_path, synth, monkeypatch):
    """Pillow < 10 opens 16-bit gray PNGs as mode "I" (32-bit int storage); a PNG's "I" is 16-bit gray."""
    root = synth.make_blender(tmp_path / "s")
    levels = ramp16()
    as_mode_i = Image.fromarray(levels.astype(np.int32))
    as_mode_i.format = "PNG"
    assert as_mode_i.mode == "I"
    monkeypatch.setattr(data_io, "_open_image", lambda path, kind="image": as_mode_i)
    rgb = data_io.decode_rgb(root / "frames" / "0003.png", (0.0, 0.0, 0.0))
    np.testing.assert_allclose(rgb[..., 1], levels * (255 / 65535), rtol=1e-6)


def test_16bit_gray_png_with_a_transparent_level(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    levels = ramp16()
    levels[:, :3] = 40000  # the tRNS key: these pixels are background
    Image.fromarray(levels).save(root / "frames" / "0003.png", transparency=40000)
    image = frame_0003(load_scene(cfg(root, background="white")))
    assert (image[:, :3] == 255).all()
    assert image[0, 5, 0].item() == round(int(levels[0, 5]) * 255 / 65535)


@pytest.mark.parametrize("channels", [2, 3, 4])
def test_16bit_gray_alpha_rgb_and_rgba_pngs(tmp_path, synth, channels):
    """PIL hands these over as 8-bit (the high byte of each sample): within one level of v * 255 / 65535."""
    root = synth.make_blender(tmp_path / "s")
    samples = np.random.default_rng(channels).integers(0, 65536, (6, 8, channels)).astype(np.uint16)
    if channels in (2, 4):
        samples[..., -1] = 65535  # opaque, so the colour is compared directly
        samples[0, 0, -1] = 0  # one transparent pixel: background
    write_png16(root / "frames" / "0003.png", samples)
    image = frame_0003(load_scene(cfg(root)))
    colour = samples[..., :3] if channels >= 3 else np.repeat(samples[..., :1], 3, axis=2)
    expected = torch.from_numpy(colour * (255 / 65535))
    if channels in (2, 4):
        expected[0, 0] = 0.0
    assert (image - expected).abs().max() <= 1.0


def test_8bit_gray_and_rgb_with_a_transparent_colour(tmp_path, synth):
    """A tRNS chunk on a gray or RGB PNG is alpha too (PIL applies it when converting to RGBA)."""
    root = synth.make_blender(tmp_path / "s")
    gray = np.full((6, 8), 90, np.uint8)
    gray[:, 4:] = 7  # transparent
    Image.fromarray(gray).save(root / "frames" / "0003.png", transparency=7)
    rgb = np.full((6, 8, 3), (10, 20, 30), np.uint8)
    rgb[:2] = (1, 2, 3)  # transparent
    Image.fromarray(rgb).save(root / "frames" / "0005.png", transparency=(1, 2, 3))
    scene = load_scene(cfg(root, background="white"))
    image = frame_0003(scene)
    assert (image[:, :4] == 90).all() and (image[:, 4:] == 255).all()
    image = scene.train[2].image_u8
    assert (image[:2] == 255).all() and image[2:].tolist() == [[[10, 20, 30]] * 8] * 4


@pytest.mark.parametrize(
    ("mode", "what"), [("F", r"'F' \(32-bit float samples\)"), ("I", r"'I' \(32-bit integer samples\)")]
)
def test_modes_without_a_0_255_range_are_rejected(tmp_path, synth, mode, what):
    root = synth.make_blender(tmp_path / "s")
    values = np.linspace(0, 2, 48, dtype=np.float32).reshape(6, 8)
    # A TIFF under the frame's name: PIL identifies images by content, as it would a mislabelled file.
    Image.fromarray(values if mode == "F" else (values * 1e6).astype(np.int32)).save(
        root / "frames" / "0003.png", format="TIFF"
    )
    with pytest.raises(DatasetError, match=rf"0003\.png: image mode {what} has no 0\.\.255 range"):
        load_scene(cfg(root))


def test_cmyk_and_16bit_gray_tiff_are_converted(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    Image.new("CMYK", (8, 6), (0, 255, 255, 0)).save(root / "frames" / "0003.png", format="TIFF")  # red
    Image.fromarray(ramp16()).save(root / "frames" / "0005.png", format="TIFF")
    scene = load_scene(cfg(root))
    assert frame_0003(scene)[0, 0].tolist() == [255, 0, 0]
    level = round(int(ramp16()[3, 4]) * 255 / 65535)
    assert 0 < level < 255 and scene.train[2].image_u8[3, 4].tolist() == [level] * 3


@pytest.mark.parametrize("mode", ["RGBA", "LA", "P"])
def test_frame_with_zero_alpha_everywhere_is_rejected(tmp_path, synth, mode):
    root = synth.make_blender(tmp_path / "s")
    rgba = synth.rgba_pattern(8, 6, 3)
    rgba[..., 3] = 0
    image = Image.fromarray(rgba)
    if mode == "LA":
        image = image.convert("LA")
    elif mode == "P":
        image = Image.fromarray(np.zeros((6, 8), np.uint8), "P")  # every pixel the transparent palette entry
    image.save(root / "frames" / "0003.png", **({"transparency": 0} if mode == "P" else {}))
    assert Image.open(root / "frames" / "0003.png").mode == mode
    with pytest.raises(DatasetError, match=r"frames/0003\.png: alpha is zero everywhere"):
        load_scene(cfg(root))


def test_frame_with_a_single_visible_pixel_is_kept(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    rgba = synth.rgba_pattern(8, 6, 3)
    rgba[..., 3] = 0
    rgba[5, 7, 3] = 1
    Image.fromarray(rgba).save(root / "frames" / "0003.png")
    assert frame_0003(load_scene(cfg(root)))[5, 7].tolist() == [1, 0, 0]  # 203 * 1/255, rounded


# ---------------------------------------------------------------------------------------------------------------
# the same image listed twice
# ---------------------------------------------------------------------------------------------------------------
def test_same_image_with_another_time_in_one_file(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")

    def repeat(d):
        d["frames"][2] = dict(d["frames"][0], time=1.0)  # same file and pose, other time

    synth.edit_json(root / "transforms_train.json", repeat)
    with pytest.raises(
        DatasetError,
        match=r"transforms_train\.json: frame 2 \('frames/0001'\) names the same image as frame 0 \('frames/0001'\) "
        r"with another time \(1 here, 0 there\)$",
    ):
        load_scene(cfg(root))


def test_same_image_with_another_pose_across_splits(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    # Test frame 0 (time 0, like train frame 0) names train's first file, written another way, from its own camera.
    synth.edit_json(root / "transforms_test.json", lambda d: d["frames"][0].update(file_path="./frames/0001.png"))
    with pytest.raises(
        DatasetError,
        match=r"transforms_test\.json: frame 0 \('\./frames/0001\.png'\) names the same image as frame 0 "
        r"\('frames/0001'\) of transforms_train\.json with another camera pose \('transform_matrix' entries differ",
    ):
        load_scene(cfg(root))
    # Only the test split loaded: the train file is still read, so the contradiction is still found.
    with pytest.raises(DatasetError, match="another camera pose"):
        load_scene(cfg(root, splits=("test",)))


def test_identical_repeats_load_with_a_warning(tmp_path, synth, caplog):
    root = synth.make_blender(tmp_path / "s")

    def copy_train_frame(d):
        d["frames"][1] = dict(d["frames"][0])  # an exact repeat inside the split

    synth.edit_json(root / "transforms_train.json", copy_train_frame)
    first = json.loads((root / "transforms_train.json").read_text())["frames"][0]
    # A test frame repeating a training frame exactly (time 0 in both files).
    synth.edit_json(root / "transforms_test.json", lambda d: d["frames"].__setitem__(0, dict(first)))
    with caplog.at_level(logging.WARNING, logger="pidg.data"):
        scene = load_scene(cfg(root))
    assert [f.name for f in scene.train] == ["frames/0001", "frames/0001", "frames/0005"]
    assert "2 image(s) listed twice with identical entries" in caplog.text
    assert "1 are training images in an evaluation split" in caplog.text


def test_repeat_with_other_json_times_is_one_time_from_frame_numbers(tmp_path, synth):
    """With time_source='frame_number' a file's time is its number, so json times cannot contradict."""
    root = synth.make_blender(tmp_path / "s")

    def repeat(d):
        d["frames"][2] = dict(d["frames"][0], time=1.0)  # same file and pose, other time

    synth.edit_json(root / "transforms_train.json", repeat)
    with pytest.raises(DatasetError, match="another time"):
        load_scene(cfg(root))
    # Files 0001, 0003, 0001 (train) and 0002, 0004 (test): t = (k - 1) / 3.
    times = load_scene(cfg(root, time_source="frame_number")).times("train").tolist()
    assert times == pytest.approx([0.0, 2 / 3, 0.0])


# ---------------------------------------------------------------------------------------------------------------
# point clouds
# ---------------------------------------------------------------------------------------------------------------
def _binary_ply(xyz: np.ndarray, dtype: str = "<f4", count: int | None = None) -> bytes:
    kind = {"<f4": "float", "<f8": "double"}[dtype]
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz) if count is None else count}\n"
        f"property {kind} x\nproperty {kind} y\nproperty {kind} z\nend_header\n"
    )
    return header.encode() + np.asarray(xyz, dtype).tobytes()


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (_binary_ply(np.zeros((0, 3))), "point cloud has 0 points"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
         "point cloud has 0 points"),
        (_binary_ply(np.array([[0, 0, 0], [1e30, 0, 0], [0, 2, 0]])),
         r"1 of 3 points have coordinates beyond \+-1e\+06 scene units \(point 1 is \(1e\+30, 0, 0\)\)$"),
        (_binary_ply(np.array([[0, 0, 0], [0, 0, -1e300]]), "<f8"), r"1 of 2 points have coordinates beyond"),
        (_binary_ply(np.array([[0, 0, 0], [0, np.inf, 0], [np.nan, 0, 0]])),
         r"2 of 3 points have NaN or infinite coordinates \(first: point 1\)"),
        (_binary_ply(np.zeros((1, 3)), count=-1), r"bad PLY element line 'element vertex -1'"),
    ],
)  # fmt: skip
def test_empty_non_finite_and_absurd_point_clouds(tmp_path, content, message):
    path = tmp_path / "points3d.ply"
    path.write_bytes(content)
    with pytest.raises(DatasetError, match=r"points3d\.ply: " + message):
        read_ply_points(path)


def test_point_cloud_with_nan_colours(tmp_path):
    path = tmp_path / "c.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        "property float red\nproperty float green\nproperty float blue\nend_header\n1 2 3 0.5 0.5 0.5\n4 5 6 nan 0 0\n"
    )
    with pytest.raises(DatasetError, match=r"c\.ply: 1 of 2 points have NaN or infinite colours"):
        read_ply_points(path)


def test_bad_point_cloud_is_named_when_loading_a_scene(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s", points=True)
    write_ply_points(root / "points3d.ply", np.zeros((0, 3)))
    with pytest.raises(DatasetError, match=r"s/points3d\.ply: point cloud has 0 points"):
        load_scene(cfg(root))
    write_ply_points(root / "points3d.ply", np.full((4, 3), 2e6))
    with pytest.raises(DatasetError, match=r"points3d\.ply: 4 of 4 points have coordinates beyond"):
        load_scene(cfg(root))


@pytest.mark.parametrize(
    ("points", "message"),
    [(np.zeros((0, 3)), "point cloud has 0 points"), (np.array([[0.0, 0, 0], [0, 0, 1e30]]), "beyond")],
)
def test_bad_hypernerf_points(tmp_path, synth, points, message):
    root = synth.make_hypernerf(tmp_path / "h", n=3)
    np.save(root / "points.npy", points)
    with pytest.raises(DatasetError, match=r"points\.npy: .*" + message):
        load_scene(cfg(root))


# ---------------------------------------------------------------------------------------------------------------
# depth maps
# ---------------------------------------------------------------------------------------------------------------
def _depth(value: float = 2.0) -> np.ndarray:
    return np.full((6, 8), value, np.float32)


def test_depth_from_npz_by_name_or_as_the_only_array(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    (root / "depth").mkdir()
    np.savez(root / "depth" / "0001.npz", _depth(1.0))  # one unnamed array (arr_0)
    np.savez_compressed(root / "depth" / "0003.npz", confidence=_depth(9.0), depth=_depth(3.0))
    np.save(root / "depth" / "0005.npy", _depth(5.0))
    scene = load_scene(cfg(root))
    assert [float(f.depth.unique()) for f in scene.train] == [1.0, 3.0, 5.0]
    assert scene.info["depth_maps"] is True


@pytest.mark.parametrize(
    ("write", "message"),
    [
        (lambda p: np.savez(p / "0003.npz", a=_depth(), b=_depth()), r"0003\.npz: depth \.npz holds arrays \['a', 'b'"),
        (lambda p: np.savez(p / "0003.npz"), r"0003\.npz: depth \.npz holds arrays \[\]"),
        (lambda p: (p / "0003.npz").write_bytes(b"PK\x03\x04broken"), r"0003\.npz: cannot read depth map"),
        (lambda p: (p / "0003.npy").write_bytes(b"hello"), r"0003\.npy: cannot read depth map: not a NumPy"),
        (lambda p: (p / "0003.npy").write_bytes(b""), r"0003\.npy: cannot read depth map: not a NumPy"),
        (lambda p: np.save(p / "0003.npy", _depth() + 1j), r"0003\.npy: depth map must be a 2D real array"),
        (
            lambda p: (np.save(p / "0003.npy", _depth()), np.savez(p / "0003.npz", _depth())),
            r"0003\.npz: 0003\.npy exists too",
        ),
    ],
)  # fmt: skip
def test_bad_depth_files(tmp_path, synth, write, message):
    root = synth.make_blender(tmp_path / "s")
    (root / "depth").mkdir()
    write(root / "depth")
    with pytest.raises(DatasetError, match=message):
        load_scene(cfg(root))


def test_infinite_and_nan_depth_is_unknown(tmp_path, synth):
    root = synth.make_blender(tmp_path / "s")
    (root / "depth").mkdir()
    depth = _depth(2.0)
    depth[:, 4:] = np.inf  # background in Blender's Z pass
    depth[0, 0] = np.nan
    depth[1, 0] = -np.inf
    np.save(root / "depth" / "0001.npy", depth)
    np.savez(root / "depth" / "0003.npz", depth=depth)
    scene = load_scene(cfg(root))
    for frame in scene.train[:2]:
        d = frame.depth
        assert d is not None and torch.isfinite(d).all()
        assert (d[:, 4:] == 0).all() and d[0, 0] == 0 and d[1, 0] == 0 and (d[2:, :4] == 2.0).all()


def test_depth_maps_info_reports_depth_found_for_loaded_frames(tmp_path, synth, caplog):
    root = synth.make_blender(tmp_path / "s")
    assert load_scene(cfg(root)).info["depth_maps"] is False  # no depth/ folder
    (root / "depth").mkdir()
    np.save(root / "depth" / "r_0001.npy", _depth())  # a name that matches no frame
    with caplog.at_level(logging.WARNING, logger="pidg.data"):
        scene = load_scene(cfg(root))
    assert scene.info["depth_maps"] is False and all(f.depth is None for f in scene.train + scene.test)
    assert "depth: depth/ holds no <frame file name>.npy or .npz for the loaded frames" in caplog.text
    np.save(root / "depth" / "0002.npy", _depth())  # a test frame's
    assert load_scene(cfg(root)).info["depth_maps"] is True
    assert load_scene(cfg(root, splits=("train",))).info["depth_maps"] is False
