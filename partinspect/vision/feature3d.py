"""The record of one measured 3D feature: parameters, their covariance split by source, its points' error model.

:class:`Feature3D` keeps a fitted line or circle (rig frame, mm) with its
covariance in three parts (GUM, JCGM 100): the image noise's, the
calibration's (:mod:`partinspect.vision.calibration_uncertainty`) and the
Type B part (a rim's shading rest, a line's shading offset, a broken
edge's band), and the error model of its triangulated points
(:class:`~partinspect.vision.pointerrors.PointErrorModel`), which the form
characteristics draw. :func:`make_feature3d` builds it from a matched
pair's two-view fit.

Frames: 3D geometry in the rig frame (left camera, mm); points in ideal
pixels.

References
----------
.. [1] JCGM 100:2008, Guide to the expression of uncertainty in
       measurement, section 5.1.
.. [2] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed.
"""

from dataclasses import dataclass

import numpy as np

from partinspect.frames import orthonormal_frame, plane_basis
from partinspect.vision.fit3d import minimal_residuals
from partinspect.vision.imagefeatures import chauvenet_z
from partinspect.vision.pointerrors import point_error_model, short_scale_ratio
from partinspect.vision.rim_errors import form_view

__all__ = ["Feature3D", "make_feature3d"]


@dataclass(frozen=True)
class Feature3D:
    """A 3D line, circle or arc measured from a matched pair of image features.

    Attributes
    ----------
    kind : str
        "line", "circle" (edge points seen over at least 300 degrees) or "arc".
    left, right : int
        Indices of the image features (``StereoResult.left.features``...).
    point, direction : ndarray, shape (3,) or None
        Lines: a point (nearest the data's centroid) and unit direction.
    start, end : ndarray, shape (3,) or None
        Lines: the extent of the triangulated points projected on the line.
    center, normal : ndarray, shape (3,) or None
        Circles and arcs; the normal points towards the left camera.
    radius : float
        Circles and arcs, mm (NaN for lines).
    angle_start, angle_end : float
        Circles and arcs: angular extent of the edge points of either image
        (back-projected onto the fitted circle's plane), rad,
        counter-clockwise about ``normal`` from
        ``partinspect.frames.reference_direction(normal)``; 0 and 2 pi
        for a circle.
    covariance : ndarray, shape (3, 3)
        Covariance of ``center`` (circles) or ``point`` (lines), mm^2: all
        three parts below together.
    radius_std : float
        Standard uncertainty of the radius, mm (NaN for lines).
    axis_cov : ndarray, shape (3, 3)
        Covariance of ``normal`` or ``direction`` (unit vectors).
    param_cov : ndarray, shape (7, 7) or (6, 6)
        Covariance of (center, normal, radius) or (point, direction).
    param_cov_image, param_cov_calibration : ndarray
        Two parts of ``param_cov``: from the image noise on the edge points
        (what a Monte Carlo of image noise reproduces), and from the
        calibration's stated uncertainty (``G G^T`` of ``calibration_response``;
        zeros without one).
    fit : Line3D or Circle3D
        The two-view fit (its covariances are the image-noise and systematic
        parts).
    correspondences : Correspondences
        Triangulated points with their 3x3 covariances.
    param_cov_systematic : ndarray
        The third part of ``param_cov``: the Type B component of a rim's
        points (module notes, "Rims of holes") or of a line's offset in
        each image (module notes, "Lines").
    point_errors : PointErrorModel or None
        Draws of the errors of ``points`` with their correlations along the
        edge (:mod:`partinspect.vision.pointerrors`), for the form's Monte
        Carlo.
    guided : str or None
        The CAD edge this line was measured as by
        :func:`partinspect.vision.guided.guided_lines` (a stretch of longer
        image lines chosen by the edge's image under the registered pose);
        None for a pair the matching made.
    calibration_response : ndarray, shape (7, q) or (6, q), or None
        The parameters' first-order responses to the calibration's q
        principal directions of uncertainty
        (:func:`partinspect.vision.calibration_uncertainty.calibration_responses`):
        ``param_cov_calibration`` is ``G G^T``, and two features measured
        with one calibration have the cross-covariance ``G_a G_b^T``, for
        the calibration's error is one error shared by all of them.
    band_place : BandPlace or None
        A broken rim whose points were moved, each by its predicted place
        across the break, onto the sharp rim's image and fitted again
        (:func:`partinspect.vision.band_place.rims_at_sharp_edge`): the
        size measured is the wall's. None otherwise.
    """

    kind: str
    left: int
    right: int
    point: np.ndarray | None
    direction: np.ndarray | None
    start: np.ndarray | None
    end: np.ndarray | None
    center: np.ndarray | None
    normal: np.ndarray | None
    radius: float
    angle_start: float
    angle_end: float
    covariance: np.ndarray
    radius_std: float
    axis_cov: np.ndarray
    param_cov: np.ndarray
    param_cov_image: np.ndarray
    param_cov_calibration: np.ndarray
    fit: object
    correspondences: object
    param_cov_systematic: np.ndarray | None = None
    point_errors: object = None
    guided: str | None = None
    calibration_response: np.ndarray | None = None
    band_place: object = None

    @property
    def points(self):
        """The triangulated correspondences, shape (N, 3), rig frame, mm: what
        registration and the form characteristics evaluate."""
        return self.correspondences.points

    @property
    def point_covs(self):
        """Their 3x3 covariances, shape (N, 3, 3), mm^2: each point's whole
        standard uncertainty as the point errors model it.

        Where there is a ``point_errors`` model (every feature of
        :func:`~partinspect.vision.stereo.measure_stereo`) these are its marginal covariances: for a
        rim's points the image noise, the noise of the background
        correction (with the share it takes from the point's own) and the
        Type B rest of the shading's displacement, with the right fit's part.
        The triangulation's own ``correspondences.cov`` carries the first
        and the last only, too little for a rim's points; for a line the
        two are the same.
        """
        if self.point_errors is not None:
            return self.point_errors.covariances()
        return self.correspondences.cov

    @property
    def params(self):
        """(center, normal, radius) or (point, direction) as one vector."""
        if self.kind == "line":
            return np.r_[self.point, self.direction]
        return np.r_[self.center, self.normal, self.radius]


def _angular_extent(points, center, normal):
    x, y, _ = orthonormal_frame(normal)
    q = points - center
    ang = np.sort(np.mod(np.arctan2(q @ y, q @ x), 2 * np.pi))
    gaps = np.diff(np.r_[ang, ang[0] + 2 * np.pi])
    k = int(np.argmax(gaps))
    start = ang[(k + 1) % len(ang)]
    extent = 2 * np.pi - gaps[k]
    return float(start), float(start + extent), float(extent)


def _image_param_cov(fit, kind, type_b_scale=1.0, radius_scale=1.0):
    """The fit's covariance of (point, direction) or (center, normal, radius): (image noise, systematic).

    A circle's systematic part has its centre and normal rows and columns
    multiplied by ``type_b_scale`` (:func:`~partinspect.vision.rim_errors.type_b_scale`): what the rim's
    residuals show of the Type B displacement's variation along the rim,
    which moves the centre and tilts the normal. The radius's row and
    column take ``radius_scale``
    (:func:`~partinspect.vision.rim_errors.radius_type_b_scale`), which
    takes the detector's per-point floor out of it, not the residuals'
    evidence: a displacement common to the whole rim moves only the radius
    and leaves no residual to judge it by.
    """
    if kind == "line":
        C = np.zeros((6, 6))
        C[:3, :3] = fit.covariance
        C[3:, 3:] = fit.direction_cov
        d0 = fit.direction
        e1, e2 = plane_basis(d0).T
        # Cross terms from the 4x4 minimal covariance (same basis as fit3d's to first order).
        E = np.stack([e1, e2], 1)
        C[:3, 3:] = E @ fit.param_cov[:2, 2:] @ E.T
        C[3:, :3] = C[:3, 3:].T
        # The systematic part: each view's one offset along the line (the
        # shading beside it, a broken edge's band; feature_views).
        if fit.param_cov_systematic is None or not np.any(fit.param_cov_systematic):
            return C, np.zeros((6, 6))
        Eb = np.zeros((6, 4))
        Eb[:3, :2], Eb[3:, 2:] = E, E
        S = Eb @ fit.param_cov_systematic @ Eb.T
        return C - S, S
    _, _, M = minimal_residuals(fit, kind, [])
    sys = np.zeros_like(fit.param_cov) if fit.param_cov_systematic is None else fit.param_cov_systematic
    img, sys = M @ (fit.param_cov - sys) @ M.T, M @ sys @ M.T
    d = np.r_[np.full(6, type_b_scale), radius_scale]
    return img, sys * np.outer(d, d)


def _on_plane(xy, K, R, T, center, normal):
    """Ideal pixels (N, 2) of a camera ``x_cam = R @ X + T`` back-projected onto a plane, rig frame."""
    d = np.c_[xy, np.ones(len(xy))] @ np.linalg.inv(K).T @ R  # ray directions, rig frame
    o = -R.T @ T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((center - o) @ normal) / (d @ normal)
    X = o + s[:, None] * d
    return X[np.isfinite(X).all(axis=1) & (s > 0)]


def _point_errors(fl, corr, view, calibration=None):
    """The :class:`~partinspect.vision.pointerrors.PointErrorModel` of a feature's triangulated points.

    The left points' random part (``view.sigma``, correlated over the edge
    filter's scale, and the background correction's noise over its own
    length) and the Type B rest of a rim's shading displacement
    (``view.bias``, over its own length), as the 3D fit models them. Where
    the residuals scatter significantly more from point to point than that
    noise predicts (:func:`~partinspect.vision.pointerrors.short_scale_ratio`
    above 1 by more than twice its standard error: on a very clean image the
    sub-pixel estimator's own ripple is as large as the noise), the random
    part is scaled up to what the residuals show: a Type A evaluation of the
    scatter the form is judged against. It is never scaled down: a ratio
    below 1 may hide structure longer than the differences see.
    ``calibration``: the points' responses to the calibration's uncertainty
    (:func:`~partinspect.vision.calibration_points.point_responses`), or None.
    """
    sigma = np.asarray(view.sigma, float) * np.ones(len(fl.ideal.xy))
    ratio, se = short_scale_ratio(fl.fit.residuals, sigma, fl.ideal.xy, view.corr_length)
    if ratio > 1.0 + 2.0 * se:
        sigma = sigma * np.sqrt(ratio)
    comps = [(sigma, view.corr_length)]
    if view.sigma_correction is not None:
        comps.append((view.sigma_correction, view.correction_corr_length))
    systematic = ()
    if view.bias is not None:
        systematic = (len(comps),)
        comps.append((view.bias, view.bias_corr_length))
    # The left feature's fit rejected its points beyond Chauvenet's threshold
    # (imagefeatures._make_features): the form's simulation cuts its tails there too.
    return point_error_model(corr, fl.ideal.normal, comps, systematic, chauvenet_z(len(fl.ideal.xy)), calibration,
                             fl.phase_factor)


def make_feature3d(match, fl, fr, fit, corr, cal_response, geo, view, type_b_scale=1.0, point_response=None,
                   radius_scale=1.0):
    """The :class:`Feature3D` record of a matched pair's two-view fit.

    Parameters
    ----------
    match : Match
        Its ``left`` and ``right`` indices are recorded.
    fl, fr : EdgeFeature
        The left and right image features.
    fit : Line3D or Circle3D
        Their two-view fit.
    corr : Correspondences
        Their triangulated points (the form is judged on them).
    cal_response : ndarray, shape (6, q) or (7, q)
        The parameters' responses to the calibration's uncertainty
        (:func:`partinspect.vision.calibration_uncertainty.calibration_responses`;
        q = 0 without it).
    geo : EpipolarGeometry
    view : View
        The left view of the fit (:func:`~partinspect.vision.stereo.feature_views`): the points'
        random and systematic parts for their error model.
    type_b_scale : float
        What a rim's residuals show of its stated Type B (:func:`~partinspect.vision.rim_errors.type_b_scale`),
        applied to the centre and normal (:func:`_image_param_cov`).
    point_response : ndarray, shape (N, 3, q), optional
        The triangulated points' responses to the calibration's uncertainty
        (:func:`partinspect.vision.calibration_points.point_responses`), which
        the points' error model draws for the form; None: not drawn.
    radius_scale : float
        The factor on a rim's radius's systematic part
        (:func:`~partinspect.vision.rim_errors.radius_type_b_scale`).

    Returns
    -------
    Feature3D
        The covariance is the fit's image-noise and systematic parts plus
        the calibration's ``G G^T``, each also kept apart. A circle or arc is a "circle"
        when the edge points of either image, back-projected onto its
        plane, cover at least 300 degrees of it.
    """
    kind = fl.kind
    img_cov, sys_cov = _image_param_cov(fit, kind, type_b_scale, radius_scale)
    G = np.asarray(cal_response, float)
    cal_cov = G @ G.T
    total = img_cov + cal_cov + sys_cov
    errors = _point_errors(fl, corr, form_view(view, fl), point_response)
    if kind == "line":
        t = (corr.points - fit.point) @ fit.direction
        return Feature3D("line", match.left, match.right, fit.point, fit.direction,
                         fit.point + t.min() * fit.direction, fit.point + t.max() * fit.direction,
                         None, None, float("nan"), float("nan"), float("nan"),
                         total[:3, :3], float("nan"), total[3:, 3:], total, img_cov, cal_cov, fit, corr, sys_cov,
                         errors, calibration_response=G)
    # The fit used each image's own edge points, so the rim it measured is
    # what either image sees; the correspondences cover only what both do.
    pts = np.vstack([_on_plane(fl.ideal.xy, geo.K1, np.eye(3), np.zeros(3), fit.center, fit.normal),
                     _on_plane(fr.ideal.xy, geo.K2, geo.R, geo.T, fit.center, fit.normal)])
    a0, a1, extent = _angular_extent(pts, fit.center, fit.normal)
    kind3 = "circle" if extent >= np.deg2rad(300.0) else "arc"
    if kind3 == "circle":
        a0, a1 = 0.0, 2 * np.pi
    return Feature3D(kind3, match.left, match.right, None, None, None, None, fit.center, fit.normal,
                     float(fit.radius), a0, a1, total[:3, :3], float(np.sqrt(total[6, 6])), total[3:6, 3:6],
                     total, img_cov, cal_cov, fit, corr, sys_cov, errors, calibration_response=G)
