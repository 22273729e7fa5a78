"""Point correspondences along matched features, triangulated with 3x3 covariances.

Each left edge point's epipolar line is intersected with the *fitted* right
curve (line or ellipse), which gives its partner in the right image without
any search; the pair satisfies the epipolar constraint exactly, so the
optimal triangulation is the intersection of the two rays. The covariance
of each 3D point is the first-order propagation (JCGM 100, 5.1) of

- the left point's 2x2 covariance (through the epipolar line into the
  right partner, and through the left ray), and
- the right curve's fit covariance (through the partner),

which are the paper's error ellipsoids (its figures 5-7): their long axis
is the depth, as it observes. The right curve's error is common to all the
points of one feature, so the points' errors are correlated; the per-point
3x3 matrices are their marginals. These points initialise the 3D fits of
:mod:`partinspect.vision.fit3d` and feed the report's figures; the 3D
features themselves are fitted to the edge points of both images directly.

Everything is vectorised over the points; coordinates are ideal pixels,
3D points in the rig frame (mm).

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., sections 9.2 (epipolar lines), 12.5
       (optimal triangulation) and 5.2 (propagation of covariance).
.. [2] Lindstrom, P. (2010). Triangulation made easy. CVPR 2010.
.. [3] Quan, L. (1996). Conic reconstruction and correspondence from two
       views. IEEE PAMI 18(2), 151-160.
.. [4] JCGM 100:2008, Guide to the expression of uncertainty in
       measurement, section 5.1.
"""

from dataclasses import dataclass

import numpy as np

from partinspect.vision.edges import CURVATURE_SAMPLING_BIAS
from partinspect.vision.fitting import ellipse_curvature, ellipse_geometry
from partinspect.vision.matching import MIN_EPIPOLAR_ANGLE
from partinspect.vision.psd import covariance_factor
from partinspect.vision.triangulation import triangulate

__all__ = ["Correspondences", "correspond", "intersect_line", "intersect_ellipse", "deblurred", "curvature_bias",
           "CURVATURE_SECOND_ORDER", "ARC_MIN_CROSSING"]


CURVATURE_SECOND_ORDER = 0.60
"""The curvature bias's second order: each point's first-order bias
``(W^2 / 2) kappa`` is taken times ``1 - 0.60 (W kappa)^2`` (W the edge
profile's width). Where ``W kappa`` nears 1, at the ends of a rim a few
pixels across seen at a slant, the first order over-states the detector's
move and the radius reads large; on exact ellipses under Gaussian and disc
blurs (``bench_psf_shape.py --ellipses``) the factor leaves what
``CURVATURE_REMAINDER`` (:mod:`partinspect.vision.rim_errors`) states, and
the discs that remainder was set on (``W kappa`` below 0.15) do not move.
docs/validation.md has the figures."""

ARC_MIN_CROSSING = np.deg2rad(10.0)
"""Arc points whose epipolar line crosses an ellipse at less than this are dropped, rad.

Lines take the matcher's gate instead
(:data:`partinspect.vision.matching.MIN_EPIPOLAR_ANGLE`): a line's
crossing angle is nearly the same at all its points, so a stricter angle
here would drop every point of a line the matcher kept. An arc's crossing
angle falls to zero where its epipolar line is tangent to it, and only the
points near there go."""


@dataclass(frozen=True)
class Correspondences:
    """Corresponding points of one matched feature.

    Attributes
    ----------
    left_index : ndarray, shape (N,)
        Indices into the left feature's points of the points used.
    left, right : ndarray, shape (N, 2)
        Corresponding ideal pixel coordinates (the right ones on the right
        fitted curve).
    points : ndarray, shape (N, 3)
        Triangulated points, rig frame, mm.
    cov : ndarray, shape (N, 3, 3)
        Their first-order covariances, mm^2 (marginals; see the module notes).
    dropped : int
        Left points without a usable partner: their epipolar line misses the
        right curve or crosses it at less than ``min_angle``.
    jac_left : ndarray, shape (N, 3, 2)
        d(points) / d(left), mm/px.
    jac_fit : ndarray, shape (N, 3, k)
        d(points) / d(right fitted curve's parameters).
    fit_cov : ndarray, shape (k, k)
        The right fit's covariance used (free directions zeroed).
    right_params : ndarray, shape (k,) or None
        The right fitted curve the partners lie on (a line's ``(a, b, c)``
        of ``a x + b y + c = 0`` or an ellipse's (xc, yc, a, b, theta)).
    """

    left_index: np.ndarray
    left: np.ndarray
    right: np.ndarray
    points: np.ndarray
    cov: np.ndarray
    dropped: int
    jac_left: np.ndarray | None = None
    jac_fit: np.ndarray | None = None
    fit_cov: np.ndarray | None = None
    right_params: np.ndarray | None = None

    def __len__(self):
        return len(self.points)


def deblurred(xy, fit, blur):
    """Edge points of an arc moved back by the curvature bias of the edge detector.

    Gaussian smoothing moves points on a curve towards its centre of
    curvature by ``blur^2 kappa / 2`` (less its second order,
    ``CURVATURE_SECOND_ORDER``), and the sub-pixel interpolation
    along a pixel axis adds ``c sin^2(2 phi) kappa`` (phi the angle between
    the normal and the nearest pixel axis, c =
    :data:`partinspect.vision.edges.CURVATURE_SAMPLING_BIAS`); both are
    undone here, with kappa the fitted ellipse's curvature at each point
    (:func:`curvature_bias`, whose parameters these are).

    Returns
    -------
    ndarray, shape (N, 2)
        The points moved back, px.
    """
    bias, n = curvature_bias(xy, fit, blur)
    return xy + bias[:, None] * n


def curvature_bias(xy, fit, blur):
    """The detector's curvature bias at each point of an arc: its size and direction.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Points, px (ideal).
    fit : EllipseFit
        Fit to those points.
    blur : float
        Width of the edge profile, px.

    Returns
    -------
    bias : ndarray, shape (N,)
        ``(blur^2 / 2 + c sin^2(2 phi)) kappa (1 - s (blur kappa)^2)``, px
        (s = ``CURVATURE_SECOND_ORDER``, the factor kept at zero or more):
        how far the detector moved each point towards the centre of
        curvature (:func:`deblurred`).
    normal : ndarray, shape (N, 2)
        The ellipse's unit normal at each point, along which
        :func:`deblurred` moves it back.
    """
    phi = fit.phases
    _, n, _ = ellipse_geometry(xy, fit.params, phi)
    kappa = ellipse_curvature(fit.params, phi)
    sin2phi_sq = 4.0 * (n[:, 0] * n[:, 1]) ** 2
    second = np.maximum(1.0 - CURVATURE_SECOND_ORDER * (blur * kappa) ** 2, 0.0)
    return (0.5 * blur * blur + CURVATURE_SAMPLING_BIAS * sin2phi_sq) * kappa * second, n


def intersect_line(lines, params):
    """Intersections of lines (N, 3) with one line ``A x + B y + C = 0``.

    ``params`` may also be (N, 3), one line per row (the perturbed fits of
    the Jacobians, all in one call).

    Returns
    -------
    points : ndarray, shape (N, 2)
    sin_angle : ndarray, shape (N,)
        Sine of the angle between each line and the fixed one.
    """
    params = np.asarray(params, float)
    h = np.cross(lines, params)
    with np.errstate(divide="ignore", invalid="ignore"):
        pts = h[:, :2] / h[:, 2:]
    ln = lines[:, :2] / np.hypot(lines[:, 0], lines[:, 1])[:, None]
    nn = params[..., :2] / np.hypot(params[..., 0], params[..., 1])[..., None]
    return pts, np.abs(ln[:, 0] * nn[..., 1] - ln[:, 1] * nn[..., 0])


def intersect_ellipse(lines, params):
    """Both intersections of lines (N, 3) with the ellipse (xc, yc, a, b, theta).

    ``params`` may also be (N, 5), one ellipse per row (the perturbed fits
    of the Jacobians, all in one call).

    Returns
    -------
    s : ndarray, shape (N, 2)
        Positions of the two intersections along each line, px, from the
        foot of the perpendicular from the centre, in the sense of the
        line's direction ``(l1, -l0)``; NaN where the line misses.
    foot, direction : ndarray, shape (N, 2)
        The foot point and the unit direction of each line, so the points
        are ``foot + s[:, k, None] * direction``.
    """
    params = np.asarray(params, float)
    xc, yc, a, b, th = (params[..., k] for k in range(5))
    ln = lines / np.hypot(lines[:, 0], lines[:, 1])[:, None]
    lx, ly = ln[:, 0], ln[:, 1]
    d = np.empty((len(ln), 2))
    d[:, 0], d[:, 1] = ly, -lx
    # Foot of the perpendicular from the centre.
    off = lx * xc + ly * yc + ln[:, 2]
    fx, fy = xc - off * lx, yc - off * ly
    ct, st = np.cos(th), np.sin(th)
    # Into the ellipse frame: u = Q^T (p - c), for the foot and the direction.
    qx, qy = fx - xc, fy - yc
    u0x, u0y = qx * ct + qy * st, -qx * st + qy * ct
    dux, duy = ly * ct - lx * st, -ly * st - lx * ct
    wa, wb = 1.0 / (a * a), 1.0 / (b * b)
    A = dux * dux * wa + duy * duy * wb
    B = dux * u0x * wa + duy * u0y * wb
    C = u0x * u0x * wa + u0y * u0y * wb - 1.0
    disc = B * B - A * C
    with np.errstate(invalid="ignore"):
        r = np.sqrt(disc)
    s = np.empty((len(ln), 2))
    s[:, 0], s[:, 1] = (-B - r) / A, (-B + r) / A
    s[disc < 0] = np.nan
    foot = np.empty((len(ln), 2))
    foot[:, 0], foot[:, 1] = fx, fy
    return s, foot, d


def _ellipse_normal_sin(points, direction, params):
    """|sin| of the angle between a direction and the ellipse's tangent at points on it."""
    xc, yc, a, b, th = params
    ct, st = np.cos(th), np.sin(th)
    qx, qy = points[:, 0] - xc, points[:, 1] - yc
    # Gradient of the implicit form in the ellipse frame, turned back to the image.
    gu, gv = (qx * ct + qy * st) / (a * a), (-qx * st + qy * ct) / (b * b)
    gx, gy = gu * ct - gv * st, gu * st + gv * ct
    return np.abs(gx * direction[:, 0] + gy * direction[:, 1]) / np.hypot(gx, gy)


def _left_crossing_sin(geo, x, left_params):
    """|sin| of the angle at which each left point's epipolar line crosses the left fitted ellipse there."""
    lines = geo.left_lines(x)  # normalised: (-l1, l0) is the unit direction
    return _ellipse_normal_sin(x, np.column_stack([-lines[:, 1], lines[:, 0]]), left_params)


def _partners(geo, kind, x, right_params, left_params, rank=None, lines_r=None, with_sin=True):
    """Right partners of left points x on the right curve; also the rank used for ellipses.

    ``right_params`` may be one row per point (perturbed fits); ``lines_r``
    the points' right epipolar lines if known already; without
    ``with_sin`` the sines are not computed (None).
    """
    if lines_r is None:
        lines_r = geo.right_lines(x)
    if kind == "line":
        y, sin_a = intersect_line(lines_r, right_params)
        return y, sin_a, None
    if rank is None:
        # Which of the two crossings of its epipolar line x is, in the sense
        # shared by both images (ordering along epipolar lines is kept).
        s_l, foot_l, d_l = intersect_ellipse(geo.left_lines(x), left_params)
        t = np.einsum("ni,ni->n", x - foot_l, d_l)
        rank = np.where(np.abs(t - s_l[:, 0]) < np.abs(t - s_l[:, 1]), 0, 1)
        rank = np.where(np.isnan(s_l).any(axis=1), np.where(t < 0, 0, 1), rank)
    s_r, foot_r, d_r = intersect_ellipse(lines_r, right_params)
    s = np.take_along_axis(s_r, rank[:, None], axis=1)[:, 0]
    y = foot_r + s[:, None] * d_r
    return y, _ellipse_normal_sin(y, d_r, right_params) if with_sin else None, rank


def _within_extent(y, pts, margin):
    """Points ``y`` (N, 2) whose position along the line through ``pts`` lies within their span +- ``margin`` px."""
    c = pts.mean(axis=0)
    _, _, Vt = np.linalg.svd(pts - c, full_matrices=False)
    t = (pts - c) @ Vt[0]
    s = (y - c) @ Vt[0]
    return (s >= t.min() - margin) & (s <= t.max() + margin)


def _near_points(y, pts, margin):
    """Points ``y`` (N, 2) within ``margin`` px of one of ``pts`` (M, 2); non-finite ones are not."""
    from scipy.spatial import cKDTree

    ok = np.isfinite(y).all(axis=1)
    out = np.zeros(len(y), bool)
    if ok.any() and len(pts):
        d, _ = cKDTree(pts).query(y[ok], distance_upper_bound=margin + 1e-9)
        out[ok] = d <= margin
    return out


def correspond(left, right, geo, *, xy=None, min_angle=None, step=1e-4, margin=2.0):
    """Triangulated correspondences along a matched pair of image features.

    Parameters
    ----------
    left, right : ImageFeature
        A matched pair (:func:`partinspect.vision.matching.match_features`).
    geo : EpipolarGeometry
    xy : ndarray, shape (N, 2), optional
        The left feature's points to use instead of ``left.ideal.xy`` (same
        order), e.g. corrected for the shading beside a rim, ideal px.
    min_angle : float, optional
        Points whose epipolar line crosses the right curve at less than
        this angle, rad, are dropped (their partner is ill-determined); on
        arcs also those whose epipolar line crosses the left fitted ellipse
        at less than this angle at the point. Default the matcher's
        :data:`~partinspect.vision.matching.MIN_EPIPOLAR_ANGLE` for lines,
        :data:`ARC_MIN_CROSSING` for arcs.
    step : float
        Relative step of the numerical Jacobians.
    margin : float
        px. Lines: a left point is kept only when its partner on the right
        line lies within the right feature's points' extent plus this; arcs:
        when its partner on the right ellipse lies within this of one of the
        right feature's points (where the right image sees the edge too).

    Returns
    -------
    Correspondences
    """
    kind = left.kind
    if min_angle is None:
        min_angle = MIN_EPIPOLAR_ANGLE if kind == "line" else ARC_MIN_CROSSING
    x = left.ideal.xy if xy is None else np.asarray(xy, float)
    pr = np.asarray(right.fit.params, float)
    pl = np.asarray(left.fit.params, float)
    y, sin_a, rank = _partners(geo, kind, x, pr, pl)
    keep = np.isfinite(y).all(axis=1) & (sin_a >= np.sin(min_angle))
    if kind != "line":
        # The crossing is judged in the left image too, on the left fitted
        # ellipse: near the epipolar tangent point a left point off the
        # ellipse by a pixel (a rim point displaced by the shading beside
        # it) moves its epipolar line to cross the right ellipse twice at
        # steeper angles, and the partner found there, far along the right
        # ellipse, passes the right-image test and sets the circularity.
        keep &= _left_crossing_sin(geo, x, pl) >= np.sin(min_angle)
    if kind == "line":
        # Only where the right image sees the edge too: the fitted right line
        # extended past its points would place a left-only stretch (or a
        # neighbour merged with it in the left image) on the line's extension.
        keep &= _within_extent(y, right.ideal.xy, margin)
    else:
        # Likewise on an arc: where the right image has no edge point, the
        # partner is the fitted ellipse extrapolated, which for a partial
        # rim can lie far from the real edge.
        keep &= _near_points(y, right.ideal.xy, margin)
    idx = np.flatnonzero(keep)
    x, y = x[idx], y[idx]
    if rank is not None:
        rank = rank[idx]
    K1, K2, R, T = geo.K1, geo.K2, geo.R, geo.T
    n = len(idx)

    # Central-difference Jacobians, vectorised over the points: the
    # partners of every perturbed point set are found first and all of
    # them triangulated in one call (triangulation is point by point).
    xs, ys = [x], [y]
    h_x = step * 10.0  # px
    for k in range(2):
        for sign in (1.0, -1.0):
            xp = x.copy()
            xp[:, k] += sign * h_x
            xs.append(xp)
    rank_x = None if rank is None else np.tile(rank, 4)
    ys.append(_partners(geo, kind, np.concatenate(xs[1:]), pr, pl, rank_x, with_sin=False)[0])
    h_p = np.array([step * max(1.0, abs(v)) if kind == "arc" else step for v in pr])
    # The perturbed fits (+-h_p of each parameter in turn) move the partners
    # along the same epipolar lines: those are computed once, and all the
    # perturbations intersected in one call.
    m = 2 * len(pr)
    pp = np.repeat(pr[None], m, axis=0)
    pp[0::2][np.diag_indices(len(pr))] += h_p
    pp[1::2][np.diag_indices(len(pr))] -= h_p
    lines_r = geo.right_lines(x)
    rank_p = None if rank is None else np.tile(rank, m)
    y_p = _partners(geo, kind, None, np.repeat(pp, n, axis=0), pl, rank_p, np.tile(lines_r, (m, 1)), False)[0]
    xs.extend([x] * m)
    ys.append(y_p)
    Xall = triangulate(np.concatenate(xs), np.concatenate(ys), K1, K2, R, T).reshape(len(xs), n, 3)
    X = Xall[0]
    Jx = np.empty((n, 3, 2))
    for k in range(2):
        Jx[:, :, k] = (Xall[1 + 2 * k] - Xall[2 + 2 * k]) / (2 * h_x)
    Jp = np.empty((n, 3, len(pr)))
    for k in range(len(pr)):
        Jp[:, :, k] = (Xall[5 + 2 * k] - Xall[6 + 2 * k]) / (2 * h_p[k])
    cov_p = np.asarray(right.fit.cov, float)
    # A near-circle's axis angle is free (infinite variance, zero effect).
    cov_p = np.where(np.isfinite(cov_p), cov_p, 0.0)
    # Through one PSD factor (see partinspect.vision.psd): a short arc's fit
    # covariance is too ill-conditioned to propagate as the matrix it is.
    Lp = covariance_factor(cov_p)
    cov_p = Lp @ Lp.T
    cov_x = left.ideal.cov[idx]
    JL = np.einsum("nij,jk->nik", Jp, Lp)
    cov = np.einsum("nij,njk,nlk->nil", Jx, cov_x, Jx) + np.einsum("nik,nlk->nil", JL, JL)
    cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
    return Correspondences(idx, x, y, X, cov, int(len(keep) - n), Jx, Jp, cov_p, pr)
