"""ISO 2768 general tolerances: the tables and the rules for using them.

A drawing that says "ISO 2768-mK" puts every dimension without its own
tolerance under linear class ``m`` of ISO 2768-1 and every form or location
without its own tolerance under geometrical class ``K`` of ISO 2768-2.

The tables are transcribed as printed in the module's constants: ISO 2768-1
table 1 (linear dimensions, ``LINEAR``), table 2 (broken edges,
``BROKEN_EDGE``), table 3 (angles by the shorter leg, ``ANGULAR``, in
degrees and minutes); ISO 2768-2 table 1 (straightness and flatness), 2
(perpendicularity), 3 (symmetry), 4 (circular run-out). Below 0.5 mm, and
in the "--" cells, the standard sets no general tolerance: the deviation
must be indicated next to the dimension (:class:`NoGeneralTolerance`).
Range boundaries follow the standard's wording: "over 6 up to 30" is the
half-open interval (6, 30]; the first range of each table is closed.

The general circularity tolerance (ISO 2768-2:1989, 5.2.2) equals the
numerical value of the diameter tolerance (individual or general), but is
never larger than the circular radial run-out tolerance of table 4
(:func:`circularity_tolerance`).
Lengths in mm, angles returned in radians.

References
----------
.. [1] ISO 2768-1:1989, General tolerances -- Part 1: Tolerances for linear
       and angular dimensions without individual tolerance indications.
.. [2] ISO 2768-2:1989, General tolerances -- Part 2: Geometrical tolerances
       for features without individual tolerance indications.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

__all__ = [
    "LINEAR_CLASSES",
    "GEOMETRICAL_CLASSES",
    "LINEAR_RANGES",
    "LINEAR",
    "BROKEN_EDGE_RANGES",
    "BROKEN_EDGE",
    "ANGULAR_RANGES",
    "ANGULAR",
    "STRAIGHTNESS_RANGES",
    "STRAIGHTNESS_FLATNESS",
    "PERPENDICULARITY_RANGES",
    "PERPENDICULARITY",
    "SYMMETRY",
    "CIRCULAR_RUNOUT",
    "NoGeneralTolerance",
    "GeneralClass",
    "parse_general",
    "linear_tolerance",
    "broken_edge_tolerance",
    "angular_tolerance",
    "straightness_tolerance",
    "flatness_tolerance",
    "perpendicularity_tolerance",
    "symmetry_tolerance",
    "runout_tolerance",
    "circularity_tolerance",
    "range_label",
    "range_index",
]

LINEAR_CLASSES = ("f", "m", "c", "v")
GEOMETRICAL_CLASSES = ("H", "K", "L")

# Each range is (low, high): the first one of a table is [low, high], the
# others (low, high], as the standard words them ("over 3 up to 6").
LINEAR_RANGES = ((0.5, 3.0), (3.0, 6.0), (6.0, 30.0), (30.0, 120.0), (120.0, 400.0), (400.0, 1000.0), (1000.0, 2000.0), (2000.0, 4000.0))
# ISO 2768-1 table 1, permissible deviation +- value in mm; None is the "--" entry.
LINEAR = {
    "f": (0.05, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5, None),
    "m": (0.1, 0.1, 0.2, 0.3, 0.5, 0.8, 1.2, 2.0),
    "c": (0.2, 0.3, 0.5, 0.8, 1.2, 2.0, 3.0, 4.0),
    "v": (None, 0.5, 1.0, 1.5, 2.5, 4.0, 6.0, 8.0),
}

BROKEN_EDGE_RANGES = ((0.5, 3.0), (3.0, 6.0), (6.0, math.inf))
# ISO 2768-1 table 2.
BROKEN_EDGE = {
    "f": (0.2, 0.5, 1.0),
    "m": (0.2, 0.5, 1.0),
    "c": (0.4, 1.0, 2.0),
    "v": (0.4, 1.0, 2.0),
}

ANGULAR_RANGES = ((0.0, 10.0), (10.0, 50.0), (50.0, 120.0), (120.0, 400.0), (400.0, math.inf))
# ISO 2768-1 table 3, as (degrees, minutes) exactly as printed.
ANGULAR = {
    "f": ((1, 0), (0, 30), (0, 20), (0, 10), (0, 5)),
    "m": ((1, 0), (0, 30), (0, 20), (0, 10), (0, 5)),
    "c": ((1, 30), (1, 0), (0, 30), (0, 15), (0, 10)),
    "v": ((3, 0), (2, 0), (1, 0), (0, 30), (0, 20)),
}

STRAIGHTNESS_RANGES = ((0.0, 10.0), (10.0, 30.0), (30.0, 100.0), (100.0, 300.0), (300.0, 1000.0), (1000.0, 3000.0))
# ISO 2768-2 table 1, tolerance in mm.
STRAIGHTNESS_FLATNESS = {
    "H": (0.02, 0.05, 0.1, 0.2, 0.3, 0.4),
    "K": (0.05, 0.1, 0.2, 0.4, 0.6, 0.8),
    "L": (0.1, 0.2, 0.4, 0.8, 1.2, 1.6),
}

PERPENDICULARITY_RANGES = ((0.0, 100.0), (100.0, 300.0), (300.0, 1000.0), (1000.0, 3000.0))
# ISO 2768-2 table 2 (by the shorter side) and table 3 (symmetry, same ranges).
PERPENDICULARITY = {
    "H": (0.2, 0.3, 0.4, 0.5),
    "K": (0.4, 0.6, 0.8, 1.0),
    "L": (0.6, 1.0, 1.5, 2.0),
}
SYMMETRY = {
    "H": (0.5, 0.5, 0.5, 0.5),
    "K": (0.6, 0.6, 0.8, 1.0),
    "L": (0.6, 1.0, 1.5, 2.0),
}

# ISO 2768-2 table 4.
CIRCULAR_RUNOUT = {"H": 0.1, "K": 0.2, "L": 0.5}

# CAD lengths come out of OCCT with float noise (29.999999999997); rounding
# to a nanometre-scale grid first keeps a nominal 30 in the range "up to 30".
_ROUND_DECIMALS = 6


class NoGeneralTolerance(ValueError):
    """ISO 2768 defines no general tolerance for this size and class."""


@dataclass(frozen=True)
class GeneralClass:
    """A general-tolerance designation such as ISO 2768-mK.

    Attributes
    ----------
    linear : str
        ISO 2768-1 class, one of "f", "m", "c", "v".
    geometrical : str or None
        ISO 2768-2 class, one of "H", "K", "L"; None when the designation
        names only a linear class ("ISO 2768-m").
    """

    linear: str
    geometrical: str | None = None

    @property
    def designation(self):
        """The designation as ISO 2768 writes it, e.g. "ISO 2768-mK"."""
        return f"ISO 2768-{self.linear}{self.geometrical or ''}"

    def __str__(self):
        return self.designation


_GENERAL_RE = re.compile(r"^\s*(?:(?:DIN\s*)?ISO\s*2768\s*-?\s*)?([fmcv])([hkl])?\s*$", re.IGNORECASE)


def parse_general(text):
    """Parse a general-tolerance designation.

    Parameters
    ----------
    text : str
        "ISO2768-mK", "ISO 2768-mK", "mK", "ISO 2768-m" (linear only); the
        letters in any case, since the two class alphabets do not overlap.

    Returns
    -------
    GeneralClass

    Raises
    ------
    ValueError
        If the text is no such designation.

    Examples
    --------
    >>> parse_general("ISO2768-mk").designation
    'ISO 2768-mK'
    """
    m = _GENERAL_RE.match(text) if isinstance(text, str) else None
    if m is None:
        raise ValueError(
            f"expected an ISO 2768 class like 'ISO 2768-mK' (linear class f, m, c or v, "
            f"then geometrical class H, K or L), got {text!r}"
        )
    return GeneralClass(m.group(1).lower(), None if m.group(2) is None else m.group(2).upper())


def range_index(ranges, value, what="size", standard="ISO 2768"):
    """Index of the table range holding ``value`` (mm); NoGeneralTolerance outside the table."""
    if not math.isfinite(value):
        raise NoGeneralTolerance(f"{what} must be a finite number, got {value}")
    v = round(float(value), _ROUND_DECIMALS)
    low0 = ranges[0][0]
    if v < low0:
        raise NoGeneralTolerance(f"{standard} sets no general tolerance below {_fmt(low0)} mm; give one in the spec")
    for i, (low, high) in enumerate(ranges):
        if (v >= low if i == 0 else v > low) and v <= high:
            return i
    raise NoGeneralTolerance(
        f"{standard} sets no general tolerance above {_fmt(ranges[-1][1])} mm; give one in the spec"
    )


def _fmt(x):
    return f"{x:g}"


def range_label(ranges, i):
    """The standard's wording of range ``i`` of a table, e.g. "over 6 up to 30 mm"."""
    low, high = ranges[i]
    if math.isinf(high):
        return f"over {_fmt(low)} mm"
    if i == 0:
        return f"up to {_fmt(high)} mm" if low == 0 else f"{_fmt(low)} up to {_fmt(high)} mm"
    return f"over {_fmt(low)} up to {_fmt(high)} mm"


def _check_class(cls, allowed, standard):
    if cls not in allowed:
        raise ValueError(f"{standard} class must be one of {', '.join(allowed)}, got {cls!r}")


def linear_tolerance(nominal_mm, cls):
    """General limit deviations of a linear dimension (ISO 2768-1, table 1).

    Parameters
    ----------
    nominal_mm : float
        Nominal size, mm (a length, distance, diameter or radius).
    cls : str
        Linear class "f", "m", "c" or "v".

    Returns
    -------
    lower, upper : float
        Limit deviations in mm, ``lower = -upper``.

    Raises
    ------
    NoGeneralTolerance
        Below 0.5 mm, above 4000 mm, and in the "--" cells (class f over
        2000 mm, class v up to 3 mm).

    Examples
    --------
    >>> linear_tolerance(50.0, "m")
    (-0.3, 0.3)

    References
    ----------
    .. [1] ISO 2768-1:1989, table 1.
    """
    _check_class(cls, LINEAR_CLASSES, "ISO 2768-1")
    i = range_index(LINEAR_RANGES, nominal_mm, "nominal size", "ISO 2768-1")
    t = LINEAR[cls][i]
    if t is None:
        raise NoGeneralTolerance(
            f"ISO 2768-1 class {cls} sets no general tolerance {range_label(LINEAR_RANGES, i)}; give one in the spec"
        )
    return (-t, t)


def broken_edge_tolerance(nominal_mm, cls):
    """General limit deviations of an external radius or chamfer height of a broken edge.

    Parameters
    ----------
    nominal_mm : float
        Radius or chamfer height, mm.
    cls : str
        Linear class "f", "m", "c" or "v".

    Returns
    -------
    lower, upper : float
        Limit deviations in mm.

    References
    ----------
    .. [1] ISO 2768-1:1989, table 2.
    """
    _check_class(cls, LINEAR_CLASSES, "ISO 2768-1")
    t = BROKEN_EDGE[cls][range_index(BROKEN_EDGE_RANGES, nominal_mm, "radius", "ISO 2768-1")]
    return (-t, t)


def angular_tolerance(shorter_leg_mm, cls):
    """General limit deviations of an angle (ISO 2768-1, table 3).

    Parameters
    ----------
    shorter_leg_mm : float
        Length of the shorter leg of the angle, mm.
    cls : str
        Linear class "f", "m", "c" or "v".

    Returns
    -------
    lower, upper : float
        Limit deviations in radians (the table is in degrees and minutes).

    Examples
    --------
    >>> import math
    >>> round(math.degrees(angular_tolerance(30.0, "m")[1]), 6)
    0.5

    References
    ----------
    .. [1] ISO 2768-1:1989, table 3.
    """
    _check_class(cls, LINEAR_CLASSES, "ISO 2768-1")
    if shorter_leg_mm < 0:
        raise NoGeneralTolerance(f"leg length must not be negative, got {shorter_leg_mm}")
    deg, minutes = ANGULAR[cls][range_index(ANGULAR_RANGES, shorter_leg_mm, "leg length", "ISO 2768-1")]
    t = math.radians(deg + minutes / 60.0)
    return (-t, t)


def straightness_tolerance(length_mm, cls):
    """General straightness tolerance of a line (ISO 2768-2, table 1).

    Parameters
    ----------
    length_mm : float
        Length of the line, mm.
    cls : str
        Geometrical class "H", "K" or "L".

    Returns
    -------
    float
        Width of the tolerance zone, mm.

    Examples
    --------
    >>> straightness_tolerance(50.0, "K")
    0.2

    References
    ----------
    .. [1] ISO 2768-2:1989, table 1.
    """
    _check_class(cls, GEOMETRICAL_CLASSES, "ISO 2768-2")
    if length_mm < 0:
        raise NoGeneralTolerance(f"length must not be negative, got {length_mm}")
    return STRAIGHTNESS_FLATNESS[cls][range_index(STRAIGHTNESS_RANGES, length_mm, "length", "ISO 2768-2")]


def flatness_tolerance(length_mm, cls):
    """General flatness tolerance, by the longer side of the surface (ISO 2768-2, table 1)."""
    return straightness_tolerance(length_mm, cls)


def perpendicularity_tolerance(shorter_side_mm, cls):
    """General perpendicularity tolerance, by the shorter side (ISO 2768-2, table 2), mm."""
    _check_class(cls, GEOMETRICAL_CLASSES, "ISO 2768-2")
    if shorter_side_mm < 0:
        raise NoGeneralTolerance(f"length must not be negative, got {shorter_side_mm}")
    return PERPENDICULARITY[cls][range_index(PERPENDICULARITY_RANGES, shorter_side_mm, "length", "ISO 2768-2")]


def symmetry_tolerance(length_mm, cls):
    """General symmetry tolerance (ISO 2768-2, table 3), mm."""
    _check_class(cls, GEOMETRICAL_CLASSES, "ISO 2768-2")
    if length_mm < 0:
        raise NoGeneralTolerance(f"length must not be negative, got {length_mm}")
    return SYMMETRY[cls][range_index(PERPENDICULARITY_RANGES, length_mm, "length", "ISO 2768-2")]


def runout_tolerance(cls):
    """General circular run-out tolerance (ISO 2768-2, table 4), mm."""
    _check_class(cls, GEOMETRICAL_CLASSES, "ISO 2768-2")
    return CIRCULAR_RUNOUT[cls]


def circularity_tolerance(diameter_tolerance_mm, cls):
    """General circularity tolerance of a circle.

    ISO 2768-2 sets it equal to the numerical value of the diameter
    tolerance, but never larger than the circular radial run-out tolerance
    of the class.

    Parameters
    ----------
    diameter_tolerance_mm : float
        Width of the diameter tolerance, ``upper - lower`` in mm, from the
        spec or from the general linear tolerance.
    cls : str
        Geometrical class "H", "K" or "L".

    Returns
    -------
    float
        Width of the circularity tolerance zone, mm.

    Examples
    --------
    >>> circularity_tolerance(0.4, "K")  # diameter 25 under ISO 2768-mK: +-0.2
    0.2
    >>> circularity_tolerance(0.05, "K")
    0.05

    References
    ----------
    .. [1] ISO 2768-2:1989, clause on circularity, and table 4.
    """
    if not diameter_tolerance_mm > 0:
        raise ValueError(f"diameter tolerance must be positive, got {diameter_tolerance_mm}")
    return min(float(diameter_tolerance_mm), runout_tolerance(cls))
