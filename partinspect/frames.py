"""Orthonormal frames built from one direction.

Circles are stored by centre, normal and radius alone, so every module
that needs a circle's in-plane axes (angles along an arc, the tangent
plane of a line or normal for a fit's perturbations) must build the same
axes from the normal. This module is the one place that rule lives.
"""

import numpy as np

__all__ = ["reference_direction", "orthonormal_frame", "plane_basis"]


def reference_direction(normal):
    """The x axis of a circle's own frame, from its normal alone.

    Parameters
    ----------
    normal : array_like, shape (3,)
        Normal of the circle's plane (any length but zero).

    Returns
    -------
    ndarray, shape (3,)
        The world x axis projected into the plane and normalised; the world
        y axis instead when ``|normal[0]| > 0.9``, where the projection of x
        would be short and ill-conditioned.
    """
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    e = _world_axis(n)
    x = e - (e @ n) * n
    return x / np.linalg.norm(x)


def _world_axis(n):
    """The world axis a frame about ``n`` starts from: x, or y where ``|n[0]| > 0.9``."""
    return np.array([1.0, 0.0, 0.0]) if abs(n[0]) <= 0.9 else np.array([0.0, 1.0, 0.0])


def orthonormal_frame(normal):
    """A right-handed orthonormal frame whose third axis is ``normal``.

    Parameters
    ----------
    normal : array_like, shape (3,)
        Unit normal (a circle's axis, a line's direction).

    Returns
    -------
    ndarray, shape (3, 3)
        Rows x, y, n: ``x = reference_direction(n)``, ``y = n x x``. Angles
        along a circle are measured in this frame: the point at angle t is
        ``center + radius * (cos t * x + sin t * y)``.
    """
    n = np.asarray(normal, dtype=float)
    x = reference_direction(n)
    return np.array([x, np.cross(n, x), n])


def plane_basis(d):
    """(3, 2) orthonormal basis of the plane normal to unit ``d``.

    The columns are ``d x e`` and ``d x (d x e)``, e the world axis
    :func:`reference_direction` takes: the y axis and the negated x axis of
    ``orthonormal_frame(d)``, computed from ``d`` directly. They are the
    directions in which a fit perturbs a line's direction or a circle's
    normal; their order and signs fix the parametrisation of the fits'
    minimal covariances.
    """
    d = np.asarray(d, dtype=float)
    e1 = np.cross(d, _world_axis(d))
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(d, e1)], 1)
