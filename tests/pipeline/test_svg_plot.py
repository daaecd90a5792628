import re
from xml.etree import ElementTree

import numpy as np
import pytest

from pipeline.report.svg_plot import (
    LegendEntry,
    Panel,
    ReferenceLine,
    Series,
    Strip,
    line_chart,
    nice_ticks,
    runs,
    tick_label,
    with_gaps,
)

SVG = "{http://www.w3.org/2000/svg}"


def _chart(**kwargs) -> ElementTree.Element:
    x = np.arange(10.0)
    y = np.where(x == 4, np.nan, np.sin(x))
    panels = [Panel([Series(x, y, "#1f77b4", dots=True), Series(x, 2 * x, "#d62728", "dashed")], y_label="a (m)",
                    reference_lines=[ReferenceLine(15.0, "#d62728", "limit")]),
              Panel(strip=Strip(x, ["#2ca02c"] * 5 + ["#d62728"] * 5), height=30)]
    return ElementTree.fromstring(line_chart(panels, x_label="frame", legend=[LegendEntry("sin", "#1f77b4")],
                                             **kwargs))


def test_a_chart_is_well_formed_svg_that_scales_to_its_container():
    root = _chart()
    assert root.tag == SVG + "svg" and root.get("width") == "100%"
    width, height = map(float, root.get("viewBox").split()[2:])
    assert width == 1000 and 200 < height < 400
    texts = [element.text for element in root.iter(SVG + "text")]
    assert {"frame", "a (m)", "sin", "limit"} <= set(texts)


def test_a_series_with_a_gap_becomes_two_polylines_and_keeps_its_style():
    root = _chart()
    groups = [g for g in root.iter(SVG + "g") if g.get("stroke") == "#1f77b4"]
    assert len(groups) == 1 and len(groups[0].findall(SVG + "polyline")) == 2
    points = [len(line.get("points").split()) for line in groups[0].findall(SVG + "polyline")]
    assert points == [4, 5]                                         # frames 0-3 and 5-9
    dashed = [g for g in root.iter(SVG + "g") if g.get("stroke") == "#d62728"]
    assert dashed[0].get("stroke-dasharray") == "6 4"
    dots = [p for p in root.iter(SVG + "path") if p.get("stroke") == "#1f77b4"][0].get("d")
    assert dots.count("h0") == 9                                    # one dot per finite point
    assert re.fullmatch(r"[-\d. ,]+", groups[0].find(SVG + "polyline").get("points"))
    assert all(len(number.split(".")[-1]) <= 1 or "." not in number   # one decimal at most
               for number in re.split(r"[ ,]", groups[0].find(SVG + "polyline").get("points")))


def test_the_strip_merges_neighbouring_cells_of_one_colour():
    rects = [r for r in _chart().iter(SVG + "rect") if r.get("fill") in ("#2ca02c", "#d62728")]
    assert [r.get("fill") for r in rects] == ["#2ca02c", "#d62728"]


def test_user_text_is_escaped():
    text = line_chart([Panel([Series(np.arange(3), np.arange(3), "red")], title="<b>&'x'")],
                      legend=[LegendEntry("a<script>", "red")], description="\"quoted\"")
    root = ElementTree.fromstring(text)
    assert "<script>" not in text and "<b>" not in text
    assert "<b>&'x'" in [t.text for t in root.iter(SVG + "text")] and root.get("aria-label") == '"quoted"'


@pytest.mark.parametrize("low, high", [(0.0, 1.0), (-3.2, 17.9), (3150.7, 4012.2), (0.013, 0.0171), (5.0, 5.0),
                                       (-120.0, -119.0), (0.0, 111.0)])
def test_nice_ticks_cover_the_range_in_round_steps(low, high):
    ticks = nice_ticks(low, high)
    assert ticks[0] <= low and ticks[-1] >= high and 3 <= len(ticks) <= 9
    steps = np.diff(ticks)
    assert np.allclose(steps, steps[0])
    mantissa = steps[0] / 10 ** np.floor(np.log10(steps[0]))
    assert any(np.isclose(mantissa, m) for m in (1, 2, 2.5, 5))
    labels = [tick_label(t, steps[0]) for t in ticks]
    assert len(set(labels)) == len(labels)                          # enough decimals to tell ticks apart


def test_ticks_and_labels_of_odd_ranges():
    assert nice_ticks(float("nan"), 1.0).tolist() == nice_ticks(0.0, 1.0).tolist()
    assert tick_label(-0.0001, 0.5) == "0" and tick_label(0.25, 0.25) == "0.25" and tick_label(-2, 1) == "−2"


def test_runs_split_at_non_finite_points():
    pieces = runs(np.arange(6.0), np.array([np.nan, 1, 2, np.inf, 4, np.nan]))
    assert [x.tolist() for x, _ in pieces] == [[1, 2], [4]]
    assert runs(np.arange(2.0), np.full(2, np.nan)) == []


def test_plotted_lines_break_where_frames_are_missing():
    frames, values = with_gaps(np.array([0, 2, 4, 8, 10]), np.arange(10.0).reshape(5, 2))
    assert frames.tolist() == [0, 2, 4, 6, 8, 10]                  # the step is 2: a gap after frame 4
    assert np.isnan(values[3]).all() and values[[0, 1, 2, 4, 5]].tolist() == np.arange(10.0).reshape(5, 2).tolist()
    assert with_gaps(np.array([3]), np.ones(1))[0].tolist() == [3]


def test_a_chart_needs_a_panel():
    with pytest.raises(ValueError, match="at least one panel"):
        line_chart([])
