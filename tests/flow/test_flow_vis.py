"""Flow pictures: the Middlebury colour wheel and quiver plots."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import pidg  # noqa: F401
from pidg.evaluation.flow_vis import (
    flow_quiver,
    flow_rgb_tensor,
    flow_to_rgb,
    make_colorwheel,
)


def colour_of(dx: float, dy: float, max_magnitude: float | None = None) -> np.ndarray:
    return flow_to_rgb(np.array([[[dx, dy]]], np.float32), max_magnitude=max_magnitude)[0, 0].astype(int)


def test_colorwheel_has_the_middlebury_segments():
    wheel = make_colorwheel()
    assert wheel.shape == (55, 3)
    np.testing.assert_array_equal(wheel[0], [255, 0, 0])  # red
    np.testing.assert_array_equal(wheel[15], [255, 255, 0])  # yellow
    np.testing.assert_array_equal(wheel[21], [0, 255, 0])  # green
    np.testing.assert_array_equal(wheel[25], [0, 255, 255])  # cyan
    np.testing.assert_array_equal(wheel[36], [0, 0, 255])  # blue
    np.testing.assert_array_equal(wheel[49], [255, 0, 255])  # magenta


def test_zero_flow_is_white_and_directions_have_their_hues():
    np.testing.assert_array_equal(colour_of(0.0, 0.0, max_magnitude=1.0), [255, 255, 255])
    right, left = colour_of(1, 0, 1.0), colour_of(-1, 0, 1.0)
    down, up = colour_of(0, 1, 1.0), colour_of(0, -1, 1.0)  # image y points down
    assert right[0] == 255 and right[1] < 10 and right[2] < 10  # red
    assert left[0] < 10 and left[1] > 100 and left[2] == 255  # cyan-blue
    assert down[0] == 255 and down[1] > 180 and down[2] == 0  # orange-yellow
    assert up[2] == 255 and up[1] == 0 and 50 < up[0] < 200  # blue-violet
    # opposite directions are far apart on the wheel
    assert np.abs(right - left).sum() > 400 and np.abs(up - down).sum() > 400


def test_magnitude_sets_saturation_and_fixed_max_keeps_colours_comparable():
    half, full = colour_of(0.5, 0, 1.0), colour_of(1.0, 0, 1.0)
    assert half[0] == 255 and 120 < half[1] < 135  # halfway to white
    assert full[1] < 10
    # a field's own maximum: every field's longest vector is fully saturated
    np.testing.assert_array_equal(colour_of(0.01, 0), colour_of(100, 0))
    # beyond a fixed maximum: the saturated colour, darkened
    beyond = colour_of(3.0, 0, 1.0)
    assert beyond[0] == pytest.approx(0.75 * 255, abs=1) and beyond[1] < 10


def test_invalid_and_non_finite_pixels_are_black():
    flow = np.zeros((4, 6, 2), np.float32)
    flow[0, 0] = np.nan
    valid = np.ones((4, 6), bool)
    valid[1, 1] = False
    rgb = flow_to_rgb(flow, 1.0, valid)
    assert rgb.shape == (4, 6, 3) and rgb.dtype == np.uint8
    assert (rgb[0, 0] == 0).all() and (rgb[1, 1] == 0).all() and (rgb[2, 2] == 255).all()
    as_tensor = flow_rgb_tensor(torch.from_numpy(flow), 1.0, torch.from_numpy(valid))
    assert as_tensor.shape == (4, 6, 3) and float(as_tensor.max()) == 1.0
    with pytest.raises(ValueError):
        flow_to_rgb(np.zeros((2, 4, 6), np.float32))


def test_quiver_draws_arrows_over_the_image():
    h, w = 40, 60
    flow = np.zeros((h, w, 2), np.float32)
    flow[..., 0] = 6.0  # everything moves right
    flow[:, : w // 2] = 0.0  # ... except the left half
    image = np.zeros((h, w, 3), np.float32)
    out = flow_quiver(flow, image, step=10, color=(255, 255, 255))
    assert out.shape == (h, w, 3) and out.dtype == np.uint8
    drawn = out.max(-1) > 0
    assert not drawn[:, : w // 2 - 1].any()  # zero vectors are skipped
    assert drawn[5, 35:41].all()  # the arrow from (35.5, 5.5) to (41.5, 5.5)
    coloured = flow_quiver(flow, None, step=10)
    assert (coloured[5, 36] != 255).any() and (coloured[0, 0] == 255).all()  # wheel colour on white
    with pytest.raises(ValueError):
        flow_quiver(flow, np.zeros((h + 1, w, 3), np.uint8))
