"""What the curvature correction leaves of a rim's radius when the PSF is not Gaussian.

The edge detector's curvature bias on a rim is removed as ``width^2 kappa / 2``
(+ the sampling term, `partinspect.vision.correspondences.deblurred`), with
``width`` the edge profile's width read from the gradient's log-curvature at
its peak: exact for a Gaussian profile, where that width is the kernel's
second moment. A lens's PSF is not Gaussian: defocus makes it a disc
(pillbox), a digital blur on the pixel grid is a sampled kernel. For each
such kernel this prints, on exact area-integrated discs (no noise) of
several radii and sub-pixel positions, the radius error left after the
correction as a fraction of the correction itself. The largest |fraction|
over the kernels is the bound ``PSF_SHAPE_BOUND`` of
`partinspect.vision.stereo`, whose rectangular standard uncertainty is
carried as a Type B of every rim's radius.

With ``--ellipses`` it does the same on exact ellipses (semi-major axes
8-40 px, axis ratios 1-0.45, random angles and sub-pixel centres) under
pixel-domain Gaussian and disc kernels, the image formations that are exact
for any outline (the optics renderer blurs an ellipse by its osculating
circle), and fits the fraction left on the mean radius against
``W^2 <kappa^3> / <kappa>`` (W the edge profile's width, kappa the
ellipse's curvature, means over its arc length): the correction's second
order, which the discs, at ``W kappa`` below 0.15, do not reach.

    python3 benchmarks/bench_psf_shape.py [--ellipses]
"""

import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_formation import _disc_kernel  # noqa: E402
from partinspect.vision.correspondences import deblurred  # noqa: E402
from partinspect.vision.edges import edge_points  # noqa: E402
from partinspect.vision.fitting import fit_ellipse  # noqa: E402
from tests.vision.synthetic import Disc, Ellipse, render_clean, render_optics  # noqa: E402

SIZE = 220


def corrected_error(img, xc, yc, R):
    """(radius error after the correction, the correction), px, of a disc."""
    return ellipse_error(img, Disc(xc, yc, R), reach=3.0)[:2]


def kernels():
    yield "Gaussian PSF 0.6 px, then pixels", lambda s: render_optics(s, SIZE, SIZE, 40.0, blur=0.6)
    yield "Gaussian PSF 1.2 px, then pixels", lambda s: render_optics(s, SIZE, SIZE, 40.0, blur=1.2)
    for r in (0.8, 1.2, 1.6, 2.0):
        yield f"pixels, then a disc of {r} px", lambda s, r=r: cv2.filter2D(
            render_clean(s, SIZE, SIZE, 40.0), -1, _disc_kernel(r), borderType=cv2.BORDER_REPLICATE)
    for g in (0.5, 0.7, 1.0):
        yield f"pixels, then a digital Gaussian {g} px", lambda s, g=g: cv2.GaussianBlur(render_clean(s, SIZE, SIZE, 40.0), (0, 0), g)


def ellipse_error(img, shape, reach=2.5):
    """(mean semi-axis error after the correction, the correction there, the edge profile's width), px.

    The edge points within ``reach`` px of the outline are the rim's.
    """
    e = edge_points(img, 1.0, noise=0.5)
    sel = np.abs(shape.distance(e.xy)) < reach
    xy, cov, W = e.xy[sel], e.cov[sel], float(np.median(e.width[sel]))
    fit = fit_ellipse(xy, cov)
    fixed = fit_ellipse(deblurred(xy, fit, W), cov, start=fit.params)
    r0, r1 = np.mean(fit.params[2:4]), np.mean(fixed.params[2:4])
    return r1 - 0.5 * (shape.a + shape.b), r1 - r0, W


def curvature_moment(q, n=20000):
    """``<kappa^3> / <kappa> / kappa_max^2`` over the arc length of an ellipse of axis ratio q (scale-free)."""
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ds = np.hypot(np.sin(t), q * np.cos(t))
    kappa = q / ds**3
    return float(np.sum(ds * kappa**3) / np.sum(ds * kappa) / (1.0 / q**2) ** 2)


def ellipses(size=150):
    rng = np.random.default_rng(7)
    pixel = [("digital Gaussian 0.7 px", lambda im: cv2.GaussianBlur(im, (0, 0), 0.7)),
             ("digital Gaussian 1.0 px", lambda im: cv2.GaussianBlur(im, (0, 0), 1.0)),
             ("digital Gaussian 1.4 px", lambda im: cv2.GaussianBlur(im, (0, 0), 1.4)),
             ("disc 1.2 px", lambda im: cv2.filter2D(im, -1, _disc_kernel(1.2), borderType=cv2.BORDER_REPLICATE)),
             ("disc 2.0 px", lambda im: cv2.filter2D(im, -1, _disc_kernel(2.0), borderType=cv2.BORDER_REPLICATE))]
    rows = []
    print(f"{'image formation':26s} {'a px':>5s} {'b/a':>5s} {'W kappa_max':>11s} {'left / correction (3 draws)':>28s}")
    for name, form in pixel:
        for a in (8.0, 10.0, 12.0, 16.0, 24.0, 40.0):
            for q in (1.0, 0.8, 0.6, 0.45):
                moment = curvature_moment(q)
                f, x = [], []
                for _ in range(3):
                    xc, yc = size / 2 + rng.uniform(-0.5, 0.5, 2)
                    shape = Ellipse(xc, yc, a, a * q, rng.uniform(0.0, np.pi))
                    err, corr, W = ellipse_error(form(render_clean([(shape, 200.0)], size, size, 40.0)), shape)
                    f.append(err / corr)
                    x.append((W * a / (a * q) ** 2) ** 2 * moment)
                rows.append((float(np.mean(x)), float(np.mean(f))))
                print(f"{name:26s} {a:5.1f} {q:5.2f} {np.sqrt(np.mean(x) / moment):11.2f} "
                      f"{np.mean(f):+10.3f} ({np.min(f):+.3f} .. {np.max(f):+.3f})")
    x, y = np.array(rows).T
    c = np.linalg.lstsq(np.c_[np.ones_like(x), x], y, rcond=None)[0]
    left = y - (c[0] + c[1] * x)
    print(f"\nfraction left = {c[0]:+.3f} + {c[1]:.3f} W^2 <kappa^3>/<kappa>  (residual SD {left.std():.3f}, "
          f"largest {np.abs(left).max():.3f}; {len(x)} cells)")


def main():
    if "--ellipses" in sys.argv[1:]:
        return ellipses()
    rng = np.random.default_rng(3)
    worst = 0.0
    print(f"{'image formation':40s} {'left after correction / correction (radii 15-80 px, 3 positions)':>20s}")
    for name, form in kernels():
        fractions = []
        for R in (15.0, 30.0, 80.0):
            for _ in range(3):
                xc, yc = SIZE / 2 + rng.uniform(-0.5, 0.5, 2)
                err, corr = corrected_error(form([(Disc(xc, yc, R), 200.0)]).astype(np.float64), xc, yc, R)
                fractions.append(err / corr)
        f = np.array(fractions)
        worst = max(worst, float(np.max(np.abs(f))))
        print(f"{name:40s} mean {f.mean():+.3f}  range {f.min():+.3f} .. {f.max():+.3f}")
    print(f"\nlargest |fraction|: {worst:.3f}  (PSF_SHAPE_BOUND)")


if __name__ == "__main__":
    main()
