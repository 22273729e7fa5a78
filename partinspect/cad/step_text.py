"""The geometric tolerances of a STEP file as its own text states them.

OCCT does not read a tolerance magnitude given as a compound entity (the
ISO 10303-21 external mapping of a complex instance, 11.2.5), which several
CAD systems write, e.g.::

    #90=(LENGTH_MEASURE_WITH_UNIT() MEASURE_REPRESENTATION_ITEM()
         MEASURE_WITH_UNIT(LENGTH_MEASURE(1.25),#4361) ...);

and it drops some tolerances altogether. This module scans the data section
for the tolerance entities themselves, so that `partinspect.cad.pmi` can
fill in and account for what OCCT missed. It is a scanner of the few
records needed, not a STEP parser.

References
----------
.. [1] ISO 10303-21:2016, Clear text encoding of the exchange structure.
.. [2] ISO 10303-47, Shape variation tolerances (the ``*_TOLERANCE``
       entities and their ``magnitude`` attribute).
"""

import re
from pathlib import Path

__all__ = ["INCH", "step_tolerance_values"]

INCH = 25.4  # mm


_RECORD = re.compile(r"#(\d+)\s*=\s*((?:[^;']|'(?:[^']|'')*')*);")
_TOLERANCE = re.compile(r"\b(\w+_TOLERANCE)\s*\(\s*'((?:[^']|'')*)'\s*,\s*'(?:[^']|'')*'\s*,\s*#(\d+)")
_SPECIFIC = re.compile(r"\b(\w+?_TOLERANCE)\s*\(\s*\)")
_MEASURE = re.compile(r"\b(LENGTH|POSITIVE_LENGTH|PLANE_ANGLE)_MEASURE\s*\(\s*([-+0-9.eE]+)\s*\)\s*,\s*#(\d+)")
_SI_PREFIX = {"MILLI": 1.0, "CENTI": 10.0, "DECI": 100.0, "MICRO": 1e-3, "KILO": 1e6}


def step_tolerance_values(path):
    """Geometric tolerances and their magnitudes as the file's text states them.

    OCCT does not read a tolerance magnitude given as a compound entity
    (ISO 10303-21 external mapping), which several CAD systems write; the
    magnitude is found here by following the tolerance's third attribute to
    its ``LENGTH_MEASURE`` and that measure's unit.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    list of (name, entity type, value)
        In the order of the entity numbers; ``value`` in mm (None when the
        magnitude or its unit cannot be read). The entity type is the
        specific one (``FLATNESS_TOLERANCE``), also for a compound entity
        (where it is the member without attributes).
    """
    text = Path(path).read_text(encoding="latin-1")
    data = text[text.find("DATA;"):]
    records = {int(m.group(1)): m.group(2) for m in _RECORD.finditer(data)}
    out = []
    for num in sorted(records):
        body = records[num]
        if "_TOLERANCE" not in body:
            continue
        m = _TOLERANCE.search(body)
        if m is None:
            continue
        etype, name, ref = m.group(1), m.group(2).replace("''", "'"), int(m.group(3))
        specific = _SPECIFIC.search(body)  # a compound's kind is its empty member
        if specific is not None:
            etype = specific.group(1)
        out.append((name, etype, _measure_mm(records, ref)))
    return out


def _measure_mm(records, ref):
    m = _MEASURE.search(records.get(ref, ""))
    if m is None:
        return None
    factor = _unit_mm(records, int(m.group(3)))
    return None if factor is None else float(m.group(2)) * factor


def _unit_mm(records, ref, depth=0):
    body = records.get(ref, "")
    if "CONVERSION_BASED_UNIT" in body:
        if re.search(r"'INCH'", body, re.I):
            return INCH
        m = re.search(r"CONVERSION_BASED_UNIT\s*\(\s*'[^']*'\s*,\s*#(\d+)", body)
        if m and depth < 3:
            return _measure_mm(records, int(m.group(1)))
        return None
    m = re.search(r"SI_UNIT\s*\(\s*(?:\.(\w+)\.|\$)\s*,\s*\.METRE\.", body)
    if m:
        return 1000.0 if m.group(1) is None else _SI_PREFIX.get(m.group(1))
    return None
