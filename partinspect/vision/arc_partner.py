"""A rim's right ellipse refitted to its corrected points, and the correspondences taken on it.

A rim's 3D fit uses its points corrected for the shading beside them
(:mod:`partinspect.vision.rim_errors`); the correspondences that the form
is judged on must place each left point's partner on the right ellipse
through the same corrected points, each weighted by its whole standard
uncertainty as the 3D fit weighs it (:func:`as_fitted`), with the random
part of that ellipse's covariance (:func:`random_covariance`) for the
point errors' model.

Frames: ideal pixels.

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed.
.. [2] Chauvenet's criterion: Taylor, J. R. (1997). An Introduction to
       Error Analysis, 2nd ed., section 6.2.
"""

from dataclasses import replace

import numpy as np

from partinspect.vision.correspondences import correspond
from partinspect.vision.fitting import ellipse_geometry, fit_ellipse, information_matrices
from partinspect.vision.imagefeatures import MAX_OUTLIER_FRACTION, chauvenet_z
from partinspect.vision.rim_errors import form_view

__all__ = ["corrected_correspondences", "as_fitted", "random_covariance"]


def corrected_correspondences(fl, fr, views, corr, geo, corr_length):
    """An arc's correspondences redone on its points as the 3D fit uses them (:func:`as_fitted`).

    Those are the triangulated points the form is judged on, the right
    ellipse's outlier screen judging each point by the form's point-level
    Type B (:func:`~partinspect.vision.rim_errors.form_view`). The 3D fit
    itself is started from the correspondences as found (``corr``): a
    start from the corrected ones can send a short arc to another local
    minimum. Lines, and arcs left with fewer than 6 corrected
    correspondences, keep ``corr``.
    """
    if fl.kind != "arc":
        return corr
    # The partner ellipse's outlier screen judges single points: by the
    # single points' Type B, as the form they are judged on (form_view).
    new = correspond(fl, as_fitted(fr, form_view(views[1], fr), corr_length), geo, xy=views[0].xy)
    return new if len(new) >= 6 else corr


def as_fitted(f, view, corr_length):
    """An arc with the points of its fit3d ``view`` (corrected as :func:`~partinspect.vision.stereo.feature_views` does) and its ellipse refitted to them.

    The correspondences place each left point's partner on the right
    fitted ellipse: fitted to the points as found, a rim's shading bends
    that ellipse away from the corrected rim the 3D fit measures, and the
    triangulated points (whose zone is the circularity) with it. Lines
    are returned as they are (their points are not corrected).

    Each point is weighted by its whole standard uncertainty
    (``view.total_sigma``: noise, the correction's noise and the Type B
    rest), as the 3D fit weighs it. Where a second step lies within the
    background reading's reach (the far wall's shadow seen through a hole,
    a countersink's cone) the correction moves a stretch of the rim by
    tenths of a pixel, and its Type B bound says so; weighted by the image
    noise alone such a stretch bends the whole ellipse, and near the
    epipolar tangents a partner moved along the ellipse moves its 3D point
    tens of times as far (validation.md, "Rims' partner ellipse").

    Points farther from the refitted ellipse than Chauvenet's threshold
    times their whole standard uncertainty are left out of it, worst
    first and the ellipse refitted each time, at most
    ``MAX_OUTLIER_FRACTION`` of them; the feature keeps all its points
    (they still say where the right image sees the edge). Where a hole seen
    very obliquely has its rim fade at an ellipse's tip, the contour can run
    on there through points off the rim by more than their whole standard
    uncertainty; the image fit, which judges residuals by the image
    noise alone and scales its threshold by their spread, keeps them, and
    they bend the right ellipse on which every partner lies.

    Returns
    -------
    EdgeFeature
        Its ``fit.cov`` is the random part of the ellipse's covariance
        (:func:`random_covariance`), what the point errors' model
        (:mod:`partinspect.vision.pointerrors`) draws anew for every image.
    """
    if f.kind != "arc":
        return f
    total = np.asarray(view.total_sigma, float) * np.ones(len(view.xy))
    keep = np.arange(len(view.xy))
    budget = int(MAX_OUTLIER_FRACTION * len(keep))
    start = f.fit.params
    while True:
        fit = fit_ellipse(view.xy[keep], total[keep] ** 2, corr_length=corr_length, start=start)
        z = np.abs(fit.residuals) / total[keep]
        worst = int(np.argmax(z))
        if budget == 0 or z[worst] <= chauvenet_z(len(keep)):
            break
        keep = np.delete(keep, worst)
        budget -= 1
        start = fit.params
    cov = random_covariance(fit, view, keep)
    return replace(f, ideal=replace(f.ideal, xy=view.xy), fit=replace(fit, cov=cov))


def random_covariance(fit, view, keep):
    """The random part of the covariance of an ellipse fitted to ``view``'s points ``keep``, each weighted by its whole uncertainty.

    The fit is a weighted regression, weights ``1 / t^2`` with ``t`` the
    points' ``total_sigma``, whose random errors are the image noise
    (``view.sigma``, correlated along the edge over ``view.corr_length``)
    and the correction's noise (over ``view.correction_corr_length``),
    independent of each other: their part of the estimate's covariance is
    the sandwich ``S^-1 (H_w^T D R D H_w) S^-1`` summed over the two, with
    ``H_w`` the rows ``h_i / t_i``, ``S = H_w^T H_w`` and ``D`` the errors'
    standard uncertainties over ``t`` [1]_. The Type B rest is not in it:
    it is fixed for the scene, and the weights already keep it out of the
    ellipse as far as the other points allow.

    Parameters
    ----------
    fit : EllipseFit
        Of the points ``view.xy[keep]``, ideal px.
    view : View
    keep : ndarray of int
        The points the fit used.

    Returns
    -------
    ndarray, shape (5, 5)
        px^2, px rad, rad^2 as ``EllipseFit.cov``; a circle's free angle
        (``fit.cov`` infinite there) keeps its infinite variance.

    References
    ----------
    .. [1] JCGM 100:2008, 5.2 (correlated input quantities); the sandwich
           covariance of a weighted least-squares estimate.
    """
    n = len(view.xy)
    xy = view.xy[keep]
    t = (np.asarray(view.total_sigma, float) * np.ones(n))[keep]
    _, _, h = ellipse_geometry(xy, fit.params, fit.phases)
    hw = h / t[:, None]
    M = np.zeros((5, 5))
    for std, length in ((view.sigma, view.corr_length), (view.sigma_correction, view.correction_corr_length)):
        if std is not None:
            a = hw * ((np.asarray(std, float) * np.ones(n))[keep] / t)[:, None]
            M += information_matrices(a, np.ones(len(a)), xy, length)[1]
    Sinv = np.linalg.pinv(hw.T @ hw, rcond=1e-13, hermitian=True)
    cov = Sinv @ M @ Sinv
    cov = 0.5 * (cov + cov.T)
    if fit.cov is not None and not np.isfinite(fit.cov[4, 4]):
        # A circle: its axis angle is undetermined and moves no point.
        cov[4, :] = cov[:, 4] = 0.0
        cov[4, 4] = np.inf
    return cov
