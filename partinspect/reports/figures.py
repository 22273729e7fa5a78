"""The report's figures, drawn from one run's data (after the paper's Figs. 3-7).

The pipeline hands :func:`build_figures` a plain dict (its interface is
described there); a figure whose data is missing or empty is left out with
a one-line note saying why. Figures only show the report's numbers, they
never change them. In report order, the paper's numbers in brackets:

1. [Fig. 3] both images, downscaled to at most ``IMAGE_WIDTH`` px, with
   every fitted feature drawn over them as a vector polyline coloured by
   its status;
2. [Fig. 4] histograms of each fit's residuals against the normal density
   the noise model predicts, at most ``MAX_RESIDUAL_PANELS``;
3. [Figs. 5-6] the standard deviations of the triangulated points along X,
   Y, Z, per point and as distributions: in the left camera frame when the
   report has a registration (Z is then the depth), else in the part frame;
4. [Fig. 7] the reconstructed points over the CAD edges with their k = 2
   error ellipsoids, magnified, in an inline canvas viewer (nothing fetched
   from anywhere).

Each :class:`Figure`'s ``body`` is trusted HTML made here, every string from
the data escaped. The plots (2 and 3) are SVG text written by
:mod:`partinspect.reports.svgplot` and embedded as ``<img>`` data URIs;
they hold no ids or dates, so the same data give the same bytes.
"""

from __future__ import annotations

import base64
import html as _html
import json
import math
from dataclasses import dataclass

import numpy as np

from partinspect.reports import svgplot

__all__ = [
    "Figure",
    "IMAGE_WIDTH",
    "MAX_RESIDUAL_PANELS",
    "STATUS_COLOURS",
    "build_figures",
    "image_figure",
    "view_strip_figure",
    "residual_figure",
    "sigma_figure",
    "scene_figure",
    "display_image",
    "jpeg_data_uri",
]

IMAGE_WIDTH = 1000  # px of the downscaled images: keeps each inline JPEG to a few hundred kB
THUMB_WIDTH = 480  # px of a view's thumbnail in the view strip
JPEG_QUALITY = 82
MAX_RESIDUAL_PANELS = 24
MAX_OVERLAY_POINTS = 240  # per polyline in the image figure
MAX_SCENE_POINTS = 4000  # 3D points in the viewer, all features together
MAX_SCENE_ELLIPSOIDS = 400
MAX_ELLIPSOIDS_PER_FEATURE = 24
MAX_EDGE_POINTS = 200  # per CAD edge polyline in the viewer
COVERAGE = 2.0

# Bright enough to read on a grey image; the same hues as the report's badges.
STATUS_COLOURS = {
    "fail": "#ff3b30",
    "inconclusive": "#ffb300",
    "pass": "#2fd158",
    "measured": "#27c4f5",
    "unmatched": "#d17bff",
}
# Darker variants for white backgrounds (3D viewer, plots).
STATUS_INK = {
    "fail": "#b3261e",
    "inconclusive": "#9a6700",
    "pass": "#1b7a3a",
    "measured": "#0b6fa4",
    "unmatched": "#7b3fb0",
}
STATUS_ORDER = ("fail", "inconclusive", "pass", "measured", "unmatched")


@dataclass(frozen=True)
class Figure:
    """One figure of the report, or the note that replaces it.

    Attributes
    ----------
    key : str
        Stable id (``"images"``, ``"residuals"``, ``"sigmas"``, ``"scene"``),
        used as the HTML id ``fig-<key>``.
    title : str
    paper : str
        The figure of the paper it follows, e.g. ``"Fig. 3"``.
    body : str or None
        Trusted HTML of the figure (inline SVG, ``<img>`` with a data URI,
        or the viewer's canvas); None when the figure is omitted.
    caption : str
        Plain text (escaped by the template).
    note : str or None
        One line saying why the figure is omitted (or partly so).
    scene : dict or None
        The 3D viewer's data (JSON-able), for the ``scene`` figure only.
    """

    key: str
    title: str
    paper: str
    body: str | None = None
    caption: str = ""
    note: str | None = None
    scene: dict | None = None


# --------------------------------------------------------------------------------------------
# helpers


def _esc(s):
    return _html.escape(str(s), quote=True)


def _finite_rows(a, ncol):
    a = np.asarray(a, dtype=float)
    if a.size == 0:
        return np.zeros((0, ncol))
    a = a.reshape(-1, ncol)
    return a[np.all(np.isfinite(a), axis=1)]


def _status(s):
    return s if s in STATUS_COLOURS else "measured"


def _nice(x):
    """The 1-2-5 number nearest below ``x`` (x > 0)."""
    e = math.floor(math.log10(x))
    m = x / 10**e
    return (5 if m >= 5 else 2 if m >= 2 else 1) * 10**e


def _fmt_sig(x, digits=3):
    return f"{x:.{digits}g}"


def display_image(img):
    """An image as 8-bit grey for display.

    8-bit images are shown as they are; 16-bit ones (often only 10-12 bits
    used) are stretched linearly so that their 99.9th percentile is white.
    Colour (H, W, 3 or 4) is averaged to grey.
    """
    a = np.asarray(img)
    if a.ndim == 3:
        a = a[..., :3].mean(axis=2)
        src_dtype = np.asarray(img).dtype
    else:
        src_dtype = a.dtype
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"expected a (H, W) grey image, got shape {np.asarray(img).shape}")
    if src_dtype == np.uint8:
        return np.asarray(np.clip(a, 0, 255), dtype=np.uint8)
    a = a.astype(np.float64)
    finite = a[np.isfinite(a)]
    if finite.size == 0:
        return np.zeros(a.shape, np.uint8)
    lo = float(finite.min())
    hi = float(np.percentile(finite, 99.9))
    if hi <= lo:
        hi = lo + 1.0
    out = (np.nan_to_num(a, nan=lo) - lo) * (255.0 / (hi - lo))
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def jpeg_data_uri(grey8, width=IMAGE_WIDTH, quality=JPEG_QUALITY):
    """Downscale an 8-bit grey image to at most ``width`` px wide; a JPEG data URI."""
    import cv2

    h, w = grey8.shape
    if w > width:
        small = cv2.resize(grey8, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    else:
        small = grey8
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_OPTIMIZE, 1])
    if not ok:  # pragma: no cover - cv2 encodes any uint8 array
        raise RuntimeError("JPEG encoding failed")
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def _subsample(xy, n):
    """At most ``n`` rows of ``xy``, evenly spaced, first and last kept."""
    if len(xy) <= n:
        return xy
    idx = np.unique(np.round(np.linspace(0, len(xy) - 1, n)).astype(int))
    return xy[idx]


def _svg_uri(svg):
    """SVG text as a base64 data URI (for an ``<img>``: the page's CSP allows data: images only)."""
    return "data:image/svg+xml;base64," + base64.b64encode(svg.encode("utf-8")).decode("ascii")


def _img_tag(uri, alt, cls="plot"):
    return f'<img class="{cls}" src="{uri}" alt="{_esc(alt)}">'


# --------------------------------------------------------------------------------------------
# Fig. 3: images with overlays


def crop_box(shape, overlays, margin=0.06, keep=0.7):
    """The part of an image worth showing: the overlays' bounding box plus a margin.

    Returns ``(x0, y0, x1, y1)`` in pixels (x1, y1 exclusive); the whole
    image when there are no overlays or the box would cover more than
    ``keep`` of its area.
    """
    h, w = shape[:2]
    pts = [_finite_rows(o.get("xy", ()), 2) for o in overlays]
    pts = [p for p in pts if len(p)]
    if not pts:
        return 0, 0, w, h
    p = np.concatenate(pts)
    pad = margin * max(w, h)
    x0, y0 = np.floor(np.maximum(p.min(axis=0) - pad, 0)).astype(int)
    x1, y1 = np.ceil(np.minimum(p.max(axis=0) + pad, [w, h])).astype(int)
    if x1 <= x0 or y1 <= y0 or (x1 - x0) * (y1 - y0) > keep * w * h:
        return 0, 0, w, h
    return int(x0), int(y0), int(x1), int(y1)


def _overlay_svg(name, img, overlays, box, width=IMAGE_WIDTH):
    """Inline SVG of one image (JPEG data URI) with its overlays as vector polylines.

    The SVG's user units are the full image's pixels, so overlays keep their
    coordinates; only ``box`` (x0, y0, x1, y1) of the image is shown.
    """
    grey = display_image(img)
    x0, y0, x1, y1 = box
    cw, ch = x1 - x0, y1 - y0
    uri = jpeg_data_uri(np.ascontiguousarray(grey[y0:y1, x0:x1]), width=width)
    parts = [
        f'<svg class="photo" viewBox="{x0} {y0} {cw} {ch}" role="img" aria-label="{_esc(name)} image with fitted features" '
        f'data-image="{_esc(name)}" xmlns="http://www.w3.org/2000/svg">',
        f'<image href="{uri}" x="{x0}" y="{y0}" width="{cw}" height="{ch}" preserveAspectRatio="none"/>',
    ]
    labels = []
    font = max(10.0, max(cw, ch * 1.2) / 55)
    # Draw passes first, failures last (on top).
    rank = {s: i for i, s in enumerate(reversed(STATUS_ORDER))}
    for ov in sorted(overlays, key=lambda o: rank.get(_status(o.get("status")), 0)):
        xy = _finite_rows(ov.get("xy", ()), 2)
        if len(xy) < 2:
            continue
        status = _status(ov.get("status"))
        xy = _subsample(xy, MAX_OVERLAY_POINTS) + 0.5  # pixel centres -> SVG user units
        pts = " ".join(f"{x:.1f},{y:.1f}" for x, y in xy)
        label = str(ov.get("label") or "")
        kind = str(ov.get("kind") or "")
        tip = f"{label or 'unmatched'} ({kind}): {status}"
        dash = ' stroke-dasharray="6 4"' if status == "unmatched" else ""
        parts.append(
            f'<g class="ov st-{status}"><title>{_esc(tip)}</title>'
            f'<polyline class="halo" points="{pts}"/><polyline class="fg" points="{pts}"{dash}/></g>'
        )
        if label:
            mid = xy[len(xy) // 2]
            labels.append(
                f'<text class="lbl st-{status}" x="{mid[0]:.1f}" y="{mid[1] - font * 0.5:.1f}" '
                f'font-size="{font:.1f}">{_esc(label)}</text>'
            )
    parts.append('<g class="labels">' + "".join(labels) + "</g>")
    parts.append("</svg>")
    return "".join(parts)


def image_figure(figures):
    """[Fig. 3] Both images with the fitted features overlaid; a Figure."""
    title = "Fitted edges in both images"
    names = [n for n in ("left", "right") if _has_image(figures.get(n))]
    if not names:
        return Figure("images", title, "Fig. 3", note="Images with fitted features: omitted, no image data was given.")
    overlays = [o for o in (figures.get("overlays") or []) if isinstance(o, dict)]
    counts = {}
    panels = []
    shapes = {n: np.asarray(figures[n]).shape[:2] for n in names}
    boxes = {n: crop_box(shapes[n], [o for o in overlays if o.get("image") == n]) for n in names}
    if len(set(shapes.values())) == 1:  # one frame for both, so that the pair lines up side by side
        b = np.array(list(boxes.values()))
        union = (int(b[:, 0].min()), int(b[:, 1].min()), int(b[:, 2].max()), int(b[:, 3].max()))
        boxes = dict.fromkeys(names, union)
    for name in names:
        mine = [o for o in overlays if o.get("image") == name]
        for o in mine:
            if len(_finite_rows(o.get("xy", ()), 2)) >= 2:
                s = _status(o.get("status"))
                counts[s] = counts.get(s, 0) + 1
        h, w = shapes[name]
        box = boxes[name]
        where = "" if box == (0, 0, w, h) else f", shown x {box[0]}-{box[2]}, y {box[1]}-{box[3]}"
        panels.append(
            f'<div class="photo-panel"><div class="photo-title">{_esc(name)} image · {w}×{h} px{where} · '
            f"{len(mine)} fitted curves</div>{_overlay_svg(name, figures[name], mine, box)}</div>"
        )
    legend = "".join(
        f'<span class="key st-{s}"><i></i>{s} ({counts[s]})</span>' for s in STATUS_ORDER if counts.get(s)
    )
    body = (
        f'<div class="photos" title="click an image to enlarge it">{"".join(panels)}</div>'
        f'<div class="legend"><span class="legend-title">curves in both images:</span>{legend}</div>' if legend
        else '<div class="legend">no fitted curves to show</div>'
    )
    missing = [n for n in ("left", "right") if n not in names]
    note = f"The {missing[0]} image was not given." if missing else None
    caption = (
        f"The images as taken (cropped to the fitted edges, downscaled to at most {IMAGE_WIDTH} px wide for the "
        "report), with each fitted line and ellipse arc drawn over its edge, coloured by the decision of its feature's "
        "characteristics (a feature takes its worst decision); \"measured\" has no characteristic, "
        "\"unmatched\" (dashed) found no CAD edge. Hover a curve for its id; click an image to enlarge it."
    )
    if not overlays:
        note = (note + " " if note else "") + "No fitted feature was given to draw over the images."
    return Figure("images", title, "Fig. 3", body=body, caption=caption, note=note)


def view_strip_figure(figures):
    """The views of a views folder side by side: each view's left image with its measured features; a Figure.

    Each thumbnail is cropped to its view's curves and downscaled to
    ``THUMB_WIDTH`` px; a curve takes the fused decision of its feature.
    """
    title = "The views"
    views = [v for v in (figures.get("views") or []) if isinstance(v, dict) and _has_image(v.get("image"))]
    if not views:
        return Figure("views", title, "", note="The views: omitted, no view images were given.")
    panels = []
    for v in views:
        mine = [o for o in (v.get("overlays") or []) if isinstance(o, dict)]
        h, w = np.asarray(v["image"]).shape[:2]
        box = crop_box((h, w), mine)
        n = sum(1 for o in mine if o.get("label"))
        panels.append(f'<div class="photo-panel"><div class="photo-title">{_esc(v.get("name", ""))} · left image · '
                      f"{n} features matched to the CAD model</div>"
                      f'{_overlay_svg(str(v.get("name", "")), v["image"], mine, box, THUMB_WIDTH)}</div>')
    caption = (f"Each view's left image (cropped to its curves, at most {THUMB_WIDTH} px wide), with the 3D fits it "
               "measured projected back, coloured by their feature's decision after fusing the views; "
               "the characteristics table names the views behind each value.")
    return Figure("views", title, "", body=f'<div class="photos views">{"".join(panels)}</div>', caption=caption)


def _has_image(img):
    if img is None:
        return False
    a = np.asarray(img)
    return a.ndim in (2, 3) and a.shape[0] > 0 and a.shape[1] > 0


# --------------------------------------------------------------------------------------------
# Fig. 4: residual histograms


RATIO_BAND = (0.8, 1.25)  # rms/sigma taken as honest; outside it the panel's numbers are red
RED = "#b3261e"


def _residual_panel(frame_box, label, image, res, sigma, xlabel):
    """One residual histogram panel's SVG fragments and its rms/sigma (None without a sigma).

    The histogram is normalised to a density over +-4 predicted sigma (or
    the 99.5th percentile of |residual|, at most 8 sigma), so that the
    predicted normal density can be drawn on the same axis.
    """
    sigma = float(sigma) if sigma is not None and np.isfinite(sigma) and sigma > 0 else None
    rms = float(np.sqrt(np.mean(res**2)))
    scale = sigma or rms or 1.0
    half = max(4.0 * scale, float(np.percentile(np.abs(res), 99.5)))
    half = min(half, 8.0 * scale) if sigma else half
    nb = int(np.clip(np.sqrt(res.size), 8, 36))
    counts, edges = np.histogram(np.clip(res, -half, half), bins=nb, range=(-half, half), density=True)
    x = np.linspace(-half, half, 101)
    curve = np.exp(-0.5 * (x / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi)) if sigma else None
    top = max(float(counts.max()), float(curve.max()) if sigma else 0.0) * 1.05 or 1.0
    # 5 % margins on x, as a plotting library leaves them: the end tick labels stay clear of the next panel.
    fr = svgplot.Frame(*frame_box, xlim=(-1.05 * half, 1.05 * half), ylim=(0.0, top))
    parts = [svgplot.stairs(fr, counts, edges, fill="#9fb3c8"),
             svgplot.stairs(fr, counts, edges, stroke="#6f87a0", width=0.6, cls="hist-edge")]
    lines, colour, ratio = [f"n = {res.size}", f"rms {rms:.3g} px"], None, None
    if sigma:
        parts.append(svgplot.polyline(fr, x, curve, svgplot.INK, 1.1, cls="curve"))
        ratio = rms / sigma
        lines += [f"σ {sigma:.3g} px", f"rms/σ {ratio:.2f}"]
        if not RATIO_BAND[0] <= ratio <= RATIO_BAND[1]:
            colour = RED
    ticks, step = svgplot.nice_ticks(*fr.xlim, nbins=5, symmetric=True, steps=svgplot.FINE_STEPS)
    parts.append(svgplot.axis_bottom(fr, ticks, svgplot.tick_labels(ticks, step), xlabel))
    parts.append(svgplot.text_box(fr, lines, colour=colour))
    parts.append(svgplot.title(fr, f"{label or 'unmatched'} ({image})" if image else (label or "unmatched")))
    return '<g class="panel">' + "".join(parts) + "</g>", ratio


def _residual_svg(shown):
    """The residual panels of ``shown`` ``(label, image, residuals, sigma)`` in rows of 4; SVG text, ratios."""
    ncols = 4 if len(shown) > 3 else len(shown)
    nrows = math.ceil(len(shown) / ncols)
    width, height = 720.0, 72.0 * (0.3 + 1.75 * nrows)
    boxes = svgplot.grid(len(shown), ncols, width, height, (10.8, 7.2, 15.8, 30.2), wspace=0.08, hspace=0.5 / 1.45)
    parts, ratios = [], []
    for i, (box, (label, image, res, sigma)) in enumerate(zip(boxes, shown)):
        lowest = i + ncols >= len(shown)  # the bottom panel of its column carries the axis label
        part, ratio = _residual_panel(box, label, image, res, sigma, "residual, px" if lowest else None)
        parts.append(part)
        if ratio is not None:
            ratios.append(ratio)
    return svgplot.document(width, height, parts, "histograms of fit residuals"), ratios


def residual_figure(figures):
    """[Fig. 4] Histograms of each fit's residuals with the predicted normal density; a Figure."""
    title = "Fit residuals against the predicted noise"
    items = []
    for r in figures.get("residuals") or []:
        res = np.asarray(r.get("residuals", ()), dtype=float).ravel()
        res = res[np.isfinite(res)]
        if res.size >= 2:
            items.append((str(r.get("label") or ""), str(r.get("image") or ""), res, r.get("sigma")))
    if not items:
        return Figure("residuals", title, "Fig. 4", note="Residual histograms: omitted, no fit residuals were given.")
    shown = items[:MAX_RESIDUAL_PANELS]
    svg, ratios = _residual_svg(shown)
    note = None
    if len(items) > len(shown):
        note = f"Showing the first {len(shown)} of {len(items)} fits; the others are left out to keep the report short."
    summary = ""
    if ratios:
        inside = sum(RATIO_BAND[0] <= q <= RATIO_BAND[1] for q in ratios)
        summary = (
            f" Median rms/σ over the {len(ratios)} fits shown: {np.median(ratios):.2f}; "
            f"{inside} of {len(ratios)} lie within {RATIO_BAND[0]}-{RATIO_BAND[1]} (outside: red)."
        )
    caption = (
        "Signed orthogonal distances of the edge points from their fitted line or ellipse (bars, "
        "normalised) and the normal density that the noise model predicts for them (curve). "
        "rms/σ near 1 means the predicted uncertainty, which every measured number inherits, is honest."
        + summary
    )
    body = _img_tag(_svg_uri(svg), "histograms of fit residuals")
    return Figure("residuals", title, "Fig. 4", body=body, caption=caption, note=note)


# --------------------------------------------------------------------------------------------
# Figs. 5-6: point standard deviations


def _point_sigmas(points3d, rotation=None):
    """Per point sigma along 3 axes (rows), and the feature boundaries.

    With ``rotation`` (3x3, part -> camera) the axes are the camera's X, Y, Z;
    without, the part frame's.
    """
    sig, principal, bounds, labels = [], [], [0], []
    for p in points3d:
        covs = np.asarray(p.get("covs", ()), dtype=float)
        if covs.size == 0:
            continue
        covs = covs.reshape(-1, 3, 3)
        ok = np.all(np.isfinite(covs), axis=(1, 2))
        covs = covs[ok]
        if len(covs) == 0:
            continue
        if rotation is not None:
            covs = np.einsum("ij,njk,lk->nil", rotation, covs, rotation)
        d = np.sqrt(np.clip(np.einsum("nii->ni", covs), 0, None))
        ev = np.sqrt(np.clip(np.linalg.eigvalsh(0.5 * (covs + covs.transpose(0, 2, 1))), 0, None))[:, ::-1]
        sig.append(d)
        principal.append(ev)
        bounds.append(bounds[-1] + len(d))
        labels.append(str(p.get("label") or ""))
    if not sig:
        return None
    return np.concatenate(sig), np.concatenate(principal), bounds, labels


AXIS_COLOURS = (("X", "#3b6fb6"), ("Y", "#2f9e6e"), ("Z", "#c2412d"))


def _sigma_lines(box, idx, sig_um, bounds, n_features, frame):
    """Panel (a): each axis's sigma per point (um) with rules between features; SVG fragment."""
    n = int(bounds[-1])
    top = max(float(np.max(sig_um)) * 1.05, 1e-6)
    fr = svgplot.Frame(*box, xlim=(-0.5, n - 0.5), ylim=(0.0, top))
    parts = [svgplot.vrules(fr, np.asarray(bounds[1:-1], dtype=float) - 0.5, "#d8dde6", 0.6)]
    for j, (name, colour) in enumerate(AXIS_COLOURS):
        parts.append(svgplot.polyline(fr, idx, sig_um[:, j], colour, 0.8, cls=f"line sigma-{name}"))
    xt, xs = svgplot.nice_ticks(0, max(n - 1, 1))
    xt, xs = xt[xt == np.round(xt)], max(xs, 1.0)  # point numbers are whole
    yt, ys = svgplot.nice_ticks(0, top)
    parts += [
        svgplot.axis_bottom(fr, xt, svgplot.tick_labels(xt, xs),
                            f"point, feature after feature ({n_features} features, {n} points)"),
        svgplot.axis_left(fr, yt, svgplot.tick_labels(yt, ys), "standard deviation, µm"),
        svgplot.legend(fr, [(f"σ{name}", colour, "line") for name, colour in AXIS_COLOURS], ncols=3),
        svgplot.title(fr, f"(a) σ per point, {frame}"),
    ]
    return '<g class="panel">' + "".join(parts) + "</g>"


def _sigma_hists(box, sig_um, med):
    """Panel (b): the distributions of each axis's sigma (um), medians in the legend; SVG fragment."""
    hi = max(float(np.max(sig_um)) * 1.05, 1e-6)
    edges = np.linspace(0, hi, 40)
    counts = [np.histogram(sig_um[:, j], bins=edges)[0] for j in range(3)]
    top = max(max(float(c.max()) for c in counts) * 1.05, 1.0)
    fr = svgplot.Frame(*box, xlim=(0.0, hi), ylim=(0.0, top))
    parts = []
    for c, (_, colour) in zip(counts, AXIS_COLOURS):
        parts.append(svgplot.stairs(fr, c, edges, fill=colour, opacity=0.25))
        parts.append(svgplot.stairs(fr, c, edges, stroke=colour, width=1.1, cls="hist-edge"))
    xt, xs = svgplot.nice_ticks(0, hi)
    yt, ys = svgplot.nice_ticks(0, top)
    entries = [(f"σ{name}: median {m:.3g} µm", colour, "patch") for (name, colour), m in zip(AXIS_COLOURS, med)]
    parts += [
        svgplot.axis_bottom(fr, xt, svgplot.tick_labels(xt, xs), "standard deviation, µm"),
        svgplot.axis_left(fr, yt, svgplot.tick_labels(yt, ys), "points"),
        svgplot.legend(fr, entries),
        svgplot.title(fr, "(b) distribution"),
    ]
    return '<g class="panel">' + "".join(parts) + "</g>"


def _sigma_svg(idx, sig_plot_um, sig_um, bounds, n_features, frame, med):
    """The two panels of the sigma figure side by side; SVG text."""
    width, height = 720.0, 216.0
    a, b = svgplot.grid(2, 2, width, height, (43.2, 7.2, 19.4, 32.4), wspace=0.22, width_ratios=(2.1, 1))
    parts = [_sigma_lines(a, idx, sig_plot_um, bounds, n_features, frame), _sigma_hists(b, sig_um, med)]
    return svgplot.document(width, height, parts, "standard deviations of 3D points along X, Y, Z")


def sigma_figure(figures, part_to_camera=None):
    """[Figs. 5-6] Standard deviations of the 3D points along X, Y, Z; a Figure.

    ``part_to_camera`` (4x4, the registration's) puts the axes in the left
    camera's frame, where Z is the depth.
    """
    title = "Standard deviations of the 3D points"
    rotation = None
    if part_to_camera is not None:
        T = np.asarray(part_to_camera, dtype=float)
        if T.shape == (4, 4) and np.all(np.isfinite(T)):
            rotation = T[:3, :3]
    got = _point_sigmas(figures.get("points3d") or [], rotation)
    if got is None:
        return Figure("sigmas", title, "Figs. 5-6",
                      note="Point standard deviations: omitted, no 3D point covariances were given.")
    sig, principal, bounds, labels = got
    frame = "left camera frame (Z = depth)" if rotation is not None else "part frame"
    n = len(sig)
    idx = np.arange(n)
    if n > 3000:  # keep the SVG small: every k-th point, the maxima of each stretch kept by max-pooling
        k = math.ceil(n / 3000)
        m = n // k * k
        pooled = sig[:m].reshape(-1, k, 3).max(axis=1)
        idx_plot, sig_plot = idx[:m:k], pooled
    else:
        idx_plot, sig_plot = idx, sig
    med = np.median(sig, axis=0) * 1000.0  # micrometres
    svg = _sigma_svg(idx_plot, sig_plot * 1000.0, sig * 1000.0, bounds, len(labels), frame, med)
    if rotation is not None:
        lateral = max(med[0], med[1])
        ratio = med[2] / lateral if lateral > 0 else float("inf")
        verdict = (f"Depth dominates, as it does in a stereo rig: the median σZ is {ratio:.1f}× the larger lateral one."
                   if ratio > 1.5 else f"Depth does not dominate here: the median σZ is {ratio:.2f}× the larger lateral one.")
    else:
        pm = np.median(principal, axis=0) * 1000
        verdict = (f"Without a registration the depth axis cannot be named; the principal standard deviations of "
                   f"the points' covariances have medians {pm[0]:.3g}, {pm[1]:.3g} and {pm[2]:.3g} µm.")
    caption = (
        f"Standard deviations of every triangulated point along the axes of the {frame}, from the diagonal of "
        f"its propagated 3×3 covariance (image noise; on rims also the shading correction's noise and its Type B "
        f"rest); medians X {med[0]:.3g}, Y {med[1]:.3g}, Z {med[2]:.3g} µm. {verdict}"
    )
    body = _img_tag(_svg_uri(svg), "standard deviations of 3D points along X, Y, Z")
    return Figure("sigmas", title, "Figs. 5-6", body=body, caption=caption)


# --------------------------------------------------------------------------------------------
# Fig. 7: interactive 3D view


def _rot(axis, deg):
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _views(part_to_camera):
    """View matrices (rows: screen right, screen down, into the screen) in the part frame."""
    top = np.diag([1.0, -1.0, -1.0])  # look down -Z: X right, Y up
    front = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # look along +Y: X right, Z up
    side = np.array([[0, 1.0, 0], [0, 0, -1], [-1, 0, 0]])  # look along -X: Y right, Z up
    iso = _rot("x", -35.264) @ front @ _rot("z", -45)  # the isometric direction (1, -1, 1) / sqrt(3)
    views = {"iso": iso, "top": top, "front": front, "side": side}
    # The first view is the one the viewer opens with: oblique, so that the
    # depth-elongated ellipsoids show their length.
    if part_to_camera is not None:
        T = np.asarray(part_to_camera, dtype=float)
        if T.shape == (4, 4) and np.all(np.isfinite(T)):
            R = T[:3, :3]
            u, _, vt = np.linalg.svd(R)
            R = u @ vt
            if np.linalg.det(R) > 0:
                views["camera"] = R
    return {k: np.round(v, 6).tolist() for k, v in views.items()}


def _r(a, digits):
    return np.round(np.asarray(a, dtype=float), digits).tolist()


def scene_data(figures, part_to_camera=None):
    """The 3D viewer's data (JSON-able dict), or None when there is nothing to show."""
    edges = []
    for e in figures.get("cad_edges") or []:
        pl = _finite_rows(e.get("polyline", ()), 3)
        if len(pl) >= 2:
            edges.append({"label": str(e.get("label") or ""), "p": _r(_subsample(pl, MAX_EDGE_POINTS), 4)})
    feats_in = []
    for f in figures.get("points3d") or []:
        pts = np.asarray(f.get("points", ()), dtype=float)
        if pts.size == 0:
            continue
        pts = pts.reshape(-1, 3)
        covs = np.asarray(f.get("covs", ()), dtype=float)
        covs = covs.reshape(-1, 3, 3) if covs.size == len(pts) * 9 else np.full((len(pts), 3, 3), np.nan)
        ok = np.all(np.isfinite(pts), axis=1)
        if not ok.any():
            continue
        feats_in.append((str(f.get("label") or ""), _status(f.get("status")), pts[ok], covs[ok]))
    if not edges and not feats_in:
        return None
    total = sum(len(p) for _, _, p, _ in feats_in)
    keep = min(1.0, MAX_SCENE_POINTS / total) if total else 1.0
    n_ell_each = max(3, min(MAX_ELLIPSOIDS_PER_FEATURE, MAX_SCENE_ELLIPSOIDS // max(1, len(feats_in))))
    feats, big = [], []
    for label, status, pts, covs in feats_in:
        n = max(2, int(round(len(pts) * keep)))
        idx = np.unique(np.round(np.linspace(0, len(pts) - 1, min(n, len(pts)))).astype(int))
        eidx = np.unique(np.round(np.linspace(0, len(pts) - 1, min(n_ell_each, len(pts)))).astype(int))
        e_pts, e_cov = [], []
        for i in eidx:
            C = 0.5 * (covs[i] + covs[i].T)
            if not np.all(np.isfinite(C)):
                continue
            w = np.linalg.eigvalsh(C)
            if w[0] < -1e-12 * max(1.0, abs(w[-1])):
                continue
            big.append(COVERAGE * math.sqrt(max(w[-1], 0.0)))
            e_pts.append(pts[i])
            e_cov.append([C[0, 0], C[0, 1], C[0, 2], C[1, 1], C[1, 2], C[2, 2]])
        good = np.all(np.isfinite(covs), axis=(1, 2))
        sig = None
        if good.any():
            d = np.sqrt(np.clip(np.einsum("nii->ni", covs[good]), 0, None)).max(axis=1)
            sig = float(f"{np.median(d):.4g}")
        feats.append({
            "label": label, "status": status, "p": _r(pts[idx], 4),
            "ep": _r(np.reshape(e_pts, (-1, 3)), 4),
            "ec": [[float(f"{v:.4g}") for v in c] for c in e_cov],
            "sigma": sig,
        })
    allp = [np.asarray(e["p"]) for e in edges] + [np.asarray(f["p"]) for f in feats]
    allp = np.concatenate(allp)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    extent = float(np.linalg.norm(hi - lo)) or 1.0
    mag = 0
    if big and np.median(big) > 0:
        mag = _nice(0.015 * extent / float(np.median(big)))
        mag = max(mag, 1)
    return {
        "center": _r((lo + hi) / 2, 4),
        "extent": round(extent, 4),
        "edges": edges,
        "features": feats,
        "mag": mag,
        "k": COVERAGE,
        "views": _views(part_to_camera),
        "colours": STATUS_INK,
    }


def scene_figure(figures, part_to_camera=None):
    """[Fig. 7] Reconstructed points over the CAD edges with magnified error ellipsoids; a Figure."""
    title = "Reconstructed 3D edges over the CAD model"
    scene = scene_data(figures, part_to_camera)
    if scene is None:
        return Figure("scene", title, "Fig. 7", note="3D view: omitted, no 3D points or CAD edges were given.")
    n_pts = sum(len(f["p"]) for f in scene["features"])
    n_ell = sum(len(f["ep"]) for f in scene["features"])
    views = "".join(f'<button type="button" data-view="{k}">{k}</button>' for k in scene["views"])
    body = (
        '<div class="viewer" id="viewer3d">'
        f'<div class="viewer-bar">{views}<button type="button" data-view="reset">reset</button>'
        '<label>ellipsoids ×<select data-mag></select></label>'
        '<span class="viewer-hint">drag to rotate · wheel to zoom · shift-drag to pan</span></div>'
        '<canvas width="1000" height="560" aria-label="3D view of the reconstructed edges"></canvas>'
        '<div class="viewer-tip" hidden></div>'
        "<noscript><p>The 3D view needs JavaScript.</p></noscript>"
        "</div>"
    )
    mag = scene["mag"]
    if scene["features"]:
        ell = (f"Ellipsoids are the k = 2 error ellipsoids of every few points ({n_ell} of {n_pts} shown points), "
               f"magnified {mag}× so that they are visible at the part's scale (the points themselves are not "
               "magnified)." if mag else "No point covariances were given, so no ellipsoids are drawn.")
    else:
        ell = "No reconstructed points were given: only the CAD edges are drawn."
    frame = "; the \"camera\" view looks from the left camera" if "camera" in scene["views"] else ""
    caption = (
        f"Reconstructed 3D points (dots, coloured by decision) over the nominal CAD edges (grey), part frame, "
        f"mm{frame}. {ell} Drag to rotate, wheel to zoom; the buttons restore fixed views."
    )
    return Figure("scene", title, "Fig. 7", body=body, caption=caption, scene=scene)


# --------------------------------------------------------------------------------------------


def build_figures(figures, report=None):
    """All figures of the report for a ``figures`` dict; a list of Figure.

    A figure that cannot be drawn is replaced by a note with the reason rather
    than losing the whole report.

    Parameters
    ----------
    figures : dict
        Every key optional; lists may be empty, arrays may be lists of numbers,
        non-finite values are dropped.

        - ``left``, ``right``: ndarray (H, W), uint8 or uint16, the grey images
          as loaded (distorted, full resolution); (H, W, 3) colour is made grey.
        - ``overlays``: list of dicts, one per 2D fit: ``image`` ("left" or
          "right"), ``xy`` ndarray (N, 2), the fitted polyline in distorted
          pixels of that image (OpenCV: the top-left pixel's centre is 0, 0),
          ``kind`` ("line", "circle", "arc"), ``label`` (CAD id, "" if
          unmatched), ``status`` ("pass", "fail", "inconclusive", "unmatched",
          "measured").
        - ``residuals``: list of dicts, one per 2D fit: ``label``, ``image``,
          ``residuals`` ndarray (M,), signed orthogonal residuals of the fitted
          edge points, px, and ``sigma``, their predicted standard deviation, px.
        - ``points3d``: list of dicts, one per feature: ``label``, ``points``
          ndarray (M, 3), part frame, mm, ``covs`` ndarray (M, 3, 3), mm^2,
          ``status`` as in ``overlays``.
        - ``cad_edges``: list of dicts: ``label``, ``polyline`` ndarray (K, 3),
          the nominal CAD edge, part frame, mm.
        - ``views``: several views only, one dict per view: ``name``,
          ``image`` (its left image) and ``overlays`` (as above, of that
          image).
    report : dict, optional
        The report.json dict; its registration's ``part_to_camera`` puts the
        point figures' axes and the viewer in the left camera frame.

    Returns
    -------
    list of Figure
    """
    if not figures:
        return []
    reg = (report or {}).get("registration") or {}
    part_to_camera = reg.get("part_to_camera") if isinstance(reg, dict) else None
    out = []
    makers = (
        ("images", "Fig. 3", "Fitted edges in both images", lambda: image_figure(figures)),
        ("residuals", "Fig. 4", "Fit residuals", lambda: residual_figure(figures)),
        ("sigmas", "Figs. 5-6", "Standard deviations of the 3D points", lambda: sigma_figure(figures, part_to_camera)),
        ("scene", "Fig. 7", "Reconstructed 3D edges", lambda: scene_figure(figures, part_to_camera)),
    )
    if figures.get("views"):
        makers = (("views", "", "The views", lambda: view_strip_figure(figures)),) + makers
    for key, paper, title, make in makers:
        try:
            out.append(make())
        except Exception as exc:  # a figure is never worth the whole report
            out.append(Figure(key, title, paper, note=f"{title}: could not be drawn ({type(exc).__name__}: {exc})."))
    return out


def scene_json(scene):
    """The scene as JSON text safe inside ``<script type="application/json">``."""
    text = json.dumps(scene, separators=(",", ":"), allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")
