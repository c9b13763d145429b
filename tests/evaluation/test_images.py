"""Saved pictures name their panels: a title strip above side-by-side panels, each title kept inside its panel."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import pytest
import torch

from pidg.evaluation.images import TITLE_STRIP_PX, with_titles


def test_titles_go_in_a_strip_above_the_unchanged_panels():
    image = torch.rand(20, 3 * 60, 3, generator=torch.Generator().manual_seed(0))
    titled = with_titles(image, ["render", "", "error, 0-9.8 px"])
    assert tuple(titled.shape) == (20 + TITLE_STRIP_PX, 180, 3) and TITLE_STRIP_PX % 2 == 0  # video frames stay even
    torch.testing.assert_close(titled[TITLE_STRIP_PX:], image, rtol=0, atol=0)
    strip = titled[:TITLE_STRIP_PX]
    first, empty, last = strip.split(60, dim=1)
    assert float(first.max()) > 0.9 and float(last.max()) > 0.9  # white text
    assert float(empty.max()) == 0.0  # an empty title leaves its panel's strip black


def test_a_long_title_stops_at_its_panel_edge():
    titled = with_titles(torch.zeros(4, 2 * 30, 3), ["a title far too long for a thirty-pixel panel", ""])
    left, right = titled[:TITLE_STRIP_PX].split(30, dim=1)
    assert float(left.max()) > 0.9 and float(right.max()) == 0.0


def test_titles_must_divide_the_image_into_equal_panels():
    with pytest.raises(ValueError, match="61 px wide cannot hold 2 equal panels"):
        with_titles(torch.zeros(4, 61, 3), ["a", "b"])
    with pytest.raises(ValueError, match="cannot hold 0 equal panels"):
        with_titles(torch.zeros(4, 60, 3), [])
