"""Plots drawn with OpenCV: the primitives (a canvas, axes with ticks, text, legends) and three kinds of
figure, `bar_line_figure` (bars with a line on a second axis), `scatter_figure` (labelled points, e.g. a
t-SNE) and `curves_figure` (lines over frames; `curves_image` for a panel of a larger figure). Used by
the figures and checkpoints stages. Unusable data is a FigureError naming it. A helper without a stage
number.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch

from .errors import KgnavbenchError
from .render import type_colour


class FigureError(KgnavbenchError, ValueError):
    """A figure cannot be drawn: a missing or unreadable run, or unusable data."""


FIGURE_SIZE = (1000, 600)  # width, height in pixels
FONT = cv2.FONT_HERSHEY_SIMPLEX
INK = (30, 30, 30)
GRID = (225, 225, 225)
# BGR: tab10's blue, orange, green, red, purple, brown, pink, grey, olive, cyan
PALETTE = (
    (180, 119, 31),
    (14, 127, 255),
    (44, 160, 44),
    (40, 39, 214),
    (189, 103, 148),
    (75, 86, 140),
    (194, 119, 227),
    (127, 127, 127),
    (34, 189, 188),
    (207, 190, 23),
)


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """Round tick values covering [lo, hi] in about n steps (1, 2, 2.5 or 5 times a power of ten)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi = 0.0, 1.0
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5, hi + 0.5
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw * (1 - 1e-9))
    first = math.floor(lo / step + 1e-9) * step
    count = math.ceil((hi - first) / step - 1e-9)
    return [first + i * step for i in range(count + 1)]


def _fmt(v: float) -> str:
    """A tick label: 1500000 -> 1.5M, 20000 -> 20k, 0.30000000000000004 -> 0.3."""
    for limit, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(v) >= limit:
            return f"{round(v / limit, 3):g}{suffix}"
    return f"{round(v, 6):g}"


def draw_text(img, text: str, org, scale=0.5, colour=INK, thickness=1, align="left", valign="baseline"):
    """putText with horizontal (left/centre/right) and vertical (top/middle/baseline) alignment."""
    (w, h), _ = cv2.getTextSize(text, FONT, scale, thickness)
    x, y = org
    x -= {"left": 0, "centre": w // 2, "right": w}[align]
    y += {"top": h, "middle": h // 2, "baseline": 0}[valign]
    cv2.putText(img, text, (int(x), int(y)), FONT, scale, colour, thickness, cv2.LINE_AA)
    return w, h


def _vertical_text(img, text: str, centre, scale=0.55, colour=INK) -> None:
    """Text read bottom to top (a y-axis label): drawn on its own strip, rotated, pasted."""
    (w, h), base = cv2.getTextSize(text, FONT, scale, 1)
    strip = np.full((h + base + 4, w + 4, 3), 255, np.uint8)
    cv2.putText(strip, text, (2, h + 2), FONT, scale, colour, 1, cv2.LINE_AA)
    strip = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
    sh, sw = strip.shape[:2]
    x0, y0 = int(centre[0] - sw / 2), int(centre[1] - sh / 2)
    x0, y0 = max(x0, 0), max(y0, 0)
    region = img[y0 : y0 + sh, x0 : x0 + sw]
    np.minimum(region, strip[: region.shape[0], : region.shape[1]], out=region)


def wrap_text(text: str, width: int, scale: float) -> list[str]:
    """Words of `text` in lines no wider than `width` pixels (a long word gets a line of its own)."""
    lines: list[str] = []
    for word in text.split():
        trial = f"{lines[-1]} {word}" if lines else word
        if lines and cv2.getTextSize(trial, FONT, scale, 1)[0][0] <= width:
            lines[-1] = trial
        else:
            lines.append(word)
    return lines or [""]


class Axes:
    """A plot area inside margins, mapping data to pixels; y ticks on the left (and optionally right)."""

    def __init__(self, img, left, top, right, bottom, xlim, ylim):
        self.img, self.left, self.top, self.right, self.bottom = img, left, top, right, bottom
        self.xlim, self.ylim = xlim, ylim

    def px(self, x: float, y: float, ylim=None) -> tuple[int, int]:
        (x0, x1), (y0, y1) = self.xlim, ylim or self.ylim
        u = self.left + (x - x0) / ((x1 - x0) or 1) * (self.right - self.left)
        v = self.bottom - (y - y0) / ((y1 - y0) or 1) * (self.bottom - self.top)
        return int(round(u)), int(round(v))

    def y_axis(self, ticks, label: str, side: str = "left", colour=INK, grid: bool = True) -> None:
        x = self.left if side == "left" else self.right
        ylim = (ticks[0], ticks[-1])
        for t in ticks:
            _, y = self.px(0, t, ylim)
            if grid:
                cv2.line(self.img, (self.left, y), (self.right, y), GRID, 1)
            cv2.line(
                self.img, (x - 5 if side == "left" else x, y), (x if side == "left" else x + 5, y), colour, 1
            )
            offset = -9 if side == "left" else 9
            draw_text(
                self.img,
                _fmt(t),
                (x + offset, y),
                0.45,
                colour,
                align="right" if side == "left" else "left",
                valign="middle",
            )
        widest = max(cv2.getTextSize(_fmt(t), FONT, 0.45, 1)[0][0] for t in ticks)
        lx = x - widest - 28 if side == "left" else x + widest + 28
        _vertical_text(self.img, label, (lx, (self.top + self.bottom) / 2), 0.55, colour)

    def x_ticks(self, ticks, label: str) -> None:
        for t in ticks:
            x, _ = self.px(t, self.ylim[0])
            cv2.line(self.img, (x, self.top), (x, self.bottom), GRID, 1)
            cv2.line(self.img, (x, self.bottom), (x, self.bottom + 5), INK, 1)
            draw_text(self.img, _fmt(t), (x, self.bottom + 10), 0.45, align="centre", valign="top")
        draw_text(self.img, label, ((self.left + self.right) // 2, self.bottom + 48), 0.55, align="centre")

    def frame(self) -> None:
        cv2.rectangle(self.img, (self.left, self.top), (self.right, self.bottom), INK, 1)


def new_canvas(title: str, size) -> np.ndarray:
    width, height = size
    img = np.full((height, width, 3), 255, np.uint8)
    draw_text(img, title, (width // 2, 30), 0.75, INK, 2, align="centre")
    return img


def draw_legend(img, entries: list[tuple[str, tuple, str]], right: int, top: int) -> None:
    """Entries (label, colour, "bar" | "line") in a row ending at x=right, at height top."""
    x = right
    for label, colour, kind in reversed(entries):
        w = cv2.getTextSize(label, FONT, 0.5, 1)[0][0]
        x -= w
        draw_text(img, label, (x, top), 0.5, valign="middle")
        x -= 30
        if kind == "bar":
            cv2.rectangle(img, (x, top - 7), (x + 22, top + 7), colour, -1)
        else:
            cv2.line(img, (x, top), (x + 22, top), colour, 2, cv2.LINE_AA)
            cv2.circle(img, (x + 11, top), 4, colour, -1, cv2.LINE_AA)
        x -= 24


def write_png(path, img: np.ndarray) -> Path:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FigureError(f"cannot create {path.parent}: {e.strerror or e}") from e
    if not cv2.imwrite(str(path), img):
        raise FigureError(f"could not write {path} (OpenCV writes .png, .jpg and a few more)")
    return path


def bar_line_figure(
    labels: list[str],
    bars: list[float],
    line: list[float],
    path,
    title: str,
    bar_label: str,
    line_label: str,
    size=FIGURE_SIZE,
) -> Path:
    """Bars (left axis) and a line with markers (right axis), one slot per label; the paper's figure of
    collisions per episode (bars) and the last-view-shows-target rate (line) per method. Each slot's
    values are written under its label in the colours of their series. A NaN value draws nothing."""
    if not labels or not len(labels) == len(bars) == len(line):
        raise FigureError(f"{len(labels)} labels, {len(bars)} bars and {len(line)} line values must match")
    img = new_canvas(title, size)
    width, height = size
    finite = [v for v in bars if math.isfinite(v)] or [1.0]
    bar_ticks = nice_ticks(0.0, max(max(finite), 0.0) * 1.05)
    finite = [v for v in line if math.isfinite(v)] or [1.0]
    line_ticks = nice_ticks(min(0.0, min(finite)), max(finite) * 1.05)
    left, right = 100, width - 100
    slot = (right - left) / len(labels)
    # every word of each name (the control row's takes 4 lines): the plot gives up the room they need
    wrapped = [wrap_text(label, int(slot) - 6, 0.45) for label in labels]
    extra = 18 * max(0, max(len(names) for names in wrapped) - 3)
    ax = Axes(img, left, 80, right, height - 110 - extra, (0, len(labels)), (bar_ticks[0], bar_ticks[-1]))
    line_colour = PALETTE[1]
    ax.y_axis(bar_ticks, bar_label, "left")
    ax.y_axis(line_ticks, line_label, "right", line_colour, grid=False)
    points, values = [], []
    for i, (names, b, v) in enumerate(zip(wrapped, bars, line)):
        cx = int(ax.left + (i + 0.5) * slot)
        if math.isfinite(b):
            _, top = ax.px(0, b)
            half = int(slot * 0.3)
            cv2.rectangle(img, (cx - half, top), (cx + half, ax.bottom), PALETTE[0], -1)
        if math.isfinite(v):
            points.append((cx, ax.px(0, v, (line_ticks[0], line_ticks[-1]))[1]))
        for k, text in enumerate(names):
            draw_text(img, text, (cx, ax.bottom + 10 + 18 * k), 0.45, align="centre", valign="top")
        values.append((cx, ax.bottom + 14 + 18 * len(names), b, v))
    if len(points) > 1:
        cv2.polylines(img, [np.array(points, np.int32)], False, line_colour, 2, cv2.LINE_AA)
    for p in points:
        cv2.circle(img, p, 5, line_colour, -1, cv2.LINE_AA)
    # the values under each slot's name, in their series' colours: labels in the plot would collide
    # with the line and the bars wherever the two are close
    for cx, y, b, v in values:
        for k, (value, colour) in enumerate(((b, PALETTE[0]), (v, line_colour))):
            if math.isfinite(value):
                draw_text(
                    img,
                    f"{value:.2f}" if k == 0 else f"{value:.1f}",
                    (cx, y + 17 * k),
                    0.45,
                    colour,
                    align="centre",
                    valign="top",
                )
    ax.frame()
    draw_legend(img, [(bar_label, PALETTE[0], "bar"), (line_label, line_colour, "line")], width - 100, 58)
    return write_png(path, img)


def _overlaps(box, boxes) -> bool:
    return any(box[0] < o[2] and o[0] < box[2] and box[1] < o[3] and o[1] < box[3] for o in boxes)


def _place_label(label: str, p, placed, width: int, height: int):
    """A box for `label` near point p that overlaps no box in `placed`: beside the point first, then in
    eight directions further out; (box, anchor) with anchor the end of a leader line, or None. Where no
    place is free, the label goes right of its point anyway."""
    (w, h), _ = cv2.getTextSize(label, FONT, 0.38, 1)
    candidates = [((p[0] + 8, p[1] - h // 2), None), ((p[0] - 8 - w, p[1] - h // 2), None)]
    for r in (16, 28, 42):
        for dx, dy in ((1, -1), (-1, -1), (1, 1), (-1, 1), (0, -1), (0, 1), (1, 0), (-1, 0)):
            ax, ay = p[0] + dx * r, p[1] + dy * r
            x = ax if dx > 0 else ax - w if dx < 0 else ax - w // 2
            y = ay - h if dy < 0 else ay if dy > 0 else ay - h // 2
            candidates.append(((x, y), (ax, ay)))
    for (x, y), anchor in candidates:
        box = (x, y, x + w, y + h + 2)
        inside = box[0] >= 0 and box[1] >= 40 and box[2] < width and box[3] < height
        if inside and not _overlaps(box, placed):
            return box, anchor
    (x, y), _ = candidates[0]
    return (x, y, x + w, y + h + 2), None


def scatter_figure(points, labels: list[str], path, title: str, size=FIGURE_SIZE) -> Path:
    """Points (n, 2) each with its label written beside it (a t-SNE of object types: the coordinates
    have no units, so no ticks). Labels keep clear of the other labels and points where they can (see
    _place_label)."""
    pts = np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor) else points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) != len(labels) or not len(pts):
        raise FigureError(
            f"scatter_figure needs (n, 2) points and n labels, not {pts.shape} and {len(labels)}"
        )
    img = new_canvas(title, size)
    width, height = size
    lo, hi = pts.min(0), pts.max(0)
    pad = (hi - lo) * 0.08 + 1e-9  # room for the labels of the outermost points
    ax = Axes(
        img,
        40,
        60,
        width - 40,
        height - 30,
        (lo[0] - pad[0], hi[0] + pad[0]),
        (lo[1] - pad[1], hi[1] + pad[1]),
    )
    ax.frame()
    pixels = [ax.px(x, y) for x, y in pts]
    placed = [(x - 6, y - 6, x + 6, y + 6) for x, y in pixels]  # labels must not hide the points either
    for p, label in zip(pixels, labels):
        rgb = type_colour(label)  # object types keep the colours they have in the renders
        cv2.circle(img, p, 5, (rgb[2], rgb[1], rgb[0]), -1, cv2.LINE_AA)
        cv2.circle(img, p, 5, INK, 1, cv2.LINE_AA)
    for p, label in zip(pixels, labels):
        box, anchor = _place_label(label, p, placed, width, height)
        placed.append(box)
        if anchor is not None:  # a label moved away from its point gets a leader line
            cv2.line(img, p, anchor, (170, 170, 170), 1, cv2.LINE_AA)
        draw_text(img, label, (box[0], box[3] - 2), 0.38, (70, 70, 70))
    return write_png(path, img)


def curves_figure(
    series: dict[str, tuple[list[float], list[float]]],
    path,
    title: str,
    xlabel: str,
    ylabel: str,
    size=FIGURE_SIZE,
    x_include: tuple[float, ...] = (),
    y_include: tuple[float, ...] = (),
    marks: dict[str, list[tuple[float, float]]] | None = None,
) -> Path:
    """One line per named series (xs, ys) on shared axes, with a legend; NaN values break a line. The
    axes cover the data and the values of x_include and y_include (0: curves over frames from the start,
    a rate from zero). `marks`: per series name, points drawn as hollow squares in its colour (a
    reference value, e.g. a paper's number)."""
    return write_png(path, curves_image(series, title, xlabel, ylabel, size, x_include, y_include, marks))


def curves_image(
    series: dict[str, tuple[list[float], list[float]]],
    title: str,
    xlabel: str,
    ylabel: str,
    size=FIGURE_SIZE,
    x_include: tuple[float, ...] = (),
    y_include: tuple[float, ...] = (),
    marks: dict[str, list[tuple[float, float]]] | None = None,
    colours: dict[str, int] | None = None,
    thin: frozenset[str] = frozenset(),
    legend_corner: str = "upper left",
) -> np.ndarray:
    """`curves_figure`'s image (BGR), for a figure of several panels. `colours`: a series' index into
    PALETTE (default: its place in `series`); series named in `thin` are drawn 1 px wide and left out of
    the legend (one seed's curve beside its row's mean). `legend_corner`: "upper left" or "lower right"
    inside the plot, whichever the curves leave free."""
    if legend_corner not in ("upper left", "lower right"):
        raise FigureError(f"legend_corner must be 'upper left' or 'lower right', not {legend_corner!r}")
    marks, colours = marks or {}, colours or {}
    clean = {}
    for name, (xs, ys) in series.items():
        xs, ys = list(map(float, xs)), list(map(float, ys))
        if len(xs) != len(ys):
            raise FigureError(f"series {name!r}: {len(xs)} x values but {len(ys)} y values")
        clean[name] = (xs, ys)
    xs_all = [x for xs, _ in clean.values() for x in xs if math.isfinite(x)]
    ys_all = [y for _, ys in clean.values() for y in ys if math.isfinite(y)]
    if not xs_all or not ys_all:
        raise FigureError("curves_figure needs at least one finite point")
    xs_all += [float(x) for x in x_include] + [x for pts in marks.values() for x, _ in pts]
    ys_all += [float(y) for y in y_include] + [y for pts in marks.values() for _, y in pts]
    img = new_canvas(title, size)
    width, height = size
    # the x axis ends at the data (2,003,200 frames must not stretch it to a 2.5M tick)
    x_hi = max(xs_all)
    x_ticks = nice_ticks(min(xs_all), x_hi)
    x_ticks = [t for t in x_ticks if t <= x_hi + 1e-9 * abs(x_hi)] or x_ticks
    x_hi = max(x_hi, x_ticks[-1])
    y_ticks = nice_ticks(min(ys_all), max(ys_all))
    ax = Axes(img, 100, 80, width - 40, height - 80, (x_ticks[0], x_hi), (y_ticks[0], y_ticks[-1]))
    ax.y_axis(y_ticks, ylabel)
    ax.x_ticks(x_ticks, xlabel)
    entries = []
    for k, (name, (xs, ys)) in enumerate(clean.items()):
        colour = PALETTE[colours.get(name, k) % len(PALETTE)]
        width_px = 1 if name in thin else 2
        runs, run = [], []
        for x, y in zip(xs, ys):
            if math.isfinite(x) and math.isfinite(y):
                run.append(ax.px(x, y))
            elif run:
                runs.append(run)
                run = []
        runs.append(run)
        for r in runs:
            if len(r) > 1:
                cv2.polylines(img, [np.array(r, np.int32)], False, colour, width_px, cv2.LINE_AA)
            elif r:
                cv2.circle(img, r[0], 1 + width_px, colour, -1, cv2.LINE_AA)
        for x, y in marks.get(name, []):
            cx, cy = ax.px(x, y)
            cv2.rectangle(img, (cx - 5, cy - 5), (cx + 5, cy + 5), colour, 2, cv2.LINE_AA)
        if name not in thin:
            entries.append((name, colour, "line"))
    ax.frame()
    # the legend inside one corner of the plot, one entry per line
    left, top = ax.left + 10, ax.top + 16
    if legend_corner == "lower right":
        text_width = max((cv2.getTextSize(n, FONT, 0.45, 1)[0][0] for n, _, _ in entries), default=0)
        left, top = ax.right - 10 - 32 - text_width, ax.bottom - 16 - 20 * (len(entries) - 1)
    for k, (name, colour, _) in enumerate(entries):
        y = top + 20 * k
        cv2.line(img, (left, y), (left + 24, y), colour, 2, cv2.LINE_AA)
        draw_text(img, name, (left + 32, y), 0.45, valign="middle")
    return img
