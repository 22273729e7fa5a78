"""Small charts written directly as SVG text: panels, axes, histograms, lines.

The report's plots need a handful of marks (step histograms, polylines,
vertical rules, tick labels, a legend, a text box) on linear axes; writing
them as SVG text is hundreds of times faster than a plotting library and
needs no font files: text stays ``<text>`` in a generic ``sans-serif``
family, which the browser draws with the reader's own fonts.

A chart is a list of SVG fragments (strings) that :func:`document` wraps.
User units are points (1/72 in) by convention, so font sizes read like a
plotting library's. :class:`Frame` maps data to user units; every mark
function takes one. Coordinates are rounded to ``DIGITS`` decimals and
non-finite data are dropped, so that the same data give the same bytes and
the SVG stays small.

Every string drawn goes through :func:`esc`: characters XML forbids are
removed and ``<``, ``>``, ``&`` and quotes are escaped, so any label gives
well-formed XML.
"""

from __future__ import annotations

import html as _html
import math
import re
from dataclasses import dataclass

import numpy as np

__all__ = [
    "AUTO_STEPS",
    "FINE_STEPS",
    "Frame",
    "INK",
    "MUTE",
    "axis_bottom",
    "axis_left",
    "document",
    "esc",
    "grid",
    "legend",
    "nice_ticks",
    "polyline",
    "stairs",
    "text",
    "text_box",
    "tick_labels",
    "title",
    "vrules",
]

DIGITS = 1  # decimals of user units (points) in the output
INK = "#1d2330"  # text
MUTE = "#5b6474"  # spines, ticks, tick labels
SPINE_WIDTH = 0.6
TICK_LENGTH = 3.5
AUTO_STEPS = (1.0, 2.0, 2.5, 5.0, 10.0)  # "nice" tick steps per decade (matplotlib's AutoLocator)
FINE_STEPS = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)  # matplotlib's MaxNLocator default
_XML_BAD = re.compile("[^\t\n\r\x20-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")


@dataclass(frozen=True)
class Frame:
    """A panel's plotting area and its data limits.

    Attributes
    ----------
    x, y : float
        Top-left corner of the plotting area, user units (y down).
    w, h : float
        Width and height, user units.
    xlim, ylim : tuple of float
        Data values at the left/right and bottom/top edges (linear axes);
        equal limits are taken one unit apart.
    """

    x: float
    y: float
    w: float
    h: float
    xlim: tuple = (0.0, 1.0)
    ylim: tuple = (0.0, 1.0)

    def px(self, xs):
        """Data x (array-like) to user units."""
        lo, hi = self.xlim
        return self.x + (np.asarray(xs, dtype=float) - lo) * (self.w / ((hi - lo) or 1.0))

    def py(self, ys):
        """Data y (array-like) to user units (y grows downwards)."""
        lo, hi = self.ylim
        return self.y + self.h - (np.asarray(ys, dtype=float) - lo) * (self.h / ((hi - lo) or 1.0))

    @property
    def bottom(self):
        return self.y + self.h

    @property
    def right(self):
        return self.x + self.w


# --------------------------------------------------------------------------------------------
# numbers and strings


_TRAILING_ZEROS = re.compile(r"(\.[0-9]*?)0+(?![0-9])")
_BARE_POINT = re.compile(r"\.(?![0-9])")
_MINUS_ZERO = re.compile(r"(?<![0-9.])-(0(?![0-9.]))")


def _trim(s):
    """Numbers in ``s`` without trailing zeros, a bare point or the sign of ``-0``."""
    return _MINUS_ZERO.sub(r"\1", _BARE_POINT.sub("", _TRAILING_ZEROS.sub(r"\1", s)))


def _n(v):
    """A coordinate as short text: ``DIGITS`` decimals, no trailing zeros, no ``-0``."""
    return _trim(f"{v:.{DIGITS}f}")


def _xy(xs, ys):
    """Coordinate pairs ``x,y`` separated by spaces, as :func:`_n` writes them (one format call per pair)."""
    pair = f"%.{DIGITS}f,%.{DIGITS}f"
    return _trim(" ".join(map(pair.__mod__, zip(np.asarray(xs, float).tolist(), np.asarray(ys, float).tolist()))))


def esc(s):
    """``s`` as XML character data or attribute text: forbidden characters dropped, markup escaped."""
    return _html.escape(_XML_BAD.sub("", str(s)), quote=True)


def nice_ticks(lo, hi, nbins=9, symmetric=False, steps=AUTO_STEPS):
    """Tick values on a linear axis from ``lo`` to ``hi``.

    The step is the smallest "nice" one (a member of ``steps`` times a power
    of ten) not below ``(hi - lo) / nbins``, as matplotlib's ``MaxNLocator``
    chooses it; the multiples of the step inside ``[lo, hi]`` are returned.

    Parameters
    ----------
    lo, hi : float
        Axis limits; a degenerate or non-finite range is widened.
    nbins : int
        About this many intervals at most.
    symmetric : bool
        Limits taken as ``-m, m`` with ``m = max(|lo|, |hi|)``: ticks are
        symmetric about zero.
    steps : sequence of float
        Nice mantissas in [1, 10], increasing, ending with 10.

    Returns
    -------
    ticks : ndarray (K,)
    step : float
    """
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi = 0.0, 1.0
    if symmetric:
        lo, hi = -max(abs(lo), abs(hi)), max(abs(lo), abs(hi))
    if hi <= lo:
        lo, hi = lo - 0.5 * max(abs(lo), 1.0), lo + 0.5 * max(abs(lo), 1.0)
    raw = (hi - lo) / max(int(nbins), 1)
    scale = 10.0 ** math.floor(math.log10(raw))
    step = next(s * scale for s in steps if s * scale >= raw * (1 - 1e-9))
    eps = 1e-9
    k = np.arange(math.ceil(lo / step - eps), math.floor(hi / step + eps) + 1)
    return k * step, step


def tick_labels(ticks, step):
    """Tick values as text with as many decimals as ``step`` needs; a typographic minus."""
    digits = next((d for d in range(16) if abs(round(step, d) - step) <= 1e-9 * step), 15)
    out = []
    for t in ticks:
        s = f"{t:.{digits}f}"
        if float(s) == 0:
            s = s.lstrip("-")
        out.append(s.replace("-", "\u2212"))
    return out


# --------------------------------------------------------------------------------------------
# layout


def grid(n, ncols, width, height, margins, wspace=0.2, hspace=0.2, width_ratios=None):
    """Boxes of ``n`` panels in rows of ``ncols``, as a gridspec lays them out.

    Parameters
    ----------
    n, ncols : int
    width, height : float
        The chart's size, user units.
    margins : tuple of float
        ``(left, right, top, bottom)`` empty borders, user units.
    wspace, hspace : float
        Gaps between panels as fractions of the mean panel width and height.
    width_ratios : sequence of float, optional
        Relative column widths.

    Returns
    -------
    list of tuple
        ``(x, y, w, h)`` per panel, row by row.
    """
    nrows = math.ceil(n / ncols)
    left, right, top, bottom = margins
    ratios = np.asarray(width_ratios if width_ratios is not None else [1.0] * ncols, dtype=float)
    cell_w = (width - left - right) / (ncols + wspace * (ncols - 1))
    cell_h = (height - top - bottom) / (nrows + hspace * (nrows - 1))
    widths = cell_w * ncols * ratios / ratios.sum()
    xs = left + np.concatenate([[0.0], np.cumsum(widths + wspace * cell_w)[:-1]])
    boxes = []
    for i in range(n):
        r, c = divmod(i, ncols)
        boxes.append((float(xs[c]), top + r * cell_h * (1 + hspace), float(widths[c]), cell_h))
    return boxes


def document(width, height, parts, label=""):
    """The chart's SVG text: a root ``<svg>`` of ``width`` x ``height`` user units around ``parts``."""
    aria = f' role="img" aria-label="{esc(label)}"' if label else ""
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{_n(width)}pt" height="{_n(height)}pt" '
        f'viewBox="0 0 {_n(width)} {_n(height)}"{aria} font-family="sans-serif" fill="{INK}">'
        f'<rect width="100%" height="100%" fill="#fff"/>' + "".join(parts) + "</svg>"
    )


# --------------------------------------------------------------------------------------------
# marks


def _finite(x, y):
    x, y = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    return x[ok], y[ok]


def polyline(frame, x, y, colour, width=1.0, cls="line"):
    """A line through the finite points ``(x, y)``, as one ``<path>``; "" for fewer than 2.

    Points that fall on the same rounded coordinates as their predecessor
    are dropped: they add bytes, not ink.

    Parameters
    ----------
    frame : Frame
    x, y : array-like (N,)
        Data coordinates; a point with a non-finite coordinate is dropped
        (the line joins its neighbours).
    colour : str
        Stroke colour.
    width : float
        Stroke width, user units.
    cls : str
        The path's class (tests and styles find marks by it).
    """
    x, y = _finite(x, y)
    if len(x) < 2:
        return ""
    X, Y = np.round(frame.px(x), DIGITS), np.round(frame.py(y), DIGITS)
    keep = np.r_[True, (np.diff(X) != 0) | (np.diff(Y) != 0)]
    X, Y = X[keep], Y[keep]
    return (f'<path class="{esc(cls)}" d="M{_n(X[0])},{_n(Y[0])}L{_xy(X[1:], Y[1:])}" fill="none" '
            f'stroke="{colour}" stroke-width="{_n(width)}" stroke-linejoin="round"/>')


def stairs(frame, counts, edges, fill=None, stroke=None, width=1.0, opacity=1.0, baseline=0.0, cls="hist"):
    """A step histogram: bar tops joined, down to ``baseline`` at both ends, as one ``<path>``.

    Parameters
    ----------
    frame : Frame
    counts : array-like (B,)
        Bar heights, data units; non-finite ones are drawn at the baseline.
    edges : array-like (B + 1,)
        Bin edges, increasing.
    fill, stroke : str, optional
        Colours; a filled histogram without ``stroke`` has no outline.
    width, opacity : float
        Outline width (user units); opacity of the fill.
    """
    c = np.nan_to_num(np.asarray(counts, dtype=float), nan=baseline, posinf=baseline, neginf=baseline)
    e = np.asarray(edges, dtype=float)
    xs = np.round(frame.px(np.repeat(e, 2)), DIGITS)
    ys = np.round(frame.py(np.r_[baseline, np.repeat(c, 2), baseline]), DIGITS)
    d = f"M{_n(xs[0])},{_n(ys[0])}L{_xy(xs[1:], ys[1:])}"
    paint = f' fill="{fill}"' if fill else ' fill="none"'
    if fill and opacity < 1:
        paint += f' fill-opacity="{opacity:g}"'
    if stroke:
        paint += f' stroke="{stroke}" stroke-width="{_n(width)}" stroke-linejoin="miter"'
    return f'<path class="{esc(cls)}" d="{d}{"Z" if fill else ""}"{paint}/>'


def vrules(frame, xs, colour, width=0.6, cls="rule"):
    """Vertical lines across the frame at the data ``xs`` (finite ones), as one ``<path>``."""
    xs = np.asarray(xs, dtype=float).ravel()
    xs = frame.px(xs[np.isfinite(xs)])
    if xs.size == 0:
        return ""
    d = "".join(f"M{_n(x)},{_n(frame.y)}V{_n(frame.bottom)}" for x in xs)
    return f'<path class="{esc(cls)}" d="{d}" stroke="{colour}" stroke-width="{_n(width)}"/>'


def text(x, y, s, size=8.0, colour=None, anchor="start", cls=None, extra=""):
    """One ``<text>`` at user coordinates ``(x, y)`` (baseline), escaped."""
    attrs = f' x="{_n(x)}" y="{_n(y)}" font-size="{size:g}"'
    if anchor != "start":
        attrs += f' text-anchor="{anchor}"'
    if colour:
        attrs += f' fill="{colour}"'
    if cls:
        attrs += f' class="{esc(cls)}"'
    return f"<text{attrs}{extra}>{esc(s)}</text>"


def title(frame, s, size=8.0):
    """A left-aligned title just above the frame."""
    return text(frame.x, frame.y - 0.55 * size, s, size, cls="title")


def text_box(frame, lines, size=6.5, colour=None, spacing=1.25, cls="box"):
    """Lines of text right-aligned in the frame's top-right corner, as one ``<text>``.

    Parameters
    ----------
    frame : Frame
    lines : sequence of str
        One ``<tspan>`` each, escaped.
    size, spacing : float
        Font size (user units) and line height as a multiple of it.
    colour : str, optional
        Fill of all lines; the chart's ink colour when None.
    cls : str
    """
    x = frame.right - 0.02 * frame.w
    y0 = frame.y + 0.03 * frame.h + size * 0.8
    spans = "".join(
        f'<tspan x="{_n(x)}" y="{_n(y0 + i * size * spacing)}">{esc(s)}</tspan>' for i, s in enumerate(lines)
    )
    fill = f' fill="{colour}"' if colour else ""
    return f'<text class="{esc(cls)}" font-size="{size:g}" text-anchor="end"{fill}>{spans}</text>'


def _inside(ticks, labels, lim):
    """The ticks (and their labels) within the limits ``lim``."""
    t = np.asarray(ticks, dtype=float)
    lo, hi = min(lim), max(lim)
    pad = 1e-9 * (hi - lo)
    keep = (t >= lo - pad) & (t <= hi + pad)
    return t[keep], [s for s, k in zip(labels, keep) if k]


def axis_bottom(frame, ticks, labels, label=None, size=7.0, label_size=8.0):
    """The x axis along the frame's bottom: spine, ticks, tick labels and an axis label.

    Parameters
    ----------
    frame : Frame
    ticks : array-like (K,)
        Tick positions, data units; those outside ``frame.xlim`` are left out.
    labels : sequence of str
        One per tick (:func:`tick_labels`).
    label : str, optional
        The axis label, centred below the tick labels.
    size, label_size : float
        Font sizes of the tick labels and of the axis label, user units.
    """
    ticks, labels = _inside(ticks, labels, frame.xlim)
    xs = frame.px(ticks)
    y = frame.bottom
    d = f"M{_n(frame.x)},{_n(y)}H{_n(frame.right)}" + "".join(f"M{_n(x)},{_n(y)}v{TICK_LENGTH}" for x in xs)
    parts = [f'<path class="axis" d="{d}" stroke="{MUTE}" stroke-width="{SPINE_WIDTH}" fill="none"/>']
    parts += [text(x, y + TICK_LENGTH + 1.0 + size, s, size, MUTE, "middle") for x, s in zip(xs, labels)]
    if label:
        parts.append(text(frame.x + frame.w / 2, y + TICK_LENGTH + 3.0 + size + label_size, label, label_size,
                          anchor="middle", cls="xlabel"))
    return "".join(parts)


def axis_left(frame, ticks, labels, label=None, size=7.0, label_size=8.0):
    """The y axis along the frame's left: as :func:`axis_bottom`, the axis label turned upright."""
    ticks, labels = _inside(ticks, labels, frame.ylim)
    ys = frame.py(ticks)
    x = frame.x
    d = f"M{_n(x)},{_n(frame.y)}V{_n(frame.bottom)}" + "".join(f"M{_n(x)},{_n(y)}h{-TICK_LENGTH}" for y in ys)
    parts = [f'<path class="axis" d="{d}" stroke="{MUTE}" stroke-width="{SPINE_WIDTH}" fill="none"/>']
    parts += [text(x - TICK_LENGTH - 1.5, y + 0.35 * size, s, size, MUTE, "end") for y, s in zip(ys, labels)]
    if label:
        width = max((len(s) for s in labels), default=1) * 0.6 * size
        lx, ly = x - TICK_LENGTH - 3.0 - width - 0.3 * label_size, frame.y + frame.h / 2
        parts.append(text(lx, ly, label, label_size, anchor="middle", cls="ylabel",
                          extra=f' transform="rotate(-90 {_n(lx)} {_n(ly)})"'))
    return "".join(parts)


def legend(frame, entries, size=7.0, ncols=1):
    """A legend in the frame's top-right corner, without a box.

    Parameters
    ----------
    frame : Frame
    entries : list of tuple
        ``(label, colour, kind)``, kind ``"line"`` (a short stroke) or
        ``"patch"`` (a lightly filled square with an outline).
    size : float
        Font size; text widths are estimated from it (no font metrics).
    ncols : int
        Entries per row.
    """
    if not entries:
        return ""
    key, gap = 2.0 * size, 0.6 * size
    col_w = max(len(str(e[0])) for e in entries) * 0.58 * size + key + gap + size
    x0 = frame.right - min(ncols, len(entries)) * col_w
    parts = []
    for i, (label, colour, kind) in enumerate(entries):
        r, c = i // ncols, i % ncols
        x, y = x0 + c * col_w, frame.y + 0.6 * size + r * 1.45 * size
        if kind == "patch":
            parts.append(f'<rect x="{_n(x)}" y="{_n(y - 0.4 * size)}" width="{_n(key * 0.8)}" '
                         f'height="{_n(0.8 * size)}" '
                         f'fill="{colour}" fill-opacity="0.25" stroke="{colour}" stroke-width="1.1"/>')
        else:
            parts.append(f'<path d="M{_n(x)},{_n(y)}h{_n(key * 0.8)}" stroke="{colour}" stroke-width="1.2"/>')
        parts.append(text(x + key + 0.2 * size, y + 0.35 * size, label, size))
    return '<g class="legend">' + "".join(parts) + "</g>"
