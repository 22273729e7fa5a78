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

    python3 benchmarks/bench_psf_shape.py
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
from tests.vision.synthetic import Disc, render_clean, render_optics  # noqa: E402

SIZE = 220


def corrected_error(img, xc, yc, R):
    """(radius error after the correction, the correction), px."""
    e = edge_points(img, 1.0, noise=0.5)
    sel = np.abs(np.hypot(e.xy[:, 0] - xc, e.xy[:, 1] - yc) - R) < 3
    xy, cov = e.xy[sel], e.cov[sel]
    fit = fit_ellipse(xy, cov)
    fixed = fit_ellipse(deblurred(xy, fit, float(np.median(e.width[sel]))), cov, start=fit.params)
    r0, r1 = np.mean(fit.params[2:4]), np.mean(fixed.params[2:4])
    return r1 - R, r1 - r0


def kernels():
    yield "Gaussian PSF 0.6 px, then pixels", lambda s: render_optics(s, SIZE, SIZE, 40.0, blur=0.6)
    yield "Gaussian PSF 1.2 px, then pixels", lambda s: render_optics(s, SIZE, SIZE, 40.0, blur=1.2)
    for r in (0.8, 1.2, 1.6, 2.0):
        yield f"pixels, then a disc of {r} px", lambda s, r=r: cv2.filter2D(
            render_clean(s, SIZE, SIZE, 40.0), -1, _disc_kernel(r), borderType=cv2.BORDER_REPLICATE)
    for g in (0.5, 0.7, 1.0):
        yield f"pixels, then a digital Gaussian {g} px", lambda s, g=g: cv2.GaussianBlur(render_clean(s, SIZE, SIZE, 40.0), (0, 0), g)


def main():
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
