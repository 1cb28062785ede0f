"""Stage 23 — figures: the paper's figures from Table I's runs, as PNG drawn with OpenCV.

`bar_line_figure` (bars with a line on a second axis), `scatter_figure` (labelled points, e.g. a
t-SNE), `curves_figure` (training curves); `tsne` is exact t-SNE in torch. `figures` draws the
paper's figures from the table's runs (collisions and last-view rate on unseen kitchens, the t-SNE of
the GCN's node features, training curves); `figures_of_table` from a preset. Bad input (a missing or
unreadable run, too few points) is a FigureError naming it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from .errors import KgnavbenchError
from .files import first_line
from .record import read_metrics  # a bad metrics.csv is a RecordError
from .render import type_colour


class FigureError(KgnavbenchError, ValueError):
    """A figure cannot be drawn: a missing or unreadable run, or unusable data."""


# ------------------------------------------------------------------------------------------------
# t-SNE (van der Maaten & Hinton 2008), exact: O(n^2) memory, meant for the 125 GCN node features


def _conditional_p(d: torch.Tensor, perplexity: float, steps: int = 100) -> torch.Tensor:
    """P(j|i) with each row's Gaussian precision beta found by bisection so that its entropy is
    log(perplexity); all rows at once."""
    n = len(d)
    off = ~torch.eye(n, dtype=torch.bool)
    # shifting a row's distances by its nearest neighbour's leaves P(j|i) unchanged and keeps exp finite
    d = (d - d.masked_fill(~off, math.inf).min(1, keepdim=True).values).masked_fill(~off, 0.0)
    target = math.log(perplexity)
    beta = torch.ones(n, 1, dtype=d.dtype)
    lo = torch.zeros_like(beta)
    hi = torch.full_like(beta, math.inf)
    for _ in range(steps):
        p = torch.exp(-d * beta) * off
        total = p.sum(1, keepdim=True)
        entropy = torch.log(total) + beta * (d * p).sum(1, keepdim=True) / total
        too_wide = entropy > target  # too many neighbours: narrow the Gaussian (raise beta)
        lo = torch.where(too_wide, beta, lo)
        hi = torch.where(too_wide, hi, beta)
        beta = torch.where(torch.isinf(hi), beta * 2, (lo + hi) / 2)
    p = torch.exp(-d * beta) * off
    return p / p.sum(1, keepdim=True)


def tsne(
    x: torch.Tensor, dims: int = 2, perplexity: float = 30.0, iterations: int = 1000, seed: int = 0
) -> torch.Tensor:
    """Embed the rows of x (n, d) in `dims` dimensions. Gradient descent with momentum (0.5, then 0.8)
    and per-parameter gains, early exaggeration 12 over the first quarter (at most 250 iterations), the
    learning rate scikit-learn's "auto" picks. float64 on the CPU: the same seed gives the same result."""
    if x.ndim != 2 or len(x) < 3:
        raise ValueError(f"t-SNE needs a (n, d) matrix with n >= 3, not shape {tuple(x.shape)}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # (n, n) with n ~ 100: handing work to threads costs far more than it saves
    try:
        y = _tsne(x.detach().to("cpu", torch.float64), dims, perplexity, iterations, seed)
    finally:
        torch.set_num_threads(threads)
    return y.to(torch.float32)


def _tsne(x: torch.Tensor, dims: int, perplexity: float, iterations: int, seed: int) -> torch.Tensor:
    """tsne's body on a float64 CPU tensor."""
    n = len(x)
    perplexity = min(float(perplexity), (n - 1) / 3)  # more neighbours than points cannot be matched
    p = _conditional_p(torch.cdist(x, x, compute_mode="donot_use_mm_for_euclid_dist").square(), perplexity)
    p = ((p + p.T) / (2 * n)).clamp_min(1e-12)  # symmetric joint probabilities
    exaggeration, early = 12.0, min(250, iterations // 4)
    rate = max(n / exaggeration / 4, 50.0)
    generator = torch.Generator().manual_seed(seed)
    y = torch.randn(n, dims, generator=generator, dtype=torch.float64) * 1e-2  # N(0, 1e-4 I) as in the paper
    velocity = torch.zeros_like(y)
    gains = torch.ones_like(y)
    for it in range(iterations):
        num = 1.0 / (1.0 + (y[:, None] - y[None]).square().sum(-1))  # Student-t kernel of the embedding
        num.fill_diagonal_(0.0)
        q = (num / num.sum()).clamp_min(1e-12)
        w = ((exaggeration if it < early else 1.0) * p - q) * num
        grad = 4.0 * (w.sum(1, keepdim=True) * y - w @ y)
        # delta-bar-delta gains: a larger step where the last move still goes downhill, smaller elsewhere
        gains = torch.where((grad > 0) != (velocity > 0), gains + 0.2, gains * 0.8).clamp_min(0.01)
        velocity = (0.5 if it < early else 0.8) * velocity - rate * gains * grad
        y = y + velocity
        y = y - y.mean(0)
    return y


# ------------------------------------------------------------------------------------------------
# Figures: PNG with OpenCV, white background, axes with round ticks

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


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
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


def _text(img, text: str, org, scale=0.5, colour=INK, thickness=1, align="left", valign="baseline"):
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


def _wrap(text: str, width: int, scale: float) -> list[str]:
    """Words of `text` in lines no wider than `width` pixels (a long word gets a line of its own)."""
    lines: list[str] = []
    for word in text.split():
        trial = f"{lines[-1]} {word}" if lines else word
        if lines and cv2.getTextSize(trial, FONT, scale, 1)[0][0] <= width:
            lines[-1] = trial
        else:
            lines.append(word)
    return lines or [""]


class _Axes:
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
            _text(
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
            _text(self.img, _fmt(t), (x, self.bottom + 10), 0.45, align="centre", valign="top")
        _text(self.img, label, ((self.left + self.right) // 2, self.bottom + 48), 0.55, align="centre")

    def frame(self) -> None:
        cv2.rectangle(self.img, (self.left, self.top), (self.right, self.bottom), INK, 1)


def _canvas(title: str, size) -> np.ndarray:
    width, height = size
    img = np.full((height, width, 3), 255, np.uint8)
    _text(img, title, (width // 2, 30), 0.75, INK, 2, align="centre")
    return img


def _legend(img, entries: list[tuple[str, tuple, str]], right: int, top: int) -> None:
    """Entries (label, colour, "bar" | "line") in a row ending at x=right, at height top."""
    x = right
    for label, colour, kind in reversed(entries):
        w = cv2.getTextSize(label, FONT, 0.5, 1)[0][0]
        x -= w
        _text(img, label, (x, top), 0.5, valign="middle")
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
    img = _canvas(title, size)
    width, height = size
    finite = [v for v in bars if math.isfinite(v)] or [1.0]
    bar_ticks = _ticks(0.0, max(max(finite), 0.0) * 1.05)
    finite = [v for v in line if math.isfinite(v)] or [1.0]
    line_ticks = _ticks(min(0.0, min(finite)), max(finite) * 1.05)
    left, right = 100, width - 100
    slot = (right - left) / len(labels)
    # every word of each name (the control row's takes 4 lines): the plot gives up the room they need
    wrapped = [_wrap(label, int(slot) - 6, 0.45) for label in labels]
    extra = 18 * max(0, max(len(names) for names in wrapped) - 3)
    ax = _Axes(img, left, 80, right, height - 110 - extra, (0, len(labels)), (bar_ticks[0], bar_ticks[-1]))
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
            _text(img, text, (cx, ax.bottom + 10 + 18 * k), 0.45, align="centre", valign="top")
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
                _text(
                    img,
                    f"{value:.2f}" if k == 0 else f"{value:.1f}",
                    (cx, y + 17 * k),
                    0.45,
                    colour,
                    align="centre",
                    valign="top",
                )
    ax.frame()
    _legend(img, [(bar_label, PALETTE[0], "bar"), (line_label, line_colour, "line")], width - 100, 58)
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
    img = _canvas(title, size)
    width, height = size
    lo, hi = pts.min(0), pts.max(0)
    pad = (hi - lo) * 0.08 + 1e-9  # room for the labels of the outermost points
    ax = _Axes(
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
        _text(img, label, (box[0], box[3] - 2), 0.38, (70, 70, 70))
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
) -> np.ndarray:
    """`curves_figure`'s image (BGR), for a figure of several panels."""
    marks = marks or {}
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
    img = _canvas(title, size)
    width, height = size
    # the x axis ends at the data (2,003,200 frames must not stretch it to a 2.5M tick)
    x_hi = max(xs_all)
    x_ticks = _ticks(min(xs_all), x_hi)
    x_ticks = [t for t in x_ticks if t <= x_hi + 1e-9 * abs(x_hi)] or x_ticks
    x_hi = max(x_hi, x_ticks[-1])
    y_ticks = _ticks(min(ys_all), max(ys_all))
    ax = _Axes(img, 100, 80, width - 40, height - 80, (x_ticks[0], x_hi), (y_ticks[0], y_ticks[-1]))
    ax.y_axis(y_ticks, ylabel)
    ax.x_ticks(x_ticks, xlabel)
    entries = []
    for k, (name, (xs, ys)) in enumerate(clean.items()):
        colour = PALETTE[k % len(PALETTE)]
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
                cv2.polylines(img, [np.array(r, np.int32)], False, colour, 2, cv2.LINE_AA)
            elif r:
                cv2.circle(img, r[0], 3, colour, -1, cv2.LINE_AA)
        for x, y in marks.get(name, []):
            cx, cy = ax.px(x, y)
            cv2.rectangle(img, (cx - 5, cy - 5), (cx + 5, cy + 5), colour, 2, cv2.LINE_AA)
        entries.append((name, colour, "line"))
    ax.frame()
    # the legend inside the plot's top-left corner, one entry per line
    for k, (name, colour, _) in enumerate(entries):
        y = ax.top + 16 + 20 * k
        cv2.line(img, (ax.left + 10, y), (ax.left + 34, y), colour, 2, cv2.LINE_AA)
        _text(img, name, (ax.left + 42, y), 0.45, valign="middle")
    return img


ATTENTION_SIZE = (1200, 560)
ATTENTION_BARS = 12  # object types shown, the most attended first
# where an attended type was seen: in the view only, in the target image only, in both, in neither (a
# softmax over all nodes weighs those too); tab10's blue, orange, green and grey, as BGR
ATTENDED_IN = (
    ("in the view", PALETTE[0]),
    ("in the target", PALETTE[1]),
    ("in both", PALETTE[2]),
    ("in neither", PALETTE[7]),
)


def attention_figure(
    view: np.ndarray,
    target: np.ndarray,
    attended: list[tuple[str, float, str]],
    path,
    title: str,
    caption: str,
    size=ATTENTION_SIZE,
) -> Path:
    """The paper's attention example: the agent's view and its target image (RGB, upscaled with
    nearest neighbours, as the network saw them), and beside them the attention weights over object
    types as horizontal bars, the most attended first (at most ATTENTION_BARS), each bar coloured by
    where its type was seen (`attended`: (type, weight, one of ATTENDED_IN's names))."""
    where = dict(ATTENDED_IN)
    if not attended:
        raise FigureError("attention_figure needs at least one attended object type")
    for name, weight, seen_in in attended:
        if seen_in not in where or not math.isfinite(weight):
            raise FigureError(f"attended type {name!r}: weight {weight!r} seen {seen_in!r} cannot be drawn")
    img = _canvas(title, size)
    width, height = size
    side = 340
    for k, (image, label) in enumerate(((view, "the agent's view"), (target, "the target image"))):
        x0, y0 = 30 + k * (side + 20), 80
        rgb = np.asarray(image, np.uint8)
        img[y0 : y0 + side, x0 : x0 + side] = cv2.resize(
            rgb[:, :, ::-1], (side, side), interpolation=cv2.INTER_NEAREST
        )
        cv2.rectangle(img, (x0 - 1, y0 - 1), (x0 + side, y0 + side), INK, 1)
        _text(img, label, (x0 + side // 2, y0 + side + 12), 0.55, align="centre", valign="top")
    shown = sorted(attended, key=lambda a: -a[1])[:ATTENTION_BARS]
    left, right, top = 30 + 2 * (side + 20) + 150, width - 60, 90
    row = min(28, (height - 150 - top) // len(shown))
    ticks = _ticks(0.0, max(w for _, w, _ in shown))
    ax = _Axes(img, left, top, right, top + row * len(shown), (0.0, ticks[-1]), (0.0, float(len(shown))))
    ax.x_ticks(ticks, "attention weight")
    for i, (name, weight, seen_in) in enumerate(shown):
        y = top + i * row
        x1, _ = ax.px(weight, 0)
        x1 = max(x1, left + 3)  # a weight near 0 still shows its colour
        cv2.rectangle(img, (left, y + 4), (x1, y + row - 4), where[seen_in], -1)
        _text(img, name, (left - 8, y + row // 2), 0.45, align="right", valign="middle")
        label = f"{weight:.2f}" if weight >= 0.005 else "<0.01"
        _text(img, label, (x1 + 5, y + row // 2), 0.4, (90, 90, 90), valign="middle")
    ax.frame()
    present = {seen_in for _, _, seen_in in attended}
    _legend(img, [(n, c, "bar") for n, c in ATTENDED_IN if n in present], width - 60, 60)
    for k, line in enumerate(_wrap(caption, width - 60, 0.5)[:2]):
        _text(img, line, (30, height - 40 + 20 * k), 0.5, (70, 70, 70))
    return write_png(path, img)


def attention_step(
    method: str, run, kitchen: str = "FloorPlan1", seed: int = 0, row: str | None = None
) -> dict:
    """One step of a trained attention policy, as `attention_figure`'s arguments (all but the path): the
    method's plugin with the run's best-validation checkpoint, built as an evaluation builds it; the
    first fixed episode of each seen static target of `kitchen` in order, until one succeeds (else the
    last tried); in it, the step whose attention (weights >= 0.01) reaches types in the most of the
    places (view only, target only, both, neither), then the most types (the earliest of those). The
    policy must have `explain(agent, top)`, as kgnavbench's learned policies with attention do."""
    from . import evaluate
    from .env import parallel_env
    from .kitchens import object_types
    from .plugins import load_plugin
    from .tasks import load_tasks

    config = evaluate.EvalConfig(method=method, run=str(run), kitchens=(kitchen,))
    plugin = load_plugin(method)
    tasks = load_tasks(kitchen)
    spec = evaluate.policy_spec(config, evaluate.kitchen_seed(seed, kitchen), tasks.graph.views.shape[1])
    policy = plugin.make_policy(plugin.config({}), spec)
    types = {name: i for i, name in enumerate(object_types())}

    def explained(agent: str) -> list[tuple[str, float]]:
        try:
            return policy.explain(agent, top=len(types))["attention"]
        except (AttributeError, TypeError, KeyError) as e:
            raise FigureError(
                f"{method}'s policy has no explain(agent, top) -> {{'attention': [(type, weight), ...]}} "
                f"({type(e).__name__}: {first_line(e)}): no attention to draw"
            ) from e

    env = parallel_env(kitchen=kitchen, n_agents=1, targets="all", tasks=tasks, features=True)
    rows = [r for r, t in enumerate(tasks.targets) if t.seen and t.kind == "static"]
    if not rows:
        raise FigureError(f"{kitchen} has no seen static target")
    for r in rows:
        target = tasks.targets[r]
        cap = evaluate.episode_cap(evaluate.column_of(tasks.split, target.seen))
        episode = {"target": target.object_id, "start": target.starts[0], "max_steps": cap}
        observations, infos = env.reset(options={"episodes": [episode]})
        (agent,) = env.agents
        policy.reset(agent)
        steps, info = [], infos[agent]
        while env.agents:
            obs = observations[agent]
            actions = policy.act(observations, infos)
            seen = (obs["view"], obs["target"], obs["view_objects"], obs["target_objects"])
            steps.append((*seen, explained(agent)))
            observations, _, terminations, truncations, infos = env.step(actions)
            info = infos[agent]
            if terminations[agent] or truncations[agent]:
                break
        if info["success"]:
            break

    def seen_in(name: str, in_view, in_target) -> str:
        v, g = in_view[types[name]] > 0, in_target[types[name]] > 0
        return ATTENDED_IN[2 if v and g else 0 if v else 1 if g else 3][0]

    def spread(i: int) -> tuple[int, int, int]:  # places with a weight >= 0.01, types, earliest
        _, _, in_view, in_target, weights = steps[i]
        places = {seen_in(n, in_view, in_target) for n, w in weights if w >= 0.01}
        return len(places), len(weights), -i

    k = max(range(len(steps)), key=spread)
    view, target_image, in_view, in_target, weights = steps[k]
    if not weights:
        raise FigureError(f"{method} attended to nothing in {kitchen}'s episode: no attention to draw")
    outcome = "success" if info["success"] else "failure"
    return {
        "view": view,
        "target": target_image,
        "attended": [(name, w, seen_in(name, in_view, in_target)) for name, w in weights],
        "title": f"Attention over object types: {kitchen}, target {target.type} ({target.kind})",
        "caption": f"{row or method} ({Path(run).name}, best.pt): step {k + 1} of "
        f"{info['episode_length']} ({outcome}), the first step whose attention (weights >= 0.01) "
        f"reaches the most places, then the most types ({len(weights)}); bars: the "
        f"{min(len(weights), ATTENTION_BARS)} most attended.",
    }


def attention_example(
    method: str, run, path, kitchen: str = "FloorPlan1", seed: int = 0, row: str | None = None
) -> Path:
    """`attention_figure` of `attention_step` into `path`."""
    return attention_figure(path=path, **attention_step(method, run, kitchen, seed, row))


# ------------------------------------------------------------------------------------------------
# The paper's figures from the table's runs

TSNE_SIZE = (1200, 900)  # more room than FIGURE_SIZE: a label per object type


def _run_dir(path, what: str) -> Path:
    path = Path(path)
    if not path.is_dir():
        raise FigureError(f"{path}: no such {what} run directory")
    return path


def read_episodes(eval_dir) -> list[dict]:
    """Every episode of an evaluation run: the JSON lines of eval_dir/episodes/<kitchen>.jsonl."""
    eval_dir = _run_dir(eval_dir, "evaluation")
    files = sorted((eval_dir / "episodes").glob("*.jsonl"))
    if not files:
        raise FigureError(f"{eval_dir} holds no episodes/*.jsonl: not a finished evaluation run")
    episodes = []
    for path in files:
        try:
            lines = path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise FigureError(f"cannot read {path}: {e}") from e
        for n, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            try:
                episode = json.loads(line)
                if not isinstance(episode, dict):
                    raise ValueError("not a JSON object")
                episodes.append(episode)
            except ValueError as e:
                raise FigureError(f"{path}, line {n}: not an episode ({e})") from e
    return episodes


def unseen_kitchen_stats(episodes: list[dict], where="episodes") -> tuple[float, float] | None:
    """(mean collisions per episode, % of episodes whose last view shows the target) over the
    episodes in unseen kitchens; None where there are none."""
    unseen = [e for e in episodes if e.get("column") == "unseen_kitchens"]
    if not unseen:
        return None
    try:
        collisions = sum(float(e["collisions"]) for e in unseen) / len(unseen)
        shown = 100.0 * sum(bool(e["last_view_shows_target"]) for e in unseen) / len(unseen)
    except (KeyError, TypeError, ValueError) as e:
        raise FigureError(
            f"{where}: an unseen-kitchens episode lacks collisions or last_view_shows_target ({e})"
        ) from e
    return collisions, shown


def _run_checkpoint(train_dir: Path, last_too: bool) -> tuple[dict, Path] | None:
    """A training run's best-validation checkpoint (with `last_too`, its last.pt where there is no
    best.pt yet: a run stopped before its first validation) and its path; None where there is none."""
    from .runs import TrainError, load_checkpoint  # lazily: recording must not cost a torch import

    path = train_dir / "best.pt"
    if last_too and not path.exists():
        path = train_dir / "last.pt"
    if not path.exists():
        return None
    try:
        return load_checkpoint(path), path
    except TrainError as e:
        raise FigureError(str(e)) from e


def _kg_checkpoint(train_dir: Path) -> tuple[dict, Path] | None:
    """The best-validation checkpoint of a training run (else its last) when its model has an
    accumulated knowledge graph, else None."""
    found = _run_checkpoint(train_dir, last_too=True)
    if found is None:
        return None
    config = found[0]["model_config"]
    if config.get("kg", "none") == "none" or config.get("kg_graph") != "accumulated":
        return None
    return found


def _attention_model(train_dir: Path) -> tuple[str, str] | None:
    """(method, attention_nodes) of a training run whose best checkpoint has a model with attention
    over its knowledge graph, else None (no best.pt yet: nothing an evaluation would test)."""
    found = _run_checkpoint(train_dir, last_too=False)
    if found is None or found[0]["model_config"].get("kg") != "attention":
        return None
    ck = found[0]
    return str(ck.get("method")), str(ck["model_config"].get("attention_nodes", "visible"))


def gcn_node_features(ck: dict, where="checkpoint") -> tuple[torch.Tensor, torch.Tensor]:
    """The third GCN layer's node features H (125, d) of a KG checkpoint over its accumulated
    co-visibility graph, and that graph's adjacency (125, 125) with the edge weights it trained on."""
    from . import models  # lazily, as above

    try:
        net = models.make_model(models.ModelConfig(**ck["model_config"]))
        net.load_state_dict(ck["model"])
        covis = models.CoVisibility()
        covis.load_state_dict(ck["covis"])
    except (RuntimeError, KeyError, TypeError, ValueError) as e:
        raise FigureError(f"{where} does not fit its model ({first_line(e)})") from e
    net.eval()
    adjacency = covis.adjacency(net.cfg.kg_edges)
    with torch.no_grad():
        h = net.kg.node_features(models.normalized_adjacency(adjacency))
    return h.float(), adjacency


def figures(rows: list[tuple[str, str | None, str]], out_dir, seed: int = 0, progress=print) -> list[Path]:
    """The paper's figures as PNGs in out_dir from rows (Table I row name, training run dir or None,
    evaluation run dir):
      * collisions_unseen.png  mean collisions per episode in unseen kitchens (bars) and the rate of
                               episodes whose last view shows the target (line), per row that has
                               unseen-kitchen episodes;
      * tsne_gcn.png           a t-SNE (seed) of the third GCN layer's node features of the last row
                               trained with an accumulated knowledge graph, the object types that have
                               a co-visibility edge, each labelled;
      * attention_example.png  the last row trained with attention: one step of an episode in
                               FloorPlan1, its view, its target and its attention over object types
                               (`attention_example`);
      * training_curves.png    validation SR (the training episodes' SR for a run without validation)
                               and training_reward.png mean reward per frame, vs frames, per trained row.
    A figure without data is skipped with a note to `progress`. Returns the paths written."""
    from .kitchens import object_types  # a data file read; nothing heavy

    out_dir = Path(out_dir)
    # read everything first: bad input fails before any figure is (re)written
    unseen, metrics, trained = [], {}, []
    for name, train_dir, eval_dir in rows:
        stats = unseen_kitchen_stats(read_episodes(eval_dir), f"{eval_dir}")
        if stats is not None:
            unseen.append((name, *stats))
        if train_dir:
            train_dir = _run_dir(train_dir, "training")
            metrics[name] = read_metrics(train_dir / "metrics.csv")
            trained.append((name, train_dir))
    # the attention example's episode, before any figure is written: +KG+Attention in Table I, the
    # last row trained with attention over the visible nodes (else over all of them)
    attention = None
    candidates = [(name, train_dir, _attention_model(train_dir)) for name, train_dir in trained]
    candidates = [(name, d, found) for name, d, found in candidates if found is not None]
    candidates.sort(key=lambda c: c[2][1] == "visible")  # stable: the table's order within each kind
    if candidates:
        name, train_dir, (method, _) = candidates[-1]
        attention = attention_step(method, train_dir, seed=seed, row=name)
    written = []

    if unseen:
        written.append(
            bar_line_figure(
                [n for n, _, _ in unseen],
                [c for _, c, _ in unseen],
                [s for _, _, s in unseen],
                out_dir / "collisions_unseen.png",
                "Unseen kitchens: collisions per episode and last view showing the target",
                "collisions per episode",
                "last view shows target (%)",
            )
        )
    else:
        progress("figures: no row has unseen-kitchen episodes; collisions_unseen.png skipped")

    kg = None
    for name, train_dir in reversed(trained):  # the last KG row: +KG+Attention in Table I
        found = _kg_checkpoint(train_dir)
        if found is not None:
            kg = (name, *found)
            break
    if kg is None:
        progress("figures: no row trained a knowledge graph; tsne_gcn.png skipped")
    else:
        name, ck, path = kg
        h, adjacency = gcn_node_features(ck, str(path))
        keep = (adjacency.sum(1) > 0).nonzero().squeeze(1)
        if len(keep) < 3:  # no co-visibility yet: every type
            keep = torch.arange(len(h))
        types = object_types()
        y = tsne(h[keep], seed=seed)
        written.append(
            scatter_figure(
                y,
                [types[i] for i in keep.tolist()],
                out_dir / "tsne_gcn.png",
                f"t-SNE of the third GCN layer's node features: {name}, {len(keep)} object types "
                f"({int(ck['frames']):,} frames)",
                size=TSNE_SIZE,
            )
        )

    if attention is None:
        progress("figures: no row trained with attention; attention_example.png skipped")
    else:
        written.append(attention_figure(path=out_dir / "attention_example.png", **attention))

    # validation SR where the run measured it (the checkpoint selection's number), else training SR
    success, reward, validated = {}, {}, 0
    for name, series in metrics.items():
        xs, ys = series.get("val_sr", ([], []))
        if xs:
            success[name] = (xs, ys)
            validated += 1
        elif series.get("success_rate", ([], []))[0]:
            success[f"{name} (training episodes)"] = series["success_rate"]
        if series.get("mean_reward", ([], []))[0]:
            reward[name] = series["mean_reward"]
    # a run that never succeeded draws its line on the x axis, under the others: the legend says so
    success = {(f"{n} (0 throughout)" if not any(ys) else n): (xs, ys) for n, (xs, ys) in success.items()}
    success_title = "Validation success rate during training" if validated else "Success rate during training"
    for curves, file, title, ylabel, y_include in (
        (success, "training_curves.png", success_title, "success rate (%)", (0,)),
        (reward, "training_reward.png", "Mean reward per frame during training", "mean reward per frame", ()),
    ):
        if curves:
            written.append(
                curves_figure(
                    curves, out_dir / file, title, "frames", ylabel, x_include=(0,), y_include=y_include
                )
            )
        else:
            progress(f"figures: no training run logged {ylabel}; {file} skipped")
    return written


def figures_of_table(
    preset: str = "quick",
    runs_dir="runs",
    out_dir="docs/figures",
    spec_path=None,
    progress=print,
    trained=None,
    device: str = "cpu",
    rows_named: tuple[str, ...] = (),
) -> list[Path]:
    """The figures of a Table I preset's runs (run_table: finished runs are only reloaded, missing
    ones are trained and evaluated first; with `trained`, a folder such as zoo/, the trained runs come
    from there and none is trained), from each row's first seed; `rows_named`: those rows only."""
    from . import jobs, table, table_spec  # lazily: the table stage imports the trainer

    spec = table_spec.load_spec(spec_path) if spec_path else table_spec.load_spec()
    if trained is None and device == "cpu" and not rows_named:
        result = table.run_table(spec, preset, runs_dir, progress)
    else:  # a run trained on CUDA is another run (its device is in its config): the table's, as asked
        sources = jobs.Sources(None if trained is None else Path(trained))
        result = table.run_table(
            spec, preset, runs_dir, progress, device=device, sources=sources, rows_named=rows_named
        )
    rows = [(r.row.name, r.train_runs[0] or None, r.eval_runs[0]) for r in result.rows]
    return figures(rows, out_dir, progress=progress)
