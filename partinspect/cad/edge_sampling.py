"""Points and tangents along a CAD edge, and its geometry as arrays.

Every stage that reasons about an edge's image (visibility, the expected
image of an edge for pose-guided measurement, the planner, the renderer's
truth) samples the CAD edge the same way: points at the middles of equal
pieces, so no sample falls on a corner, at about one per 0.25 mm.

Part frame (STEP), mm; angles in radians.
"""

import math

import numpy as np

from partinspect.frames import orthonormal_frame

__all__ = ["feature_geometry", "sample_edge"]

_SAMPLE_SPACING = 0.25  # mm between edge samples
_MIN_SAMPLES, _MAX_SAMPLES = 24, 400


def feature_geometry(feature):
    """The geometry of an inventory feature as a dict of arrays.

    Parameters
    ----------
    feature : partinspect.cad.features.Feature

    Returns
    -------
    dict
        Lines: ``start``, ``end``. Circles: ``center``, ``normal``,
        ``radius``. Arcs: those of a circle plus ``start``, ``end``,
        ``angle_start``, ``angle_end`` (radians, counter-clockwise about
        ``normal`` from ``reference_direction(normal)``). Part frame, mm.
    """
    if feature.kind == "line":
        return {"start": np.array(feature.start, float), "end": np.array(feature.end, float)}
    g = {"center": np.array(feature.center, float), "normal": np.array(feature.normal, float), "radius": float(feature.radius)}
    if feature.kind == "arc":
        g.update(
            start=np.array(feature.start, float),
            end=np.array(feature.end, float),
            angle_start=float(feature.angle_start),
            angle_end=float(feature.angle_end),
        )
    return g


def sample_edge(kind, geometry, n=None):
    """Points and unit tangents along an edge, away from its ends.

    Parameters
    ----------
    kind : {"line", "circle", "arc"}
    geometry : dict
        As :func:`feature_geometry` returns.
    n : int, optional
        Number of samples; default one per 0.25 mm, between 24 and 400.
        They sit at the middles of ``n`` equal pieces, so no sample falls on
        an end point (a corner).

    Returns
    -------
    points, tangents : ndarray, shape (n, 3)
        Part frame, mm; unit tangents.
    """
    if kind == "line":
        a, b = geometry["start"], geometry["end"]
        extent = float(np.linalg.norm(b - a))
    else:
        c, r = geometry["center"], geometry["radius"]
        t0, t1 = (0.0, 2 * math.pi) if kind == "circle" else (geometry["angle_start"], geometry["angle_end"])
        extent = r * (t1 - t0)
    if n is None:
        n = int(np.clip(math.ceil(extent / _SAMPLE_SPACING), _MIN_SAMPLES, _MAX_SAMPLES))
    s = (np.arange(n) + 0.5) / n
    if kind == "line":
        return a + s[:, None] * (b - a), np.repeat(((b - a) / extent)[None], n, axis=0)
    x, y = orthonormal_frame(geometry["normal"])[:2]
    t = t0 + s * (t1 - t0)
    cos, sin = np.cos(t)[:, None], np.sin(t)[:, None]
    return c + r * (cos * x + sin * y), -sin * x + cos * y
