"""The SVG line chart shared by the report and the motion evaluation."""
from __future__ import annotations

import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import re
from xml.etree import ElementTree

from pidg.evaluation.charts import svg_chart
from pidg.evaluation.evaluate import psnr_over_time_chart


def test_a_chart_without_points_is_an_svg_that_says_why():
    svg = svg_chart({"a": []}, "minutes", "PSNR", empty_note="the runs have no TensorBoard scalars")
    assert ElementTree.fromstring(svg).tag.endswith("svg") and "no TensorBoard scalars" in svg and "polyline" not in svg


def test_the_chart_maps_its_extremes_to_the_plot_corners():
    svg = svg_chart({"a": [(0.0, 10.0), (2.0, 30.0)]}, "minutes", "PSNR", width=500, height=200)
    (points,) = re.findall(r'points="([^"]+)"', svg)
    (x0, y0), (x1, y1) = [tuple(map(float, p.split(","))) for p in points.split()]
    assert (x0, y1) == (56.0, 12.0) and (x1, y0) == (500 - 290, 200 - 40)  # left/bottom and right/top of the plot


def test_the_psnr_over_time_chart_draws_the_scored_views_in_time_order():
    views = [{"view": "b", "time": 0.5, "psnr": 30.0}, {"view": "a", "time": 0.0, "psnr": 20.0},
             {"view": "c", "time": 1.0, "psnr": float("nan")}, {"view": "d", "time": 0.25, "psnr": 40.0}]
    svg = psnr_over_time_chart(views)
    (points,) = re.findall(r'points="([^"]+)"', svg)
    xy = [tuple(map(float, p.split(","))) for p in points.split()]
    assert len(xy) == 3 and [x for x, _ in xy] == sorted(x for x, _ in xy)  # the NaN view left out, time order
    # highest PSNR (t = 0.25) at the top of the plot, lowest (t = 0) at its bottom
    assert xy[1][1] == min(y for _, y in xy) and xy[0][1] == max(y for _, y in xy)
    assert "no view was scored" in psnr_over_time_chart([{"view": "x", "time": 0.0, "psnr": None}])
