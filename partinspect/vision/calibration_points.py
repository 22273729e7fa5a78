"""The calibration's error in a feature's triangulated points: how it bends them, not only where it puts the fit.

A calibration that states its covariance moves every 3D feature's fitted
parameters (:mod:`partinspect.vision.calibration_uncertainty`), but the
form of an edge (straightness, circularity) is judged on its triangulated
points, and a wrong calibration does more to them than move the whole
feature. Each left edge point's partner is where its epipolar line crosses
the right fitted curve (:func:`partinspect.vision.correspondences.correspond`):
an error of the epipolar geometry of e px slides the partner along that
curve by about ``e / sin(crossing angle)``, little where the epipolar lines
cross a rim steeply and several times more towards its epipolar tangent
points, so the depth error varies round the rim and bends the circle out of
round; the intrinsics' and distortion's errors re-map each image's points
unevenly. That distortion is common to all the feature's points (one
calibration, one error), and a form value's Monte Carlo has to draw it
(:class:`partinspect.vision.pointerrors.PointErrorModel`) or it reads the
bend as form.

The response of every point to each principal direction of the stated
covariance (:func:`~partinspect.vision.calibration_uncertainty.uncertainty_directions`)
is found by central differences at +-1 standard deviation, as the fitted
parameters' are: the recorded pixels of both points are read again with the
moved intrinsics and distortion, the partner slides along the right curve's
tangent to the moved epipolar line, and the pair is triangulated with the
moved cameras. With independent standard normal ``z_j``, ``sum_j z_j g_j``
is a draw of the points' error from the calibration [1]_, [2]_.

Units: ideal pixels (undistorted, OpenCV pixel frame), 3D points in the rig
(left camera) frame, mm.

References
----------
.. [1] JCGM 100:2008, Evaluation of measurement data -- Guide to the
       expression of uncertainty in measurement, section 5.2 (correlated
       input quantities).
.. [2] JCGM 101:2008, Supplement 1 to the GUM: propagation of
       distributions using a Monte Carlo method, section 6.4.8.
.. [3] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., sections 9.2 and 12.5.
"""

import numpy as np

from partinspect.vision.calibration import distort_normalized, distortion_jacobian
from partinspect.vision.calibration_uncertainty import perturbed_calibration, uncertainty_directions
from partinspect.vision.triangulation import fundamental_matrix, triangulate

__all__ = ["reread", "curve_tangents", "point_responses"]


def reread(xy, K, D, steps=3):
    """Ideal pixels re-read with other intrinsics, as a function of them.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Ideal pixels under ``K``, ``D`` (OpenCV's camera matrix and
        distortion vector).
    steps : int
        Newton steps of the undistortion, started from the points'
        normalised coordinates under ``K``, ``D`` and with their distortion
        Jacobian there (computed once for every re-reading): for a board
        session's intrinsics moved by one standard uncertainty, three steps
        leave under 1e-4 px in the corners of the image, where the
        distortion is largest, against responses of tenths of a pixel.

    Returns
    -------
    callable
        ``read(K_new, D_new) -> ndarray (N, 2)``: where ``K_new``, ``D_new``
        put the recorded pixels that ``K``, ``D`` put at ``xy``.
    """
    K = np.asarray(K, float)
    xn = (np.asarray(xy, float) - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
    uv = distort_normalized(xn, D) @ K[:2, :2].T + K[:2, 2]
    Jinv = np.linalg.inv(distortion_jacobian(xn, D))

    def read(K_new, D_new):
        K_new = np.asarray(K_new, float)
        target = (uv - K_new[:2, 2]) @ np.linalg.inv(K_new[:2, :2]).T
        x = xn
        for _ in range(steps):
            x = x + np.einsum("nij,nj->ni", Jinv, target - distort_normalized(x, D_new))
        return x @ K_new[:2, :2].T + K_new[:2, 2]

    return read


def curve_tangents(params, y):
    """Unit tangents (N, 2) of a fitted image curve at points ``y`` (N, 2) on it.

    ``params``: a line's (a, b, c) of ``a x + b y + c = 0``, or an ellipse's
    (xc, yc, a, b, theta), px and rad. The sense is arbitrary.
    """
    params = np.asarray(params, float)
    if len(params) == 3:
        t = np.array([-params[1], params[0]]) / np.hypot(params[0], params[1])
        return np.tile(t, (len(y), 1))
    xc, yc, a, b, th = params
    ct, st = np.cos(th), np.sin(th)
    qx, qy = y[:, 0] - xc, y[:, 1] - yc
    # The implicit form's gradient in the ellipse frame, turned back to the image.
    gu, gv = (qx * ct + qy * st) / (a * a), (-qx * st + qy * ct) / (b * b)
    g = np.c_[gu * ct - gv * st, gu * st + gv * ct]
    return np.c_[-g[:, 1], g[:, 0]] / np.hypot(g[:, 0], g[:, 1])[:, None]


def _retriangulated(read_left, read_right, tangent, moved):
    """Left points and right partners triangulated as the ``moved`` calibration reads them (:func:`reread`)."""
    x2 = read_left(moved.K1, moved.D1)
    y2 = read_right(moved.K2, moved.D2)
    F = fundamental_matrix(moved.K1, moved.K2, np.asarray(moved.R, float), np.asarray(moved.T, float).ravel())
    lines = np.c_[x2, np.ones(len(x2))] @ F.T
    # The partner slides along the right curve (locally its tangent) to the
    # moved epipolar line; the curve's own bend over that slide is second
    # order and cancels between the two central differences.
    s = -(np.einsum("ni,ni->n", lines[:, :2], y2) + lines[:, 2]) / np.einsum("ni,ni->n", lines[:, :2], tangent)
    return triangulate(x2, y2 + s[:, None] * tangent, moved.K1, moved.K2, moved.R, moved.T)


def point_responses(corr, calib):
    """First-order responses of a feature's triangulated points to the calibration's uncertainty.

    Parameters
    ----------
    corr : Correspondences
        With ``left``, ``right`` (ideal px) and ``right_params`` (the right
        fitted curve the partners lie on).
    calib : StereoCalibration
        The calibration the points were triangulated with, with ``std``
        and ``cov`` where it states one.

    Returns
    -------
    ndarray, shape (N, 3, q)
        Column j: the change of every point, mm, when the calibration moves
        along the j-th of its q principal directions of uncertainty
        (central differences at +-1 standard deviation); q = 0 when it
        states none. ``sum_j g_j g_j^T`` per point is its covariance from
        the calibration, and one standard normal deviate per direction,
        common to all points, draws the whole feature's error.
    """
    directions = uncertainty_directions(calib)
    n = len(corr.points)
    if not directions or n == 0 or corr.right_params is None:
        return np.zeros((n, 3, 0))
    x, y = np.asarray(corr.left, float), np.asarray(corr.right, float)
    tangent = curve_tangents(corr.right_params, y)
    read_left, read_right = reread(x, calib.K1, calib.D1), reread(y, calib.K2, calib.D2)
    out = np.empty((n, 3, len(directions)))
    for j, d in enumerate(directions):
        up, down = (_retriangulated(read_left, read_right, tangent,
                                    perturbed_calibration(calib, {k: s * v for k, v in d.items()}))
                    for s in (1.0, -1.0))
        out[:, :, j] = 0.5 * (up - down)
    return out
