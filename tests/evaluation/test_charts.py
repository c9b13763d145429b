"""The SVG line chart shared by the report and the motion evaluation."""
from __future__ import annotations

import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import re
from xml.etree import ElementTree

from pidg.evaluation.charts import svg_chart


def test_a_chart_without_points_is_an_svg_that_says_why():
    svg = svg_chart({"a": []}, "minutes", "PSNR", empty_note="the runs have no TensorBoard scalars")
    assert ElementTree.fromstring(svg).tag.endswith("svg") and "no TensorBoard scalars" in svg and "polyline" not in svg


def test_the_chart_maps_its_extremes_to_the_plot_corners():
    svg = svg_chart({"a": [(0.0, 10.0), (2.0, 30.0)]}, "minutes", "PSNR", width=500, height=200)
    (points,) = re.findall(r'points="([^"]+)"', svg)
    (x0, y0), (x1, y1) = [tuple(map(float, p.split(","))) for p in points.split()]
    assert (x0, y1) == (56.0, 12.0) and (x1, y0) == (500 - 290, 200 - 40)  # left/bottom and right/top of the plot
