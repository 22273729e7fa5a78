"""A broken edge's unpredicted band place: its size in each camera and its modes round a rim.

A rounded or chamfered edge (ISO 13715) shows the images not one step but
a band, the break's width across, on which the grey level's step lies
somewhere: where, follows the band's surface normal against the light and
the line of sight. Where that place is not predicted
(:mod:`partinspect.vision.band_place` predicts it only where it can),
it is a Type B component of the edge's image: per camera, its size in
pixels at the edge's depth (:func:`edge_band`); round a rim, a smooth
function of the rim's angle, carried as the modes of its longest waves
(:func:`band_harmonics`), each an unknown coefficient of stated standard
uncertainty.

References
----------
.. [1] ISO 13715:2019, Technical product documentation -- Edges of
       undefined shape -- Indication and dimensioning.
.. [2] JCGM 100:2008 (GUM), 4.3.7 (a quantity known only to lie in an
       interval: rectangular distribution) and 5.2 (correlated input
       quantities).
"""

from typing import NamedTuple

import numpy as np

from partinspect.vision.fitting import ellipse_geometry

__all__ = ["EdgeBand", "edge_band", "band_harmonics", "BAND_MEAN_SHARE", "BAND_HARMONIC_SHARE", "BAND_HARMONICS"]

BAND_MEAN_SHARE = 0.5
"""Standard uncertainty of a broken rim's mean band place over the RMS
distance ``b`` of the step from the sharp edge (:func:`edge_band`): the
place is taken anywhere on a band of width ``w``, uniform, so
``b = w / sqrt(3)`` and the mean's u is ``w / sqrt(12) = b / 2``."""

BAND_HARMONICS = 3
"""The waves round a rim that the band's place is carried in: the first
three harmonics of the normal's angle. The place follows the band's
shading, a smooth function of two first harmonics (the light's and the
view's component along the normal), clipped where the band turns into
its own shadow: its shape round the rim is in the longest waves. These
are also the waves a fit of a partial arc cannot tell from its radius and
centre; shorter ones average out along it."""

BAND_HARMONIC_SHARE = float(np.sqrt(3.0 / 24.0))
"""Standard uncertainty of each component of each harmonic of the band
place over ``b``: its amplitude uniform between 0 and half the band at an
unknown angle, so each component's variance is ``w^2 / 24``, ``b sqrt(3 / 24)``
= 0.354 b. Over ``BAND_HARMONICS`` harmonics the place's variance about
its mean is then ``w^2 / 8``: more than a place uniform on the band
independently at each point (``w^2 / 12``), half of the most a place that
stays on the band can have (``w^2 / 4``, a square wave between its edges)."""


class EdgeBand(NamedTuple):
    """Where a broken edge's step lies across its band, per camera (:func:`edge_band`)."""

    left: float
    """Standard uncertainty in the left image, px."""
    right: float
    """In the right image, px."""
    parallax: float
    """The share of it that differs between the two cameras: the angle
    between their lines of sight to the feature over the quarter turn
    through which the band's surface normal turns (at most 1)."""


def edge_band(points, geo, edge_break):
    """Per view, the standard uncertainty, px, of where a broken edge's step lies across its band.

    ``edge_break`` is the RMS distance, mm, of the apparent step from the
    sharp edge over the break's band and sizes; at the points' median depth
    in each camera it is ``edge_break * f / Z`` px. Where on the band the
    step appears depends on the band's normal against the light and the
    line of sight: across a rounded band the normal turns through a quarter
    turn, so two cameras whose lines of sight differ by an angle ``a`` see
    it at places that differ by up to ``a / (pi / 2)`` of the band
    (``parallax``); the rest is common to them.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        The feature's triangulated points, rig frame, mm.
    geo : EpipolarGeometry
    edge_break : float
        mm.

    Returns
    -------
    EdgeBand
    """
    z_left = float(np.median(points[:, 2]))
    z_right = float(np.median(points @ np.asarray(geo.R)[2] + np.asarray(geo.T).ravel()[2]))
    centre = np.median(points, axis=0)
    eye_right = -np.asarray(geo.R).T @ np.asarray(geo.T).ravel()
    a, b = centre / np.linalg.norm(centre), (centre - eye_right) / np.linalg.norm(centre - eye_right)
    angle = float(np.arccos(np.clip(a @ b, -1.0, 1.0)))
    return EdgeBand(edge_break * geo.K1[0, 0] / z_left, edge_break * geo.K2[0, 0] / z_right,
                    min(angle / (0.5 * np.pi), 1.0))


def band_harmonics(xy, fit, band):
    """A broken rim's band place in one image as modes: its mean round the rim and its longest waves, px.

    The step's place across a rounded or chamfered rim's band follows the
    band's normal against the light and the view, smoothly round the rim:
    its mean moves every point alike (the radius), its first harmonic moves
    the rim's image as a whole (the centre), the second and third bend it
    (on a partial arc, radius and centre again). Each is one unknown
    coefficient (``BAND_MEAN_SHARE``, ``BAND_HARMONIC_SHARE`` times
    ``band``, :func:`edge_band`'s RMS distance of the step from the sharp
    edge). Carried as a field correlated over a fraction of the rim instead,
    the band's wiggles on a partial arc trade radius against centre and
    state them several times larger than any place on the band can move
    them.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        The rim's points, ideal px.
    fit : EllipseFit
        The image ellipse (its ``params`` and the points' ``phases``).
    band : float
        px.

    Returns
    -------
    ndarray, shape (1 + 2 * BAND_HARMONICS, N)
        Displacements along each point's outward normal, whose angle is
        ``t``: ``band`` times ``BAND_MEAN_SHARE``, then
        ``BAND_HARMONIC_SHARE`` times ``cos(k t)`` and ``sin(k t)`` for
        k = 1 .. ``BAND_HARMONICS``.
    """
    _, n, _ = ellipse_geometry(xy, fit.params, fit.phases)
    t = np.arctan2(n[:, 1], n[:, 0])
    k = np.arange(1, BAND_HARMONICS + 1)[:, None]
    waves = np.stack([np.cos(k * t), np.sin(k * t)], axis=1).reshape(2 * BAND_HARMONICS, len(xy))
    return band * np.vstack([np.full((1, len(xy)), BAND_MEAN_SHARE), BAND_HARMONIC_SHARE * waves])
