"""Nominal geometry the tolerances need: distances and angles between edges.

Plain functions on numpy arrays (part frame, mm, radians). The same
definitions serve the nominal (CAD) and the measured value of a
characteristic, so what is compared is the same quantity.

Feature records are ``partinspect.cad.features.Feature`` or anything with
its fields: ``id``, ``kind`` ("line", "circle", "arc"); lines ``start``,
``end``; circles and arcs ``center``, ``normal``, ``radius``.

References
----------
.. [1] ISO 1101:2017, Geometrical product specifications (GPS) --
       Geometrical tolerancing (the features these quantities belong to).
.. [2] ISO 2768-1:1989, 4.3: an angle is toleranced by the length of its
       shorter leg.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "line_angle",
    "line_legs",
    "line_gap",
    "line_tilt",
    "angle_shorter_leg",
    "feature_distance",
    "lines_parallel",
]

# Below this sine two directions count as parallel: CAD directions agree to
# ~1e-12, so anything above 1e-9 is a real angle.
_PARALLEL_SIN = 1e-9
# Lines a distance is toleranced between must be parallel as the CAD module
# counts parallel (cad.features.DIRECTION_TOL).
_DISTANCE_PARALLEL_SIN = 1e-6
# Below this part of their length apart two lines are one line.
_COINCIDENT = 1e-6


def _vec(v):
    return np.asarray(v, dtype=float).reshape(3)


def _unit(v):
    v = _vec(v)
    n = np.linalg.norm(v)
    if n == 0:
        raise ValueError("zero-length direction")
    return v / n


_TIE = 1e-9
"""Relative difference of two distances below which they are equal (many
times the rounding of a closest point, far below any measured length)."""


def _closest_points(a0, da, b0, db):
    """Closest points of the infinite lines a0 + s da and b0 + t db (not parallel)."""
    w = a0 - b0
    a, b, c = da @ da, da @ db, db @ db
    d, e = da @ w, db @ w
    den = a * c - b * b
    s = (b * e - c * d) / den
    t = (a * e - b * d) / den
    return a0 + s * da, b0 + t * db


def line_angle(a_start, a_end, b_start, b_end, legs=None):
    """The angle between two line segments, in (0, pi) radians.

    The angle between the lines' directions, each turned to point along
    its segment away from where the two lines come closest: for lines in
    one plane, the vertex where they meet; for skew lines, the feet of
    their common perpendicular. Each leg runs from its foot towards the
    segment's endpoint farther from it. Two edges meeting at a corner so
    give the corner's angle (a 120 degree corner is 120 degrees, not 60),
    whichever way the edges are oriented.

    The legs are the lines' directions, not rays from one vertex to the
    far endpoints: for skew lines such rays would lean by the common
    perpendicular's length over the segment's, an angle neither line
    makes, and would change with where a measured segment ends. Two
    edges of perpendicular planes, each across their line of
    intersection, so give the dihedral angle however far apart the edges
    lie.

    Which way a leg points is decided by where the segment lies: where
    the segments cross, the foot lies inside them and the farther end can
    swap sides with where a measured edge is seen to end, turning the
    angle into its supplement (pi - angle). A measured angle is therefore
    taken with ``legs``: each measured direction turned to agree with the
    nominal (CAD) edges' legs, :func:`line_legs` of the nominal segments in
    the measured features' frame, so it is the angle the nominal names.

    Parameters
    ----------
    a_start, a_end, b_start, b_end : array_like, shape (3,)
        Endpoints of the two segments, one frame, mm.
    legs : (array_like, array_like), optional
        Reference directions, shape (3,) each, same frame: each segment's
        direction is turned to the side of its reference. Default: the
        legs found from the segments themselves (:func:`line_legs`).

    Returns
    -------
    float
        Radians.

    Raises
    ------
    ValueError
        If the lines are parallel (no vertex; use a distance or a
        parallelism tolerance instead).
    """
    a0, a1, b0, b1 = _vec(a_start), _vec(a_end), _vec(b_start), _vec(b_end)
    if legs is None:
        ua, ub = line_legs(a0, a1, b0, b1)
    else:
        ua, ub = _unit(a1 - a0), _unit(b1 - b0)
        if np.linalg.norm(np.cross(ua, ub)) < _PARALLEL_SIN:
            raise ValueError("the lines are parallel")
        ua, ub = (u if u @ _vec(ref) >= 0 else -u for u, ref in zip((ua, ub), legs))
    return math.acos(max(-1.0, min(1.0, float(ua @ ub))))


def line_legs(a_start, a_end, b_start, b_end):
    """The legs of the angle between two segments: unit directions, shape (3,) each.

    Each line's direction turned to point from the foot of the common
    perpendicular (the vertex of lines that meet) towards the segment's
    endpoint farther from it (:func:`line_angle`).

    Raises
    ------
    ValueError
        If the lines are parallel.
    """
    a0, a1, b0, b1 = _vec(a_start), _vec(a_end), _vec(b_start), _vec(b_end)
    da, db = _unit(a1 - a0), _unit(b1 - b0)
    if np.linalg.norm(np.cross(da, db)) < _PARALLEL_SIN:
        raise ValueError("the lines are parallel")
    pa, pb = _closest_points(a0, da, b0, db)
    return _leg(a0, a1, da, pa), _leg(b0, b1, db, pb)


def _leg(p0, p1, d, foot):
    """Unit direction ``+-d`` from ``foot`` (on the line) towards the segment's farther endpoint.

    Ends as far from the foot to rounding (``_TIE`` of the segment's length)
    are a tie, which the end point ``p1`` takes: which end the foot's last
    bit of rounding favours depends on the processor's floating-point path.
    """
    s0, s1 = float((p0 - foot) @ d), float((p1 - foot) @ d)
    far = s1 if abs(s1) >= abs(s0) - _TIE * abs(s1 - s0) else s0
    return d if far >= 0 else -d


def line_gap(a_start, a_end, b_start, b_end):
    """Length of the common perpendicular of two lines that are not parallel, mm (0 where they meet).

    Raises
    ------
    ValueError
        If the lines are parallel.
    """
    a0, b0 = _vec(a_start), _vec(b_start)
    n = np.cross(_unit(_vec(a_end) - a0), _unit(_vec(b_end) - b0))
    sin = float(np.linalg.norm(n))
    if sin < _PARALLEL_SIN:
        raise ValueError("the lines are parallel")
    return abs(float((b0 - a0) @ n)) / sin


def line_tilt(a_start, a_end, b_start, b_end, towards=None):
    """Signed tilt of line a against a parallel line b, towards a direction, radians.

    With ``u_b`` the unit direction of b (start to end), ``u_a`` a's turned
    to agree with it and ``w`` the unit direction the tilt is taken towards,
    made perpendicular to b, the tilt is ``asin(u_a . w)``: how fast a's
    distance from b, along ``w``, grows along b. Over a's length ``L`` that
    distance so spreads by ``L sin(tilt)``: the parallelism of a line to a
    datum plane with normal ``w`` (ISO 1101 18.5, a zone of two planes
    parallel to the datum). A tilt across ``w`` changes it only to second
    order. Zero for parallel lines; the sign follows b's orientation.

    Parameters
    ----------
    a_start, a_end, b_start, b_end : array_like, shape (3,)
    towards : array_like, shape (3,), optional
        The direction (a datum plane's normal), same frame. By default the
        offset from b to a's midpoint, across b: the plane the two span.

    Raises
    ------
    ValueError
        If the direction runs along b, or by default if the lines lie on
        one line.
    """
    a0, a1, b0, b1 = _vec(a_start), _vec(a_end), _vec(b_start), _vec(b_end)
    ua, ub = _unit(a1 - a0), _unit(b1 - b0)
    if ua @ ub < 0:
        ua = -ua
    v = 0.5 * (a0 + a1) - 0.5 * (b0 + b1) if towards is None else _unit(towards)
    across = v - (v @ ub) * ub
    dist = float(np.linalg.norm(across))
    scale = max(1.0, float(np.linalg.norm(b1 - b0))) if towards is None else 1.0
    if dist < _COINCIDENT * scale:
        raise ValueError("the lines lie on one line" if towards is None else "the direction runs along the lines")
    return math.asin(max(-1.0, min(1.0, float(ua @ across) / dist)))


def angle_shorter_leg(a_start, a_end, b_start, b_end):
    """Length of the shorter of the two segments, mm (ISO 2768-1 picks the angle tolerance by it)."""
    return min(float(np.linalg.norm(_vec(a_end) - _vec(a_start))), float(np.linalg.norm(_vec(b_end) - _vec(b_start))))


def feature_distance(fa, fb):
    """Nominal distance between two features, mm.

    - circle or arc to circle or arc: between the centres;
    - line to circle or arc: from the centre to the (infinite) line;
    - line to line: between parallel lines.

    Raises
    ------
    ValueError
        For two lines that are not parallel: their distance is not a size.
    """
    def is_line(f):
        return f.kind == "line"

    if not is_line(fa) and not is_line(fb):
        return float(np.linalg.norm(_vec(fa.center) - _vec(fb.center)))
    if is_line(fa) and is_line(fb):
        da, db = _unit(_vec(fa.end) - _vec(fa.start)), _unit(_vec(fb.end) - _vec(fb.start))
        sin = float(np.linalg.norm(np.cross(da, db)))
        if sin > _DISTANCE_PARALLEL_SIN:
            raise ValueError(f"the lines are not parallel ({math.degrees(math.asin(min(1.0, sin))):.3g} degrees apart)")
        return _point_line_distance(0.5 * (_vec(fb.start) + _vec(fb.end)), fa)
    line, other = (fa, fb) if is_line(fa) else (fb, fa)
    return _point_line_distance(other.center, line)


def _point_line_distance(p, line):
    a = _vec(line.start)
    d = _unit(_vec(line.end) - a)
    v = _vec(p) - a
    return float(np.linalg.norm(v - (v @ d) * d))


def lines_parallel(a_start, a_end, b_start, b_end):
    """Whether two lines are parallel as the CAD module counts parallel (for a distance, a parallelism)."""
    da, db = _unit(_vec(a_end) - _vec(a_start)), _unit(_vec(b_end) - _vec(b_start))
    return float(np.linalg.norm(np.cross(da, db))) <= _DISTANCE_PARALLEL_SIN
