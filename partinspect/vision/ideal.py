"""Edge measurements moved from distorted to ideal pixel coordinates.

The 2D chain works on the image as recorded (distorted pixels); the
projective geometry of two views (epipolar lines, triangulation, the 3D fits
of :mod:`partinspect.vision.fit3d`) needs *ideal* pixels, those a pinhole
camera with the same ``K`` would have recorded:
``x_ideal = K @ [undistort(K^-1 x_distorted), 1]``. The covariances follow
by first-order propagation through the Jacobian of that map (JCGM 100,
section 5.1), which is the inverse of the distortion Jacobian conjugated by
the linear part of ``K``.

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., section 7.4 (radial distortion).
.. [2] JCGM 100:2008, Evaluation of measurement data -- Guide to the
       expression of uncertainty in measurement, section 5.1.
"""

from dataclasses import dataclass, fields

import numpy as np

from partinspect.vision.calibration import distortion_jacobian, undistort_points

__all__ = ["IdealPoints", "IDEAL_FIELDS", "to_ideal", "ideal_points", "camera_matrices"]


@dataclass(frozen=True)
class IdealPoints:
    """Edge points in ideal pixel coordinates.

    Attributes
    ----------
    xy : ndarray, shape (N, 2)
        Ideal pixel coordinates, px.
    cov : ndarray, shape (N, 2, 2)
        Their covariances, px^2.
    normal : ndarray, shape (N, 2)
        Unit edge normals carried into the ideal image (co-vectors: mapped
        by the inverse transpose of the Jacobian).
    normal_std : ndarray, shape (N,)
        Standard uncertainty across the edge, ``sqrt(n^T cov n)``, px.
    jacobian : ndarray, shape (N, 2, 2)
        ``d x_ideal / d x_distorted`` at each point.
    """

    xy: np.ndarray
    cov: np.ndarray
    normal: np.ndarray
    normal_std: np.ndarray
    jacobian: np.ndarray

    def at(self, keep):
        """The points at positions ``keep`` (ndarray of int or bool), every field alike."""
        return IdealPoints(*(getattr(self, name)[keep] for name in IDEAL_FIELDS))


IDEAL_FIELDS = tuple(f.name for f in fields(IdealPoints))
"""The fields of :class:`IdealPoints`, in order: all are per point (first
axis N), so a subset of the points, or several sets joined, is made field by
field without mapping the points to ideal pixels again."""


def to_ideal(uv, K, D):
    """Ideal pixel coordinates of distorted pixels (no covariances).

    Parameters
    ----------
    uv : array_like, shape (N, 2)
        Distorted pixel coordinates (OpenCV pixel frame).
    K : ndarray, shape (3, 3)
    D : array_like
        OpenCV distortion vector.

    Returns
    -------
    ndarray, shape (N, 2)
        ``K @ [undistort_points(uv, K, D), 1]``, px.
    """
    xn = undistort_points(uv, K, D)
    return xn @ np.asarray(K, float)[:2, :2].T + np.asarray(K, float)[:2, 2]


def ideal_points(uv, cov, K, D, normal=None):
    """Map edge points and their covariances to ideal pixel coordinates.

    Parameters
    ----------
    uv : array_like, shape (N, 2)
        Distorted pixel coordinates.
    cov : array_like, shape (N, 2, 2)
        Their covariances, px^2.
    K : ndarray, shape (3, 3)
    D : array_like
        OpenCV distortion vector.
    normal : array_like, shape (N, 2), optional
        Unit edge normals in the distorted image; default: the eigenvector
        of the largest eigenvalue of each covariance (the across-edge
        direction for :class:`~partinspect.vision.edges.EdgePoints`).

    Returns
    -------
    IdealPoints

    Notes
    -----
    With ``x_d = K_2 d(x_n) + k`` and ``x_i = K_2 x_n + k`` (``K_2`` the
    upper-left 2x2 block of ``K``), ``d x_i / d x_d = K_2 J_d^-1 K_2^-1``
    where ``J_d`` is the distortion Jacobian at the undistorted point. The
    first-order covariance is ``J cov J^T``; the distortion is smooth on
    the scale of a pixel, so the second-order terms are far below the
    first (a few 1e-6 of a px^2 for the default rig).
    """
    uv = np.asarray(uv, float).reshape(-1, 2)
    cov = np.asarray(cov, float).reshape(-1, 2, 2)
    K = np.asarray(K, float)
    K2 = K[:2, :2]
    xn = undistort_points(uv, K, D)
    xy = xn @ K2.T + K[:2, 2]
    Jd = distortion_jacobian(xn, D)
    J = np.einsum("ij,njk,kl->nil", K2, np.linalg.inv(Jd), np.linalg.inv(K2))
    C = np.einsum("nij,njk,nlk->nil", J, cov, J)
    C = 0.5 * (C + np.transpose(C, (0, 2, 1)))
    if normal is None:
        _, vec = np.linalg.eigh(cov)
        normal = vec[:, :, 1]
    normal = np.asarray(normal, float).reshape(-1, 2)
    # A normal is a co-vector: it maps by the inverse transpose.
    n = np.einsum("nji,nj->ni", np.linalg.inv(J), normal)
    n /= np.linalg.norm(n, axis=1)[:, None]
    s = np.sqrt(np.einsum("ni,nij,nj->n", n, C, n))
    return IdealPoints(xy, C, n, s, J)


def camera_matrices(calib):
    """The two 3x4 camera matrices of a rig for ideal pixels.

    Returns
    -------
    P1, P2 : ndarray, shape (3, 4)
        ``K1 [I | 0]`` and ``K2 [R | T]``: rig frame (mm) to ideal pixels.
    """
    P1 = np.asarray(calib.K1, float) @ np.c_[np.eye(3), np.zeros(3)]
    P2 = np.asarray(calib.K2, float) @ np.c_[np.asarray(calib.R, float), np.asarray(calib.T, float).ravel()]
    return P1, P2
