"""Optimal two-view triangulation with first-order 3D covariances.

Points are given in *ideal* pixel coordinates: distortion already removed
(``K @ [undistort_points(uv), 1]``), so each camera is a pinhole
``P1 = K1 [I | 0]``, ``P2 = K2 [R | T]`` in the rig (left camera) frame.

References
----------
.. [1] Lindstrom, P. (2010). Triangulation made easy. CVPR 2010,
       1554-1561: the niter2 correction used here.
.. [2] Hartley, R. I., & Sturm, P. (1997). Triangulation. Computer Vision
       and Image Understanding 68(2), 146-157.
.. [3] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., sections 5.2 (covariance of an estimate by
       back-propagation) and 9.2 (the fundamental matrix).
"""

import numpy as np

__all__ = ["fundamental_matrix", "correct_matches", "triangulate", "triangulation_covariance"]


def _skew(t):
    t = np.asarray(t, dtype=float).ravel()
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def fundamental_matrix(K1, K2, R, T):
    """Fundamental matrix F with ``x2^T F x1 = 0`` for ideal pixel coordinates.

    Parameters
    ----------
    K1, K2 : ndarray, shape (3, 3)
    R : ndarray, shape (3, 3)
    T : ndarray, shape (3,)
        ``X_right = R X_left + T``.

    Returns
    -------
    F : ndarray, shape (3, 3), scaled to unit Frobenius norm.
    """
    F = np.linalg.inv(K2).T @ _skew(T) @ R @ np.linalg.inv(K1)
    return F / np.linalg.norm(F)


def correct_matches(x1, x2, F):
    """Move each match the least (in image distance) to satisfy the epipolar constraint.

    Lindstrom's niter2: two Newton-like steps, which for real camera
    geometry reach the Hartley-Sturm optimum to machine precision.

    Parameters
    ----------
    x1, x2 : ndarray, shape (N, 2)
        Ideal pixel coordinates in the left and right image.
    F : ndarray, shape (3, 3)

    Returns
    -------
    y1, y2 : ndarray, shape (N, 2)
        Corrected coordinates with ``y2^T F y1 = 0``.
    """
    x1 = np.asarray(x1, dtype=float)
    x2 = np.asarray(x2, dtype=float)
    Ft = F[:2, :2]
    h1 = np.c_[x1, np.ones(len(x1))]
    h2 = np.c_[x2, np.ones(len(x2))]
    # Gradients of the epipolar residual c = x2^T F x1 with respect to x2 and x1.
    n2 = (h1 @ F.T)[:, :2]
    n1 = (h2 @ F)[:, :2]
    a = np.einsum("ni,ij,nj->n", n2, Ft, n1)
    b = 0.5 * (np.einsum("ni,ni->n", n1, n1) + np.einsum("ni,ni->n", n2, n2))
    c = np.einsum("ni,ij,nj->n", h2, F, h1)
    d = np.sqrt(np.maximum(b * b - a * c, 0.0))
    lam = c / (b + d)
    d1, d2 = lam[:, None] * n1, lam[:, None] * n2
    # Second iteration: the gradients at the first-order corrected points.
    n2 = n2 - d1 @ Ft.T
    n1 = n1 - d2 @ Ft
    lam = lam * 2 * d / (np.einsum("ni,ni->n", n1, n1) + np.einsum("ni,ni->n", n2, n2))
    return x1 - lam[:, None] * n1, x2 - lam[:, None] * n2


def triangulate(x1, x2, K1, K2, R, T):
    """Optimal (maximum-likelihood under isotropic image noise) triangulation.

    Parameters
    ----------
    x1, x2 : ndarray, shape (N, 2)
        Matching ideal pixel coordinates, left and right.
    K1, K2, R, T : camera matrices and the left-to-right motion (mm).

    Returns
    -------
    X : ndarray, shape (N, 3)
        Points in the rig (left camera) frame, mm.
    """
    y1, y2 = correct_matches(x1, x2, fundamental_matrix(K1, K2, R, T))
    # The corrected rays intersect exactly; solve the 2-unknown depth system in least squares.
    r1 = np.c_[y1, np.ones(len(y1))] @ np.linalg.inv(K1).T  # left ray directions
    r2 = np.c_[y2, np.ones(len(y2))] @ np.linalg.inv(K2).T @ R  # right rays, rotated into the left frame
    c2 = -R.T @ np.asarray(T, dtype=float).ravel()  # right camera centre in the rig frame
    # Minimise |s r1 - (c2 + t r2)|: normal equations of a 2x2 system per point.
    a11 = np.einsum("ni,ni->n", r1, r1)
    a12 = -np.einsum("ni,ni->n", r1, r2)
    a22 = np.einsum("ni,ni->n", r2, r2)
    b1 = r1 @ c2
    b2 = -(r2 @ c2)
    det = a11 * a22 - a12 * a12
    s = (a22 * b1 - a12 * b2) / det
    t = (a11 * b2 - a12 * b1) / det
    return 0.5 * (s[:, None] * r1 + c2 + t[:, None] * r2)


def _projection_jacobian(X, K, R, T):
    """d(ideal pixel)/dX for a pinhole camera x = K (R X + T); shape (N, 2, 3)."""
    Xc = X @ R.T + T
    z = Xc[:, 2]
    J = np.zeros((len(X), 2, 3))
    J[:, 0, 0] = 1 / z
    J[:, 0, 2] = -Xc[:, 0] / z**2
    J[:, 1, 1] = 1 / z
    J[:, 1, 2] = -Xc[:, 1] / z**2
    return np.einsum("ij,njk,kl->nil", K[:2, :2], J, R)


def triangulation_covariance(X, cov1, cov2, K1, K2, R, T):
    """First-order covariance of triangulated points.

    The back-propagation of [3]_: for the maximum-likelihood point,
    ``Sigma_X = (J^T W J)^-1`` with ``J`` (4x3) the derivative of both
    projections at X and ``W = blockdiag(cov1^-1, cov2^-1)``.

    Parameters
    ----------
    X : ndarray, shape (N, 3)
        Triangulated points, rig frame, mm.
    cov1, cov2 : ndarray, shape (N, 2, 2) or (2, 2)
        Covariances of the ideal pixel coordinates in each image, px^2.
    K1, K2, R, T : the calibration.

    Returns
    -------
    cov : ndarray, shape (N, 3, 3)
        Covariance of each point, mm^2, rig frame.
    """
    X = np.asarray(X, dtype=float)
    n = len(X)
    W1 = np.linalg.inv(np.broadcast_to(cov1, (n, 2, 2)))
    W2 = np.linalg.inv(np.broadcast_to(cov2, (n, 2, 2)))
    J1 = _projection_jacobian(X, K1, np.eye(3), np.zeros(3))
    J2 = _projection_jacobian(X, K2, R, np.asarray(T, dtype=float).ravel())
    info = np.einsum("nji,njk,nkl->nil", J1, W1, J1) + np.einsum("nji,njk,nkl->nil", J2, W2, J2)
    cov = np.linalg.inv(info)
    return 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
