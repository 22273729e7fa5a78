"""Systematic error of the sub-pixel edge estimator on exact straight edges, by direction and optical blur.

No noise: what remains is the estimator's own bias, a function of where
the edge crosses the pixel it is read in (its sub-pixel phase). Along a
straight edge that phase steps by ``tan a`` per pixel of the dominant
axis (``a`` the edge's angle to it), so the bias repeats every
``1 / frac(tan a)`` points: a short ripple for most directions, a slow
pattern near an axis and near 45 deg, which a line fit does not absorb and
a straightness zone sees as form. The edges are formed as in a camera (a
Gaussian PSF of ``blur`` px, then integration over each pixel's square:
``tests.vision.synthetic.render_optics``). The table gives, per blur and
edge angle, the RMS of the points' distances to the true line (``all``)
and of their 15-point running mean (``slow``: the part a form zone sees),
for the estimator as used (the vertex of the parabola through the
logarithms of the three gradient magnitudes) and, as the baseline in the
same run, the plain parabola through the magnitudes (Devernay's).

    python3 benchmarks/bench_subpixel.py [--blurs 0.4 0.6 0.8 1.0]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import partinspect.vision.edges as edges  # noqa: E402
from tests.vision.synthetic import HalfPlane, render  # noqa: E402

ANGLES = (0.5, 2.0, 5.0, 10.0, 20.0, 30.0, 40.0, 42.0, 43.0, 44.0, 44.5, 45.0)
SIZE = 240
MARGIN = 30
RUN = 15  # points in the running mean ("slow")


def parabola_offset(a, b, c):
    """Devernay's vertex of the parabola through the magnitudes, and its Jacobian."""
    D = a - 2.0 * b + c
    J = np.column_stack([(c - b), (a - c), (b - a)]) / (D * D)[:, None]
    return (a - c) / (2.0 * D), J


ESTIMATORS = {"as used": None, "parabola": parabola_offset}


def residuals(angle_deg, blur, offset=0.3):
    """Signed distances (px) of the edge points of one exact straight edge to it, in order along it."""
    th = np.radians(angle_deg)
    a, b = -np.sin(th), np.cos(th)
    c0 = SIZE / 2.0 + offset
    hp = HalfPlane(a, b, -(a * c0 + b * (c0 + 0.4)))
    img = render([(hp, 160.0)], SIZE, SIZE, background=40.0, blur=blur, noise=0.0, quantise=False)
    ep = edges.edge_points(img, 1.0, noise=0.5)
    xy = ep.xy
    d = hp.distance(xy)
    ok = (np.all((xy > MARGIN) & (xy < SIZE - MARGIN), axis=1)) & (np.abs(d) < 1.0)
    s = xy[ok] @ np.array([np.cos(th), np.sin(th)])
    return d[ok][np.argsort(s)]


def figures(d):
    """(RMS about the mean, RMS of the running mean about the mean), px."""
    d = d - d.mean()
    slow = np.convolve(d, np.ones(RUN) / RUN, mode="valid")
    return float(np.sqrt(np.mean(d * d))), float(np.sqrt(np.mean(slow * slow)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blurs", type=float, nargs="+", default=[0.4, 0.6, 0.8, 1.0])
    args = ap.parse_args(argv)
    saved = edges._subpixel_offset
    print("systematic error of edge points on exact straight edges, px RMS (all / slow = %d-point running mean); "
          "sigma 1, no noise, %dx%d px" % (RUN, SIZE, SIZE))
    head = "blur  angle   " + "   ".join(f"{name:>17s}" for name in ESTIMATORS)
    print(head)
    print("-" * len(head))
    try:
        for blur in args.blurs:
            for ang in ANGLES:
                cells = []
                for estimator in ESTIMATORS.values():
                    edges._subpixel_offset = saved if estimator is None else estimator
                    cells.append("%.4f / %.4f" % figures(residuals(ang, blur)))
                print(f"{blur:4.1f}  {ang:5.1f}   " + "   ".join(f"{c:>17s}" for c in cells))
    finally:
        edges._subpixel_offset = saved


if __name__ == "__main__":
    main()
