"""Line charts as inline SVG text, drawn by the browser.

The report's plots used to be matplotlib figures saved as PNG: saving them took seconds of a run that aims
at real time, and importing matplotlib a quarter of a second more. A line chart is a few hundred points per
series, which SVG draws as well as any raster and which plain string building writes in milliseconds.

A chart is a grid of :class:`Panel` sharing one x axis: each panel holds :class:`Series` (solid, dashed or
dotted, with or without dots, broken wherever a value is NaN), horizontal :class:`ReferenceLine`\\ s and
optionally a :class:`Strip` of per-x category colours; the chart has one legend of :class:`LegendEntry`.
Coordinates are written with one decimal in user units (the viewBox is :data:`WIDTH` wide), every text is
escaped, and the ``<svg>`` scales to its container's width.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

#: Width of every chart's viewBox (user units, about the pixels of a report column).
WIDTH = 1000
#: Font size of tick labels and legends; titles and axis labels are a little larger.
FONT = 12
#: Stroke dash patterns by line style.
DASHES = {"solid": None, "dashed": "6 4", "dotted": "1.5 3"}

#: Space around each panel's plot area: tick labels and the y label on the left, the x tick labels below.
_LEFT, _RIGHT, _TICKS_BELOW, _GAP_BELOW, _TITLE, _GAP_ABOVE = 62, 14, 20, 10, 18, 8
#: Height of one legend line and of the x label under the chart.
_LEGEND_LINE, _X_LABEL = 20, 26


@dataclass(frozen=True)
class Series:
    """A line over ``x``; NaN in ``y`` (or ``x``) breaks it. ``style``: a key of :data:`DASHES`."""

    x: np.ndarray
    y: np.ndarray
    colour: str
    style: str = "solid"
    width: float = 1.2
    dots: bool = False
    opacity: float = 1.0


@dataclass(frozen=True)
class ReferenceLine:
    """A horizontal line across a panel at ``y``, labelled at its right end when ``label`` is given."""

    y: float
    colour: str
    label: str | None = None
    style: str = "dashed"


@dataclass(frozen=True)
class Strip:
    """One coloured cell per ``x`` (``colours[k]`` centred on ``x[k]``, ``step`` wide): categories over x."""

    x: np.ndarray
    colours: Sequence[str]
    step: float = 1.0


@dataclass(frozen=True)
class Panel:
    """One plot area. ``height``: its height in user units; ``y_min`` forces the y axis to start there."""

    series: Sequence[Series] = ()
    title: str = ""
    y_label: str = ""
    reference_lines: Sequence[ReferenceLine] = ()
    strip: Strip | None = None
    height: float = 160.0
    y_min: float | None = None


@dataclass(frozen=True)
class LegendEntry:
    """``style``: a key of :data:`DASHES` for a line, or ``"box"`` for a filled square (a strip's colour)."""

    label: str
    colour: str
    style: str = "solid"


@dataclass(frozen=True)
class _Box:
    """A panel's plot area in user units and the data range it shows."""

    left: float
    top: float
    width: float
    height: float
    x_range: tuple[float, float]
    y_range: tuple[float, float] = field(default=(0.0, 1.0))

    def px(self, x):
        low, high = self.x_range
        return self.left + (np.asarray(x, dtype=float) - low) / (high - low) * self.width

    def py(self, y):
        low, high = self.y_range
        return self.top + self.height - (np.asarray(y, dtype=float) - low) / (high - low) * self.height


def nice_ticks(low: float, high: float, count: int = 5) -> np.ndarray:
    """About ``count`` evenly spaced round numbers (steps of 1, 2 or 5 times a power of ten) from at or below
    ``low`` to at or above ``high``, so that an axis ending at the first and last tick shows all the data.
    An empty or non-finite range is widened around its value (or taken as 0..1)."""
    if not (math.isfinite(low) and math.isfinite(high)):
        low, high = 0.0, 1.0
    if high < low:
        low, high = high, low
    if high - low < 1e-12:
        half = max(abs(low) * 0.1, 0.5)
        low, high = low - half, high + half
    raw = (high - low) / max(count - 1, 1)
    power = 10.0 ** math.floor(math.log10(raw))
    step = power * next(m for m in (1, 2, 2.5, 5, 10) if m * power >= raw * (1 - 1e-9))
    first, last = math.floor(low / step + 1e-9), math.ceil(high / step - 1e-9)
    return np.arange(first, last + 1) * step


def tick_label(value: float, step: float) -> str:
    """``value`` with as many decimals as the tick ``step`` needs (never "-0")."""
    decimals = next((d for d in range(7) if abs(step * 10 ** d - round(step * 10 ** d)) < 1e-6 * 10 ** d), 6)
    text = f"{value:.{decimals}f}"
    return "0" if float(text) == 0 else text.replace("-", "−")


def with_gaps(frames: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``frames (F,)`` and ``values (F, ...)`` with a NaN row after each frame followed by a gap (a step longer
    than the smallest), so that a plotted line breaks where frames are missing instead of bridging them."""
    frames, values = np.asarray(frames), np.asarray(values, dtype=float)
    if len(frames) < 2:
        return frames, values
    steps = np.diff(frames)
    after = np.flatnonzero(steps > steps.min()) + 1
    return (np.insert(frames.astype(float), after, frames[after - 1] + steps.min()),
            np.insert(values, after, np.nan, axis=0))


def runs(x: np.ndarray, y: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The unbroken pieces of a line: maximal runs of points whose ``x`` and ``y`` are both finite."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    finite = np.isfinite(x) & np.isfinite(y)
    edges = np.flatnonzero(np.diff(np.concatenate(([0], finite.astype(np.int8), [0]))))
    return [(x[start:stop], y[start:stop]) for start, stop in zip(edges[::2], edges[1::2], strict=True)]


def _n(value: float) -> str:
    """A coordinate in one decimal, trailing zeros dropped: 12.0 -> "12", -0.04 -> "0"."""
    text = f"{value:.1f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _points(xs: np.ndarray, ys: np.ndarray) -> str:
    return " ".join(f"{_n(x)},{_n(y)}" for x, y in zip(xs, ys, strict=True))


def _stroke(colour: str, style: str, width: float, opacity: float = 1.0) -> str:
    dash = DASHES[style]
    return (f"fill='none' stroke='{html.escape(colour)}' stroke-width='{width:g}'"
            + (f" stroke-dasharray='{dash}'" if dash else "")
            + (f" stroke-opacity='{opacity:g}'" if opacity < 1 else ""))


def _text(x: float, y: float, text: str, *, anchor: str = "start", size: int = FONT, extra: str = "") -> str:
    return (f"<text x='{_n(x)}' y='{_n(y)}' font-size='{size}' text-anchor='{anchor}'{extra}>"
            f"{html.escape(text)}</text>")


def _x_extent(panels: Sequence[Panel]) -> tuple[float, float]:
    lows, highs = [], []
    for panel in panels:
        for series in panel.series:
            x = np.asarray(series.x, dtype=float)
            x = x[np.isfinite(x)]
            if len(x):
                lows.append(x.min())
                highs.append(x.max())
        if panel.strip is not None and len(panel.strip.x):
            lows.append(float(np.min(panel.strip.x)) - panel.strip.step / 2)
            highs.append(float(np.max(panel.strip.x)) + panel.strip.step / 2)
    if not lows:
        return 0.0, 1.0
    low, high = min(lows), max(highs)
    return (low - 0.5, high + 0.5) if high - low < 1e-12 else (low, high)


def _y_ticks(panel: Panel) -> np.ndarray:
    values = [np.asarray(s.y, dtype=float).ravel() for s in panel.series]
    values.append(np.array([line.y for line in panel.reference_lines] + ([panel.y_min] if panel.y_min is not None
                                                                         else []), dtype=float))
    values = np.concatenate(values)
    values = values[np.isfinite(values)]
    if not len(values):
        return nice_ticks(0.0, 1.0)
    low = min(values.min(), panel.y_min) if panel.y_min is not None else values.min()
    return nice_ticks(float(low), float(values.max()))


def _legend(entries: Sequence[LegendEntry], top: float) -> tuple[str, float]:
    """The legend's SVG from ``top``, wrapped to the chart's width, and its height."""
    parts, x, y = [], float(_LEFT), top + _LEGEND_LINE / 2
    for entry in entries:
        width = 30 + 0.6 * FONT * len(entry.label) + 18
        if x + width > WIDTH - _RIGHT and x > _LEFT:
            x, y = float(_LEFT), y + _LEGEND_LINE
        if entry.style == "box":
            parts.append(f"<rect x='{_n(x + 6)}' y='{_n(y - 6)}' width='12' height='12' "
                         f"fill='{html.escape(entry.colour)}'/>")
        else:
            parts.append(f"<line x1='{_n(x)}' y1='{_n(y)}' x2='{_n(x + 24)}' y2='{_n(y)}' "
                         f"{_stroke(entry.colour, entry.style, 2)}/>")
        parts.append(_text(x + 30, y + 4, entry.label))
        x += width
    return "".join(parts), (y + _LEGEND_LINE / 2 - top) if entries else 0.0


def _panel(panel: Panel, box: _Box, x_ticks: np.ndarray, x_step: float, tick_labels: bool) -> str:
    parts = []
    if panel.strip is None:
        y_ticks = _y_ticks(panel)
        box = _Box(box.left, box.top, box.width, box.height, box.x_range, (float(y_ticks[0]), float(y_ticks[-1])))
        y_step = float(y_ticks[1] - y_ticks[0]) if len(y_ticks) > 1 else 1.0
        for tick in y_ticks:
            y = float(box.py(tick))
            parts.append(f"<line x1='{_n(box.left)}' y1='{_n(y)}' x2='{_n(box.left + box.width)}' y2='{_n(y)}' "
                         "stroke='#e4e4e4'/>")
            parts.append(_text(box.left - 5, y + 4, tick_label(tick, y_step), anchor="end"))
    for tick in x_ticks:
        x = float(box.px(tick))
        if panel.strip is None:
            parts.append(f"<line x1='{_n(x)}' y1='{_n(box.top)}' x2='{_n(x)}' y2='{_n(box.top + box.height)}' "
                         "stroke='#e4e4e4'/>")
        if tick_labels:
            parts.append(_text(x, box.top + box.height + 15, tick_label(tick, x_step), anchor="middle"))
    if panel.strip is not None:
        parts.append(_strip(panel.strip, box))
    for line in panel.reference_lines:
        y = float(box.py(line.y))
        parts.append(f"<line x1='{_n(box.left)}' y1='{_n(y)}' x2='{_n(box.left + box.width)}' y2='{_n(y)}' "
                     f"{_stroke(line.colour, line.style, 1)}/>")
        if line.label:  # above the line, or below it when the line runs along the panel's top
            label_y = y - 4 if y - box.top > 14 else y + 13
            parts.append(_text(box.left + box.width - 4, label_y, line.label, anchor="end", size=FONT - 1,
                               extra=f" fill='{html.escape(line.colour)}'"))
    for series in panel.series:
        parts.append(_series(series, box))
    parts.append(f"<rect x='{_n(box.left)}' y='{_n(box.top)}' width='{_n(box.width)}' height='{_n(box.height)}' "
                 "fill='none' stroke='#888'/>")
    if panel.title:
        parts.append(_text(box.left + box.width / 2, box.top - 6, panel.title, anchor="middle", size=FONT + 1))
    if panel.y_label:
        middle = box.top + box.height / 2
        parts.append(_text(box.left - 48, middle, panel.y_label, anchor="middle",
                           extra=f" transform='rotate(-90 {_n(box.left - 48)} {_n(middle)})'"))
    return "".join(parts)


def _series(series: Series, box: _Box) -> str:
    pieces = runs(series.x, series.y)
    pixels = [(box.px(x), box.py(y)) for x, y in pieces]
    lines = "".join(f"<polyline points='{_points(xs, ys)}'/>" for xs, ys in pixels if len(xs) > 1)
    text = f"<g {_stroke(series.colour, series.style, series.width, series.opacity)}>{lines}</g>" if lines else ""
    if series.dots:
        # Zero-length strokes with round caps: one path of dots instead of a <circle> per point.
        dots = "".join(f"M{_n(x)} {_n(y)}h0" for xs, ys in pixels for x, y in zip(xs, ys, strict=True))
        text += (f"<path d='{dots}' stroke='{html.escape(series.colour)}' stroke-width='{series.width + 2.5:g}' "
                 "stroke-linecap='round' fill='none'/>")
    return text


def _strip(strip: Strip, box: _Box) -> str:
    """One rectangle per run of neighbouring cells of one colour, clipped to the panel."""
    order = np.argsort(np.asarray(strip.x, dtype=float))
    x = np.asarray(strip.x, dtype=float)[order]
    colours = [strip.colours[k] for k in order]
    low, high = box.x_range
    parts, start = [], 0
    for k in range(1, len(x) + 1):
        if k < len(x) and colours[k] == colours[start] and abs(x[k] - x[k - 1] - strip.step) < 1e-9:
            continue
        left = max(x[start] - strip.step / 2, low)
        right = min(x[k - 1] + strip.step / 2, high)
        if right > left:
            x0, x1 = float(box.px(left)), float(box.px(right))
            parts.append(f"<rect x='{_n(x0)}' y='{_n(box.top)}' width='{_n(x1 - x0)}' height='{_n(box.height)}' "
                         f"fill='{html.escape(colours[start])}'/>")
        start = k
    return "".join(parts)


def line_chart(panels: Sequence[Panel], *, columns: int = 1, x_label: str = "", y_label: str = "",
               legend: Sequence[LegendEntry] = (), legend_below: bool = False, description: str = "") -> str:
    """An ``<svg>`` of ``panels`` laid out in rows of ``columns``, sharing one x axis (its tick labels under
    the lowest panel of each column), with ``legend`` above the panels (or below them with
    ``legend_below``), ``x_label`` under the chart and ``y_label`` along its left side (besides each panel's
    own). ``description`` is the chart's accessible name (``aria-label``)."""
    if not panels:
        raise ValueError("a chart needs at least one panel")
    x_range = _x_extent(panels)
    x_ticks = nice_ticks(*x_range, count=max(3, 9 // columns + 1))
    x_step = float(x_ticks[1] - x_ticks[0]) if len(x_ticks) > 1 else 1.0
    x_ticks = x_ticks[(x_ticks >= x_range[0] - 1e-9) & (x_ticks <= x_range[1] + 1e-9)]
    outer_left = 24 if y_label else 0
    cell_width = (WIDTH - outer_left) / columns
    legend_svg, legend_height = _legend(legend, 0.0)
    top = 4.0 if legend_below else 4.0 + legend_height
    parts = []
    rows = [panels[start:start + columns] for start in range(0, len(panels), columns)]
    for r, row in enumerate(rows):
        above = _TITLE if any(panel.title for panel in row) else _GAP_ABOVE
        labelled = [r * columns + c + columns >= len(panels) for c in range(len(row))]
        below = _TICKS_BELOW if any(labelled) else _GAP_BELOW
        height = max(panel.height for panel in row)
        for c, panel in enumerate(row):
            box = _Box(outer_left + c * cell_width + _LEFT, top + above, cell_width - _LEFT - _RIGHT, height,
                       x_range)
            parts.append(_panel(panel, box, x_ticks, x_step, labelled[c]))
        top += above + height + below
    if x_label:
        parts.append(_text(outer_left + _LEFT + (WIDTH - outer_left - _LEFT - _RIGHT) / 2, top + 10, x_label,
                           anchor="middle", size=FONT + 1))
        top += _X_LABEL
    if y_label:
        middle = top / 2
        parts.append(_text(14, middle, y_label, anchor="middle", size=FONT + 1,
                           extra=f" transform='rotate(-90 14 {_n(middle)})'"))
    if legend_below:
        legend_svg, legend_height = _legend(legend, top)
    else:
        legend_svg = f"<g>{legend_svg}</g>"
    parts.append(legend_svg)
    total = top + (legend_height if legend_below else 0) + 4
    return (f"<svg xmlns='http://www.w3.org/2000/svg' class='plot' viewBox='0 0 {WIDTH} {_n(total)}' width='100%' "
            f"role='img' aria-label='{html.escape(description)}' font-family='sans-serif' fill='#222'>"
            + "".join(parts) + "</svg>")
