"""The stereo measurement chain: an image pair to 3D lines and circles with covariances.

Per image: noise estimate -> sub-pixel edge points with covariances ->
contours -> line and ellipse segments; then the points are moved to ideal
pixels, the segments merged and matched across the images by the
epipolar constraint, corresponding points triangulated with their error
ellipsoids, and each matched feature fitted in 3D to the edge points of both
images at once (:mod:`partinspect.vision.fit3d`), initialised from a PCA line
or a plane-and-circle fit through the triangulated points.

Uncertainty (GUM, JCGM 100): each 3D feature's covariance is the
first-order propagation of the edge points' covariances (sandwich form, the
along-edge correlation of smoothed noise included). When the calibration
carries standard uncertainties of its parameters (``calib.std``), their
contribution is added: the sensitivity of the 3D parameters to each
calibration parameter is obtained numerically (central differences of
+-1 standard deviation: the edge points are re-mapped to ideal pixels with
the perturbed intrinsics and distortion, the cameras rebuilt, and one
Gauss-Newton step of the 3D fit taken from its solution, which is the
first-order response), calibration parameters taken as uncorrelated. Both
parts are kept separately in each :class:`Feature3D`.

Frames: 2D points in distorted pixels as detected, or ideal pixels where
said; 3D geometry in the rig frame (left camera, mm).

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed.
.. [2] Lindstrom, P. (2010). Triangulation made easy. CVPR 2010.
.. [3] Quan, L. (1996). Conic reconstruction and correspondence from two
       views. IEEE PAMI 18(2), 151-160.
.. [4] JCGM 100:2008, Guide to the expression of uncertainty in
       measurement, section 5.1.
"""

from dataclasses import dataclass, replace

import cv2
import numpy as np

from partinspect.vision.contours import chain_edges, segment_contours
from partinspect.vision.correspondences import correspond
from partinspect.vision.edges import edge_points
from partinspect.vision.fit3d import View, _basis, _circle_residuals, _line_residuals, fit_circle_3d, fit_line_3d
from partinspect.vision.ideal import camera_matrices, to_ideal
from partinspect.vision.matching import epipolar_geometry, image_features, match_features
from partinspect.vision.noise import estimate_noise

__all__ = ["ImageResult", "Feature3D", "StereoResult", "measure_stereo", "measure_images",
           "feature_views", "fit_feature", "calibration_covariance", "calibration_parameters"]


@dataclass(frozen=True)
class ImageResult:
    """The 2D chain of one image.

    Attributes
    ----------
    noise : float
        Estimated image noise, grey levels.
    edges : EdgePoints
        Distorted pixels.
    segments : list of Segment
    features : list of ImageFeature
        Segments merged into edges, refitted in ideal pixels.
    """

    noise: float
    edges: object
    segments: list
    features: list


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
        Circles and arcs: angular extent of the triangulated points, rad,
        counter-clockwise about ``normal`` from
        ``partinspect.cad.features.reference_direction(normal)``; 0 and 2 pi
        for a circle.
    covariance : ndarray, shape (3, 3)
        Covariance of ``center`` (circles) or ``point`` (lines), mm^2,
        image noise and calibration together.
    radius_std : float
        Standard uncertainty of the radius, mm (NaN for lines).
    axis_cov : ndarray, shape (3, 3)
        Covariance of ``normal`` or ``direction`` (unit vectors).
    param_cov : ndarray, shape (7, 7) or (6, 6)
        Covariance of (center, normal, radius) or (point, direction).
    param_cov_image, param_cov_calibration : ndarray
        The two parts of ``param_cov``: from the edge points alone, and from
        the calibration's standard uncertainties (zeros without them).
    fit : Line3D or Circle3D
        The two-view fit (its covariances are the image part).
    correspondences : Correspondences
        Triangulated points with their 3x3 covariances.
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

    @property
    def params(self):
        """(center, normal, radius) or (point, direction) as one vector."""
        if self.kind == "line":
            return np.r_[self.point, self.direction]
        return np.r_[self.center, self.normal, self.radius]


@dataclass(frozen=True)
class StereoResult:
    """Everything :func:`measure_stereo` found.

    Attributes
    ----------
    left, right : ImageResult
    geometry : EpipolarGeometry
    matching : Matching
        Matches and unmatched features with their reasons.
    features : tuple of Feature3D
    failed : tuple of (Match, str)
        Matched pairs whose 3D fit failed, with the reason.
    calibration_included : bool
        Whether the calibration's standard uncertainties were propagated.
    """

    left: ImageResult
    right: ImageResult
    geometry: object
    matching: object
    features: tuple
    failed: tuple
    calibration_included: bool


def measure_images(image, K, D, *, sigma=1.0):
    """The 2D chain of one image (distorted pixels in, ideal-pixel features out)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    noise = float(estimate_noise(img))
    edges = edge_points(img, sigma, noise=noise)
    segments = segment_contours(edges, chain_edges(edges))
    return ImageResult(noise, edges, segments, image_features(edges, segments, K, D))


# ------------------------------------------------------------------ 3D fits


def feature_views(fl, fr, corr_length, calib, uv=None, remap=False):
    """fit3d Views of a matched pair: ideal points, their
    across-edge standard uncertainties, the cameras of ``calib``.

    ``uv`` optionally replaces the two features' distorted points (Monte
    Carlo); with it, or with ``remap`` (a perturbed calibration), the
    distorted points are mapped to ideal pixels again with ``calib``.
    """
    P1, P2 = camera_matrices(calib)
    views = []
    for f, P, K, D, pts in ((fl, P1, calib.K1, calib.D1, None if uv is None else uv[0]),
                            (fr, P2, calib.K2, calib.D2, None if uv is None else uv[1])):
        xy = f.ideal.xy if pts is None and not remap else to_ideal(f.uv if pts is None else pts, K, D)
        views.append(View(xy, f.ideal.normal_std, P, corr_length))
    return views


def _initial_line(points):
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt[0]


def _initial_circle(points):
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    e1, e2 = vt[0], vt[1]
    q = np.c_[(points - c) @ e1, (points - c) @ e2]
    # Kasa's algebraic circle in the plane.
    A = np.c_[2 * q, np.ones(len(q))]
    sol, *_ = np.linalg.lstsq(A, (q * q).sum(1), rcond=None)
    r = np.sqrt(max(sol[2] + sol[0] ** 2 + sol[1] ** 2, 1e-12))
    return c + sol[0] * e1 + sol[1] * e2, n, r


def fit_feature(fl, fr, views, points):
    """The two-view 3D fit of one matched pair, initialised from triangulated points."""
    if fl.kind == "line":
        p0, d0 = _initial_line(points)
        return fit_line_3d(views, p0, d0)
    c0, n0, r0 = _initial_circle(points)
    return fit_circle_3d(views, c0, n0, r0)


def _angular_extent(points, center, normal):
    from partinspect.cad.features import reference_direction

    x = reference_direction(normal)
    y = np.cross(normal, x)
    q = points - center
    ang = np.sort(np.mod(np.arctan2(q @ y, q @ x), 2 * np.pi))
    gaps = np.diff(np.r_[ang, ang[0] + 2 * np.pi])
    k = int(np.argmax(gaps))
    start = ang[(k + 1) % len(ang)]
    extent = 2 * np.pi - gaps[k]
    return float(start), float(start + extent), float(extent)


# ------------------------------------------------------ calibration uncertainty


def calibration_parameters(calib):
    """Names, values and standard uncertainties of the calibration parameters with std > 0.

    Returns
    -------
    list of (str, int, float)
        ``(group, index, std)``: group "intrinsics1", "intrinsics2" or
        "extrinsics", index in OpenCV's order (fx, fy, cx, cy, D...; rx, ry,
        rz, tx, ty, tz).
    """
    out = []
    for group in ("intrinsics1", "intrinsics2", "extrinsics"):
        std = np.asarray(calib.std.get(group, ()), float).ravel()
        for k, s in enumerate(std):
            if s > 0:
                out.append((group, k, float(s)))
    return out


def perturbed_calibration(calib, deltas):
    """A copy of ``calib`` with parameters shifted: ``deltas`` maps (group, index) -> shift."""
    K1, D1, K2, D2 = (np.array(a, float) for a in (calib.K1, calib.D1, calib.K2, calib.D2))
    R, T = np.array(calib.R, float), np.array(calib.T, float).ravel()
    rvec = cv2.Rodrigues(R)[0].ravel()
    for (group, k), d in deltas.items():
        if group == "extrinsics":
            if k < 3:
                rvec[k] += d
            else:
                T[k - 3] += d
            continue
        K, D = (K1, D1) if group == "intrinsics1" else (K2, D2)
        if k < 4:
            K[[0, 1, 0, 1][k], [0, 1, 2, 2][k]] += d
        else:
            D[k - 4] += d
    R = cv2.Rodrigues(rvec)[0]
    return replace(calib, K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T)


def _minimal_residuals(fit, kind, views):
    """Residual function of the fit3d parametrisation centred on the solution, and its map to params."""
    if kind == "line":
        d0 = fit.direction
        e1, e2 = _basis(d0)
        res = _line_residuals(views, fit.point, d0, e1, e2)
        theta0 = np.zeros(4)
        M = np.zeros((6, 4))
        M[:3, 0], M[:3, 1], M[3:, 2], M[3:, 3] = e1, e2, e1, e2
    else:
        n0 = fit.normal
        e1, e2 = _basis(n0)
        res = _circle_residuals(views, n0, e1, e2)
        theta0 = np.r_[fit.center, 0.0, 0.0, fit.radius]
        M = np.zeros((7, 6))
        M[:3, :3] = np.eye(3)
        M[3:6, 3], M[3:6, 4] = e1, e2
        M[6, 5] = 1.0
    return res, theta0, M


def calibration_covariance(fit, kind, fl, fr, corr_length, calib):
    """Covariance of a 3D feature's parameters due to the calibration's uncertainty.

    Parameters
    ----------
    fit : Line3D or Circle3D
        The fit with the nominal calibration.
    kind : str
        "line" or "arc".
    fl, fr : ImageFeature
    corr_length : float
    calib : StereoCalibration
        With ``std``.

    Returns
    -------
    ndarray, shape (6, 6) or (7, 7)
        Of (point, direction) or (center, normal, radius); zeros when the
        calibration has no standard uncertainties.

    Notes
    -----
    For each parameter p_k with standard uncertainty u_k the fit's
    minimal parameters respond, to first order, by one Gauss-Newton step
    from the solution: ``d theta = -(J^T J)^-1 J^T d r`` with ``d r`` the
    change of the weighted residuals when p_k moves; central differences at
    +-u_k give ``c_k u_k`` directly, and ``sum_k (c_k u_k)(c_k u_k)^T`` is
    the law of propagation for uncorrelated inputs (JCGM 100, 5.1.2).
    """
    params = calibration_parameters(calib)
    views0 = feature_views(fl, fr, corr_length, calib)
    res0, theta0, M = _minimal_residuals(fit, kind, views0)
    n = M.shape[0]
    if not params:
        return np.zeros((n, n))
    h = 1e-6 * np.maximum(1.0, np.abs(theta0))
    J = np.stack([(res0(theta0 + e) - res0(theta0 - e)) / (2 * s) for e, s in zip(np.diag(h), h)], 1)
    pinv = np.linalg.pinv(J)
    cols = []
    for group, k, s in params:
        r = []
        for sign in (1.0, -1.0):
            cal = perturbed_calibration(calib, {(group, k): sign * s})
            res, _, _ = _minimal_residuals(fit, kind, feature_views(fl, fr, corr_length, cal, remap=True))
            r.append(res(theta0))
        cols.append(-pinv @ (0.5 * (r[0] - r[1])))
    G = M @ np.stack(cols, 1)
    return G @ G.T


# ------------------------------------------------------------------ the chain


def _image_param_cov(fit, kind):
    if kind == "line":
        C = np.zeros((6, 6))
        C[:3, :3] = fit.covariance
        C[3:, 3:] = fit.direction_cov
        d0 = fit.direction
        e1, e2 = _basis(d0)
        # Cross terms from the 4x4 minimal covariance (same basis as fit3d's to first order).
        E = np.stack([e1, e2], 1)
        C[:3, 3:] = E @ fit.param_cov[:2, 2:] @ E.T
        C[3:, :3] = C[:3, 3:].T
        return C
    _, _, M = _minimal_residuals(fit, kind, [])
    return M @ fit.param_cov @ M.T


def _make_feature3d(match, fl, fr, fit, corr, cal_cov):
    kind = fl.kind
    img_cov = _image_param_cov(fit, kind)
    total = img_cov + cal_cov
    if kind == "line":
        t = (corr.points - fit.point) @ fit.direction
        return Feature3D("line", match.left, match.right, fit.point, fit.direction,
                         fit.point + t.min() * fit.direction, fit.point + t.max() * fit.direction,
                         None, None, float("nan"), float("nan"), float("nan"),
                         total[:3, :3], float("nan"), total[3:, 3:], total, img_cov, cal_cov, fit, corr)
    a0, a1, extent = _angular_extent(corr.points, fit.center, fit.normal)
    kind3 = "circle" if extent >= np.deg2rad(300.0) else "arc"
    if kind3 == "circle":
        a0, a1 = 0.0, 2 * np.pi
    return Feature3D(kind3, match.left, match.right, None, None, None, None, fit.center, fit.normal,
                     float(fit.radius), a0, a1, total[:3, :3], float(np.sqrt(total[6, 6])), total[3:6, 3:6],
                     total, img_cov, cal_cov, fit, corr)


def measure_stereo(left, right, calib, *, sigma=1.0, progress=None, match_options=None):
    """Measure the 3D lines and circles of a part from a calibrated stereo pair.

    Parameters
    ----------
    left, right : ndarray, shape (H, W) or (H, W, 3)
        The images as recorded (distorted), grey levels.
    calib : StereoCalibration
        With optional ``std`` (standard uncertainties of the intrinsics and
        extrinsics), which are then propagated into every 3D feature (see
        the module notes: numerical sensitivities, one Gauss-Newton step of
        the two-view fit per calibration parameter and sign).
    sigma : float
        Scale of the edge filter, px (the paper's sigma = 1 to start).
    progress : callable, optional
        ``progress(message)`` at each stage.
    match_options : dict, optional
        Keyword arguments of :func:`partinspect.vision.matching.match_features`.

    Returns
    -------
    StereoResult
    """
    say = progress or (lambda message: None)
    say("edges and segments: left image")
    L = measure_images(left, calib.K1, calib.D1, sigma=sigma)
    say("edges and segments: right image")
    R = measure_images(right, calib.K2, calib.D2, sigma=sigma)
    geo = epipolar_geometry(calib)
    say("matching")
    matching = match_features(L.features, R.features, geo, **(match_options or {}))
    say(f"3D fits of {len(matching.matches)} matched features")
    feats, failed = [], []
    corr_length = L.edges.sigma
    with_cal = bool(calibration_parameters(calib))
    for m in matching.matches:
        fl, fr = L.features[m.left], R.features[m.right]
        corr = correspond(fl, fr, geo)
        if len(corr) < 6:
            failed.append((m, f"only {len(corr)} corresponding points"))
            continue
        try:
            views = feature_views(fl, fr, corr_length, calib)
            fit = fit_feature(fl, fr, views, corr.points)
        except (np.linalg.LinAlgError, ValueError) as exc:
            failed.append((m, f"3D fit failed: {exc}"))
            continue
        cal_cov = calibration_covariance(fit, fl.kind, fl, fr, corr_length, calib) if with_cal else \
            np.zeros((6, 6) if fl.kind == "line" else (7, 7))
        feats.append(_make_feature3d(m, fl, fr, fit, corr, cal_cov))
    return StereoResult(L, R, geo, matching, tuple(feats), tuple(failed), with_cal)
