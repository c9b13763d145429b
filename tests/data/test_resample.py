"""Shrinking images to ``DataConfig.downscale``: D-NeRF's protocol (the area average of the straight RGBA, then
compositing), checked against an independent numpy computation, and which scenes take it by default."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

import pidg  # noqa: F401
from pidg.data import DataConfig, load_scene
from pidg.data.io import decode_rgb


def straight_rgba(width: int, height: int, seed: int) -> np.ndarray:
    """Random colours with transparent, half-transparent and opaque pixels; the transparent ones keep a colour (as
    Blender's straight-alpha PNGs do at object outlines), which the area average of straight RGBA mixes in."""
    rng = np.random.default_rng(seed)
    rgba = rng.integers(0, 256, (height, width, 4)).astype(np.uint8)
    rgba[..., 3] = rng.choice(np.array([0, 60, 200, 255], np.uint8), (height, width))
    rgba[0, 0, 3] = 255  # never transparent everywhere
    return rgba


def dnerf_protocol(rgba: np.ndarray, factor: int, background: float) -> np.ndarray:
    """What D-NeRF's / TiNeuVox's loaders compute, in float64 on the 0..255 scale: the mean of each factor x factor
    block of the straight RGBA in [0, 1], then rgb * a + background * (1 - a)."""
    values = rgba.astype(np.float64) / 255.0
    h, w = values.shape[:2]
    blocks = values.reshape(h // factor, factor, w // factor, factor, 4).mean(axis=(1, 3))
    return 255.0 * (blocks[..., :3] * blocks[..., 3:] + background * (1.0 - blocks[..., 3:]))


@pytest.mark.parametrize("background", [(1.0, 1.0, 1.0), (0.0, 0.0, 0.0)])
def test_area_rgba_is_the_dnerf_protocol(tmp_path, background):
    rgba = straight_rgba(12, 8, seed=1)
    Image.fromarray(rgba).save(tmp_path / "f.png")
    shrunk = decode_rgb(tmp_path / "f.png", background, size=(6, 4))
    expected = dnerf_protocol(rgba, 2, background[0])
    assert shrunk.shape == (4, 6, 3) and shrunk.dtype == np.float32
    np.testing.assert_allclose(shrunk, expected, atol=2e-3)
    # compositing first (a different image wherever a block mixes alpha and colour) is what it must not do
    composited = decode_rgb(tmp_path / "f.png", background).astype(np.float64)
    premultiplied_first = composited.reshape(4, 2, 6, 2, 3).mean(axis=(1, 3))
    assert np.abs(premultiplied_first - expected).max() > 1.0


def test_an_opaque_image_is_area_averaged(tmp_path):
    rgb = np.random.default_rng(2).integers(0, 256, (8, 12, 3)).astype(np.uint8)
    Image.fromarray(rgb).save(tmp_path / "f.png")
    shrunk = decode_rgb(tmp_path / "f.png", (1.0, 1.0, 1.0), size=(4, 4))  # 3 x 2 blocks
    np.testing.assert_allclose(shrunk, rgb.astype(np.float64).reshape(4, 2, 4, 3, 3).mean(axis=(1, 3)), atol=2e-3)


def test_auto_takes_the_dnerf_protocol_on_dnerf_scenes_only(tmp_path, synth):
    auto, lanczos, area = (DataConfig(tmp_path, resample=r) for r in ("auto", "lanczos", "area-rgba"))
    assert auto.resample_for("dnerf") == "area-rgba"
    assert auto.resample_for("pidg") == auto.resample_for("hypernerf") == "lanczos"
    assert lanczos.resample_for("dnerf") == "lanczos" and area.resample_for("pidg") == "area-rgba"
    dnerf = synth.make_blender(tmp_path / "dnerf", n_train=2, n_test=1, width=12, height=8)
    frames = {}
    for k in (1, 3, 2):
        frames[k] = straight_rgba(12, 8, seed=k)
        Image.fromarray(frames[k]).save(dnerf / "frames" / f"{k:04d}.png")
    scene = load_scene(DataConfig(dnerf, background="white", downscale=2, progress=False))
    assert scene.info["layout"] == "dnerf" and scene.info["resample"] == "area-rgba"
    for frame, k in zip(scene.train + scene.test, (1, 3, 2)):
        stored = frame.image_u8.numpy().astype(np.float64)
        assert np.abs(stored - dnerf_protocol(frames[k], 2, 1.0)).max() <= 0.5 + 1e-3  # rounded to 8 bits
        assert (frame.width, frame.height) == (6, 4)
    lanczos_scene = load_scene(DataConfig(dnerf, background="white", downscale=2, resample="lanczos", progress=False))
    assert lanczos_scene.info["resample"] == "lanczos"
    assert not np.array_equal(lanczos_scene.train[0].image_u8.numpy(), scene.train[0].image_u8.numpy())
    pidg_scene = synth.make_blender(tmp_path / "pidg", n_train=2, n_test=1, width=12, height=8, masks=True)
    assert load_scene(DataConfig(pidg_scene, downscale=2, progress=False)).info["resample"] == "lanczos"
