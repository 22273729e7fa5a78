"""The right ellipse a rim's left points take their partners on (:func:`partinspect.vision.arc_partner.as_fitted`)."""

import numpy as np

from partinspect.vision.fit3d import View
from partinspect.vision.fitting import fit_ellipse
from partinspect.vision.ideal import IdealPoints
from partinspect.vision.imagefeatures import ImageFeature
from partinspect.vision.arc_partner import as_fitted, random_covariance

TRUE = np.array([1566.4, 820.8, 43.8, 33.2, 0.18])
"""A 5 mm hole's rim as the right camera of the robustness run's gen-015 saw it, px."""


def _ellipse(params, t):
    xc, yc, a, b, th = params
    c, s = np.cos(th), np.sin(th)
    xy = np.c_[xc + a * np.cos(t) * c - b * np.sin(t) * s, yc + a * np.cos(t) * s + b * np.sin(t) * c]
    nl = np.c_[np.cos(t) / a, np.sin(t) / b]
    n = np.c_[nl[:, 0] * c - nl[:, 1] * s, nl[:, 0] * s + nl[:, 1] * c]
    return xy, n / np.linalg.norm(n, axis=1)[:, None]


def _rim(shift, sigma=0.02):
    """A whole rim, one point per px, with a 30 degree stretch moved across the edge by ``shift`` px.

    As gen-015's right image showed it: where the wall's shading beside
    the rim reaches a second step (the far wall's shadow through the hole)
    the background correction moved 14 points by about -0.37 px, and
    their Type B bound said 0.23 px; elsewhere 0.01-0.05 px.

    Returns the ImageFeature (fitted as the image chain fits it: by the
    noise alone), its View and the offsets.
    """
    tt = np.linspace(0.0, 2 * np.pi, 20000, endpoint=False)
    loc, _ = _ellipse(TRUE, tt)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(loc, axis=0), axis=1))]
    t = np.interp(np.arange(0.0, arc[-1], 1.0), arc, tt)
    xy, n = _ellipse(TRUE, t)
    stretch = np.abs(((t - 3.0) + np.pi) % (2 * np.pi) - np.pi) < np.deg2rad(15.0)
    off = np.where(stretch, shift, 0.0)
    xy = xy + off[:, None] * n
    s = np.full(len(t), sigma)
    bias = np.where(stretch, 0.23, 0.02)
    along = np.c_[-n[:, 1], n[:, 0]]
    cov = (s ** 2)[:, None, None] * n[:, :, None] * n[:, None, :] + 1e-6 * along[:, :, None] * along[:, None, :]
    ideal = IdealPoints(xy, cov, n, s, np.repeat(np.eye(2)[None], len(t), axis=0))
    fit = fit_ellipse(xy, cov, corr_length=1.0, start=TRUE)
    f = ImageFeature("arc", (0,), np.arange(len(t)), xy, cov, ideal, fit, 1.2, 1)
    view = View(xy, s, np.eye(3, 4), 1.0, bias, 0.2 * TRUE[2], 0.5 * s, 2.2)
    return f, view, off


def _off_rim(params):
    """Largest distance, px, of the ellipse ``params`` from the true rim."""
    ref, _ = _ellipse(TRUE, np.linspace(0, 2 * np.pi, 720, endpoint=False))
    other, _ = _ellipse(params, np.linspace(0, 2 * np.pi, 40000, endpoint=False))
    return float(np.sqrt(((ref[:, None] - other[None]) ** 2).sum(-1).min(1)).max())


def test_a_stretch_its_type_b_flags_does_not_bend_the_partner_ellipse():
    f, view, _ = _rim(-0.37)
    got = as_fitted(f, view, 1.0)
    # Weighted by the image noise alone (the image chain's fit, and the
    # partner ellipse before), the 14 points bend the whole ellipse by a
    # tenth of a pixel: near the epipolar tangents that moved gen-015's
    # triangulated rim by up to 0.2 mm and read its circularity 15 u high.
    assert _off_rim(f.fit.params) > 0.08
    assert _off_rim(got.fit.params) < 0.02
    assert len(got.fit.residuals) == len(f.ideal.xy)  # weighted down, not left out


def test_random_covariance_is_the_spread_of_the_weighted_fit_over_noise_draws():
    from partinspect.vision.pointerrors import correlated_field

    f, view, off = _rim(0.0)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(view.xy, axis=0), axis=1))]
    rng = np.random.default_rng(5)
    got = as_fitted(f, view, 1.0)
    draws = []
    for _ in range(300):
        e = (correlated_field(s, 1.0, rng, 1)[0] * view.sigma
             + correlated_field(s, 2.2, rng, 1)[0] * view.sigma_correction)
        moved = view.__class__(**{**view.__dict__, "xy": view.xy + e[:, None] * f.ideal.normal})
        draws.append(as_fitted(f, moved, 1.0).fit.params)
    emp = np.cov(np.array(draws)[:, :4].T)
    stated = got.fit.cov[:4, :4]
    ratio = np.sqrt(np.diag(emp) / np.diag(stated))
    # 300 draws: a standard deviation to about 4 %.
    assert np.all(np.abs(ratio - 1.0) < 0.15), ratio
    # The image chain's own covariance, weighted as the points' noise alone, is not the weighted fit's.
    assert np.any(np.abs(np.sqrt(np.diag(f.fit.cov[:4, :4]) / np.diag(stated)) - 1.0) > 0.15)


def test_without_a_type_b_the_random_covariance_is_the_fits_own():
    f, view, _ = _rim(0.0)
    plain = View(view.xy, view.sigma, view.P, 1.0)
    fit = fit_ellipse(view.xy, view.sigma ** 2, corr_length=1.0, start=TRUE)
    got = random_covariance(fit, plain, np.arange(len(view.xy)))
    assert np.allclose(got[:4, :4], fit.cov[:4, :4], rtol=1e-6, atol=0.0)
