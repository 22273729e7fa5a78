"""Monte Carlo check of the 3D features' first-order covariances (JCGM 101).

The input quantities are drawn from their stated distributions and the
matching-free part of the chain is repeated for every draw: the matched
features' edge points (distorted pixels) are displaced across the edge by
Gaussian errors with their standard uncertainties and the along-edge
correlation of smoothed noise (``exp(-d^2 / (4 l^2))`` between points at
distance d, l the edge filter's sigma, as the sandwich covariances assume),
and the background correction of the points of rims by its own noise
(correlated over :func:`partinspect.vision.rim_errors.correction_corr_length`);
the calibration parameters with a standard uncertainty are drawn
independently; the points are mapped to ideal pixels again and the
two-view 3D fit redone from the nominal solution. The covariance of the
outputs over the draws is the Monte Carlo covariance, set beside the
first-order one.

References
----------
.. [1] JCGM 101:2008, Evaluation of measurement data -- Supplement 1 to the
       GUM: propagation of distributions using a Monte Carlo method.
.. [2] JCGM 100:2008, Guide to the expression of uncertainty in
       measurement.
"""

from dataclasses import dataclass, replace

import numpy as np

from partinspect.vision.fit3d import fit_circle_3d, fit_line_3d
from partinspect.vision.edges import BACKGROUND_POSITION_COUPLING
from partinspect.vision.calibration_uncertainty import perturbed_calibration, uncertainty_directions
from partinspect.vision.rim_errors import correction_corr_length, correction_std_of, coupled_noise

from partinspect.vision.stereo import feature_views
__all__ = ["MonteCarloFeature", "monte_carlo", "correlated_normal_errors", "with_monte_carlo_covariances"]


@dataclass(frozen=True)
class MonteCarloFeature:
    """Monte Carlo and first-order uncertainty of one 3D feature.

    Attributes
    ----------
    feature : int
        Index into ``StereoResult.features``.
    kind : str
    draws : int
        Number of Monte Carlo trials that converged.
    samples : ndarray, shape (draws, 6) or (draws, 7)
        The parameters of each trial: (point, direction) or (center,
        normal, radius), rig frame, mm.
    mean : ndarray
        Their mean.
    cov_mc : ndarray
        Their covariance (the Monte Carlo covariance).
    cov_first_order : ndarray
        The first-order covariance of the same inputs, for comparison:
        ``Feature3D.param_cov`` less its systematic (Type B) part, and less
        its calibration part unless the calibration is drawn.
    std_ratio : ndarray
        ``sqrt(diag(cov_mc) / diag(cov_first_order))`` (NaN where the
        first-order variance is zero).
    """

    feature: int
    kind: str
    draws: int
    samples: np.ndarray
    mean: np.ndarray
    cov_mc: np.ndarray
    cov_first_order: np.ndarray
    std_ratio: np.ndarray


def correlated_normal_errors(xy, corr_length, size, rng):
    """Standard normal errors correlated along an edge.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        The points, px.
    corr_length : float or None
        Correlation length l, px: correlation ``exp(-d^2 / (4 l^2))``.
    size : int
        Number of independent draws.
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (size, N)
    """
    n = len(xy)
    z = rng.standard_normal((size, n))
    if not corr_length:
        return z
    d2 = ((xy[:, None, :] - xy[None, :, :]) ** 2).sum(-1)
    C = np.exp(-d2 / (4.0 * corr_length * corr_length))
    w, V = np.linalg.eigh(C)
    # Eigen-decomposition rather than Cholesky: C is numerically
    # semi-definite for densely spaced points.
    A = V * np.sqrt(np.clip(w, 0.0, None))
    return z @ A.T


def _params(fit, kind, ref):
    if kind == "line":
        d = fit.direction if fit.direction @ ref[3:6] >= 0 else -fit.direction
        return np.r_[fit.point, d]
    n = fit.normal if fit.normal @ ref[3:6] >= 0 else -fit.normal
    return np.r_[fit.center, n, fit.radius]


def monte_carlo(result, calib, features=None, *, draws=200, seed=0, image_noise=True, calibration=True):
    """Monte Carlo covariances of 3D features of a stereo measurement.

    Parameters
    ----------
    result : StereoResult
        From :func:`partinspect.vision.stereo.measure_stereo`.
    calib : StereoCalibration
        The calibration used (its ``std`` is drawn from when
        ``calibration``).
    features : sequence of int, optional
        Indices into ``result.features``; default all.
    draws : int
        Monte Carlo trials per feature.
    seed : int
        Seed of ``numpy.random.default_rng``.
    image_noise, calibration : bool
        Which inputs to draw.

    Returns
    -------
    list of MonteCarloFeature
    """
    rng = np.random.default_rng(seed)
    directions = uncertainty_directions(calib) if calibration else []
    out = []
    for k in range(len(result.features)) if features is None else features:
        f3 = result.features[k]
        fl, fr = result.left.features[f3.left], result.right.features[f3.right]
        # A feature carries the filter scale it was found with (the adaptive
        # rounds may have found it with another than its neighbours).
        corr_length = fl.corr_length
        kind = "line" if f3.kind == "line" else "arc"
        ref = f3.params
        noises, corrections = [], []
        for f in (fl, fr):
            normal = f.edge_normal
            s = np.sqrt(np.einsum("ni,nij,nj->n", normal, f.cov_uv, normal))
            z = correlated_normal_errors(f.uv, corr_length, draws, rng) if image_noise else np.zeros((draws, len(f.uv)))
            noises.append((z * s)[:, :, None] * normal[None])
            # The background correction of a rim's points is read from the
            # same noisy image: its noise is drawn too, the share that comes
            # from the points' own errors (BACKGROUND_POSITION_COUPLING times
            # their average along the edge) and the rest, correlated over
            # its own, longer length.
            offset, std = getattr(f, "background_offset", None), getattr(f, "background_std", None)
            if image_noise and kind == "arc" and offset is not None:
                _, rest, w = coupled_noise(f.uv, s, std, corr_length)
                own = BACKGROUND_POSITION_COUPLING * (w @ (z * s).T).T
                zc = correlated_normal_errors(f.uv, correction_corr_length(corr_length), draws, rng)
                corrections.append(offset[None] + (own + zc * rest)[:, :, None] * normal[None])
            else:
                corrections.append(None)
        stds = (correction_std_of(fl, corr_length), correction_std_of(fr, corr_length))
        samples = []
        for t in range(draws):
            cal = calib
            if directions:
                cal = perturbed_calibration(calib, _calibration_draw(directions, rng))
            fl_t, fr_t = (f if c is None else replace(f, background_offset=c[t])
                          for f, c in ((fl, corrections[0]), (fr, corrections[1])))
            views = feature_views(fl_t, fr_t, corr_length, cal, uv=(fl.uv + noises[0][t], fr.uv + noises[1][t]),
                                  correction_std=stds)
            try:
                if kind == "line":
                    fit = fit_line_3d(views, f3.point, f3.direction)
                else:
                    fit = fit_circle_3d(views, f3.center, f3.normal, f3.radius)
            except (np.linalg.LinAlgError, ValueError):
                continue
            samples.append(_params(fit, kind, ref))
        samples = np.array(samples)
        cov = np.cov(samples, rowvar=False)
        # The Monte Carlo draws the random inputs (image noise, calibration);
        # the Type B rim-shading part of param_cov is not drawn, so it is
        # left out of the comparison.
        sys_cov = getattr(f3, "param_cov_systematic", None)
        fo = f3.param_cov if sys_cov is None else f3.param_cov - sys_cov
        if not calibration:
            fo = fo - f3.param_cov_calibration
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.sqrt(np.diag(cov) / np.diag(fo))
        out.append(MonteCarloFeature(int(k), f3.kind, len(samples), samples, samples.mean(axis=0), cov, fo, ratio))
    return out


def with_monte_carlo_covariances(stereo, calib, draws):
    """The stereo result with Monte Carlo covariances in place of the first-order ones.

    Returns the new result and the ratios of Monte Carlo to first-order
    standard uncertainties of the image noise's part over all parameters
    (for the report). The image noise is drawn; the calibration's part
    stays first order (``G G^T`` of the feature's ``calibration_response``),
    for the calibration's error is one error shared by every feature, and
    the registration and the characteristics need it as that
    (:func:`monte_carlo` with ``calibration=True`` checks its first order
    feature by feature); the systematic (Type B) part is not sampled and
    is added unchanged.
    """
    from dataclasses import replace

    feats, ratios = list(stereo.features), []
    for mc in monte_carlo(stereo, calib, draws=draws, seed=0, calibration=False):
        f = feats[mc.feature]
        C = 0.5 * (mc.cov_mc + mc.cov_mc.T) + f.param_cov_calibration
        # The draws cover the image noise only; the Type B part (rim shading) is added as it was.
        if getattr(f, "param_cov_systematic", None) is not None:
            C = C + f.param_cov_systematic
        extra = {"radius_std": float(np.sqrt(C[6, 6]))} if f.kind != "line" else {}
        feats[mc.feature] = replace(f, param_cov=C, covariance=C[:3, :3], axis_cov=C[3:6, 3:6], **extra)
        ratios.extend(r for r in mc.std_ratio if np.isfinite(r))
    return replace(stereo, features=tuple(feats)), np.array(ratios)


def _calibration_draw(directions, rng):
    """One draw of the calibration's parameter shifts: ``sum_j z_j d_j``, z standard normal."""
    draw = {}
    for d, z in zip(directions, rng.standard_normal(len(directions))):
        for lab, v in d.items():
            draw[lab] = draw.get(lab, 0.0) + z * v
    return draw
