"""Baseline for bench_report.py: the report's two plots as matplotlib drew them.

A verbatim copy of ``residual_figure`` and ``sigma_figure`` (with their
matplotlib helpers ``_svg_uri``, ``_mpl_figure``, ``_RC``; the others are
still the figures module's own) from
``partinspect/reports/figures.py`` at commit 634b1d5, before they were
written directly as SVG (``partinspect/reports/svgplot.py``). Kept only to
measure against; production code does not import it. Needs matplotlib.
"""

import base64
import io
import math

import numpy as np

from partinspect.reports.figures import MAX_RESIDUAL_PANELS, Figure, _img_tag, _point_sigmas


def _svg_uri(fig):
    """A matplotlib Figure as a deterministic SVG data URI (text as paths: no font needed)."""
    import matplotlib

    buf = io.StringIO()
    with matplotlib.rc_context({"svg.hashsalt": "partinspect", "svg.fonttype": "path"}):
        fig.savefig(buf, format="svg", metadata={"Date": None, "Creator": None})
    return "data:image/svg+xml;base64," + base64.b64encode(buf.getvalue().encode("utf-8")).decode("ascii")


def _mpl_figure(width_in, height_in):
    """A matplotlib Figure on the Agg canvas, without pyplot's global state."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=(width_in, height_in), dpi=100)
    FigureCanvasAgg(fig)
    return fig


_RC = {
    "font.size": 8,
    "axes.titlesize": 8,
    "axes.labelsize": 8,
    "xtick.labelsize": 7,
    "ytick.labelsize": 7,
    "legend.fontsize": 7,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.edgecolor": "#5b6474",
    "axes.linewidth": 0.6,
    "xtick.color": "#5b6474",
    "ytick.color": "#5b6474",
    "text.color": "#1d2330",
    "axes.labelcolor": "#1d2330",
}


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
    import matplotlib

    from matplotlib.ticker import MaxNLocator

    ncols = 4 if len(shown) > 3 else len(shown)
    nrows = math.ceil(len(shown) / ncols)
    ratios = []
    with matplotlib.rc_context(_RC):
        fig = _mpl_figure(10.0, 0.3 + 1.75 * nrows)
        axes = fig.subplots(nrows, ncols, squeeze=False)
        for ax in axes.ravel()[len(shown):]:
            ax.set_visible(False)
        for ax, (label, image, res, sigma) in zip(axes.ravel(), shown):
            sigma = float(sigma) if sigma is not None and np.isfinite(sigma) and sigma > 0 else None
            rms = float(np.sqrt(np.mean(res**2)))
            scale = sigma or rms or 1.0
            half = max(4.0 * scale, float(np.percentile(np.abs(res), 99.5)))
            half = min(half, 8.0 * scale) if sigma else half
            nb = int(np.clip(np.sqrt(res.size), 8, 36))
            # One filled step patch per panel, not a rectangle per bar: the SVG
            # of some forty panels is written several times faster.
            counts, edges = np.histogram(np.clip(res, -half, half), bins=nb, range=(-half, half), density=True)
            ax.stairs(counts, edges, fill=True, color="#9fb3c8")
            ax.stairs(counts, edges, color="#6f87a0", linewidth=0.6)
            text = f"n = {res.size}\nrms {rms:.3g} px"
            colour = "#1d2330"
            if sigma:
                x = np.linspace(-half, half, 201)
                ax.plot(x, np.exp(-0.5 * (x / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi)), color="#1d2330", lw=1.1)
                ratio = rms / sigma
                ratios.append(ratio)
                text += f"\nσ {sigma:.3g} px\nrms/σ {ratio:.2f}"
                if not 0.8 <= ratio <= 1.25:
                    colour = "#b3261e"
            ax.text(0.98, 0.97, text, transform=ax.transAxes, ha="right", va="top", fontsize=6.5, color=colour,
                    linespacing=1.25)
            ax.set_title(f"{label or 'unmatched'} ({image})" if image else (label or "unmatched"), loc="left")
            ax.set_yticks([])
            ax.spines["left"].set_visible(False)
            ax.xaxis.set_major_locator(MaxNLocator(5, symmetric=True))
        for ax in axes[-1]:
            ax.set_xlabel("residual, px")
        # Fixed margins, not tight_layout: that costs a whole extra draw.
        h = 0.3 + 1.75 * nrows
        fig.subplots_adjust(left=0.015, right=0.99, bottom=0.42 / h, top=1 - 0.22 / h, wspace=0.08, hspace=0.5 / 1.45)
        uri = _svg_uri(fig)
    note = None
    if len(items) > len(shown):
        note = f"Showing the first {len(shown)} of {len(items)} fits; the others are left out to keep the report short."
    summary = ""
    if ratios:
        inside = sum(0.8 <= q <= 1.25 for q in ratios)
        summary = (
            f" Median rms/σ over the {len(ratios)} fits shown: {np.median(ratios):.2f}; "
            f"{inside} of {len(ratios)} lie within 0.8-1.25 (outside: red)."
        )
    caption = (
        "Signed orthogonal distances of the edge points from their fitted line or ellipse (bars, "
        "normalised) and the normal density that the noise model predicts for them (curve). "
        "rms/σ near 1 means the predicted uncertainty, which every measured number inherits, is honest."
        + summary
    )
    body = _img_tag(uri, "histograms of fit residuals")
    return Figure("residuals", title, "Fig. 4", body=body, caption=caption, note=note)


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
    axes_names = ("X", "Y", "Z")
    colours = ("#3b6fb6", "#2f9e6e", "#c2412d")
    import matplotlib

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
    with matplotlib.rc_context(_RC):
        fig = _mpl_figure(10.0, 3.0)
        gs = fig.add_gridspec(1, 2, width_ratios=(2.1, 1))
        ax = fig.add_subplot(gs[0, 0])
        for j in range(3):
            ax.plot(idx_plot, sig_plot[:, j] * 1000.0, color=colours[j], lw=0.8, label=f"σ{axes_names[j]}")
        for b in bounds[1:-1]:
            ax.axvline(b - 0.5, color="#d8dde6", lw=0.6, zorder=0)
        ax.set_ylim(0, None)
        ax.set_xlim(-0.5, n - 0.5)
        ax.set_xlabel(f"point, feature after feature ({len(labels)} features, {n} points)")
        ax.set_ylabel("standard deviation, µm")
        ax.set_title(f"(a) σ per point, {frame}", loc="left")
        ax.legend(loc="upper right", ncols=3, frameon=False)
        ax2 = fig.add_subplot(gs[0, 1])
        hi = max(float(np.max(sig)) * 1000 * 1.05, 1e-6)
        bins = np.linspace(0, hi, 40)
        for j in range(3):
            ax2.hist(sig[:, j] * 1000, bins=bins, histtype="stepfilled", alpha=0.25, color=colours[j])
            ax2.hist(sig[:, j] * 1000, bins=bins, histtype="step", lw=1.1, color=colours[j],
                     label=f"σ{axes_names[j]}: median {med[j]:.3g} µm")
        ax2.set_xlim(0, hi)
        ax2.set_xlabel("standard deviation, µm")
        ax2.set_ylabel("points")
        ax2.set_title("(b) distribution", loc="left")
        ax2.legend(loc="upper right", frameon=False)
        fig.subplots_adjust(left=0.06, right=0.99, bottom=0.15, top=0.91, wspace=0.22)
        uri = _svg_uri(fig)
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
    body = _img_tag(uri, "standard deviations of 3D points along X, Y, Z")
    return Figure("sigmas", title, "Figs. 5-6", body=body, caption=caption)

