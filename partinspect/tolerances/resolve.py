"""Tie a tolerance spec to a CAD model: characteristics with nominal values and limits.

:func:`resolve_spec` checks the spec against the feature inventory (ids
exist, ``at:`` selectors pick exactly one edge, characteristics fit the
feature kind, distances and angles are defined) and turns it into
:class:`Characteristic` definitions. :func:`general_characteristics` adds
what the general tolerances (ISO 2768) define for everything the spec
leaves out; :func:`characteristics_for` gives both.

General tolerances are applied per characteristic, not per feature, as
ISO 2768 words it ("features without individual tolerance indications"):
a circle whose spec gives only a position still has its diameter under the
general class.

References
----------
.. [1] ISO 2768-1:1989, General tolerances -- Part 1: Tolerances for linear
       and angular dimensions without individual tolerance indications.
.. [2] ISO 2768-2:1989, General tolerances -- Part 2: Geometrical tolerances
       for features without individual tolerance indications.
.. [3] ISO 14253-1:2017, Decision rules for verifying conformity or
       nonconformity with specifications.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType

import numpy as np

from partinspect.cad.features import cylinder_sides, faces_of
from partinspect.errors import InputError
from partinspect.tolerances import iso2768
from partinspect.tolerances.geometry import feature_distance, line_angle, line_tilt, lines_parallel
from partinspect.tolerances.datum_shift import DatumRef, parse_datum
from partinspect.tolerances.material import MaterialCondition
from partinspect.tolerances.spec import APPLIES_TO, FEATURE_ID_RE, ToleranceSpec, format_loc, join_errors

__all__ = [
    "MAX_SELECTOR_DISTANCE",
    "TIE_DISTANCE",
    "Characteristic",
    "ResolvedSpec",
    "resolve_spec",
    "select_edge",
    "general_characteristics",
    "characteristics_for",
    "with_edge_breaks",
    "with_material_sizes",
]

# An at: point is meant to lie on the edge; 1 mm is far beyond CAD rounding
# yet well below the spacing of distinct edges on a machined part.
MAX_SELECTOR_DISTANCE = 1.0
# Two edges closer to the point than this apart are the same distance away
# as far as CAD coordinates can tell.
TIE_DISTANCE = 1e-6

# Diameter and radius toleranced on one feature would be the same size twice.
_SAME_AS = {"diameter": "size", "radius": "size"}

_ROUND = 12


def _round(x):
    return None if x is None else round(float(x), _ROUND)


@dataclass(frozen=True)
class Characteristic:
    """One toleranced quantity of the part, with its nominal value and limits.

    Attributes
    ----------
    id : str
        Unique name: ``"circle-3.diameter"``, ``"edge-near-top.straightness"``
        (the spec's name), ``"distance(circle-1,circle-3)"``,
        ``"angle(line-1,line-2)"``.
    type : str
        "diameter", "radius", "position", "straightness", "circularity",
        "profile", "distance", "angle" or "parallelism" (an ``angles``
        entry between parallel lines: the first's tilt towards
        ``towards``, or in their common plane,
        :func:`~partinspect.tolerances.geometry.line_tilt`).
    features : tuple of str
        CAD feature ids involved (one, or two for distances and angles).
    nominal : float
        Nominal value from the CAD model (or the spec's ``nominal``): mm,
        radians for angles. Zero for geometrical tolerances (the ideal form
        or location deviates by nothing).
    lower_limit, upper_limit : float or None
        Specification limits, same unit as ``nominal``. Geometrical
        tolerances are one-sided: lower_limit None, upper_limit the zone
        width (or zone diameter for position).
    source : str
        "spec", or e.g. "ISO 2768-mK (general tolerance)".
    rule : str
        Where the limits come from, for the report: "part.tol.yaml line 7"
        or "ISO 2768-1 table 1, class m, over 6 up to 30 mm".
    unit : str
        "mm" or "rad".
    edge_break : tuple of 2 float or None
        Sizes and circularity of circles only: the rim's edge break (min,
        max), mm, from the spec (:mod:`partinspect.tolerances.edge_break`);
        None for a sharp rim.
    band_place : tuple of 2 float or None
        Sizes of a broken rim only: where its apparent edge lies across the
        break's band (0 the wall, 1 the face) and that place's standard
        uncertainty, predicted from the images once the pose is known
        (:mod:`partinspect.vision.band_place`); None: uniform across the band.
    material : MaterialCondition or None
        Position only: the MMC or LMC modifier and, once
        :func:`with_material_sizes` resolved it, the size characteristic
        its bonus comes from (:mod:`partinspect.tolerances.material`);
        None: regardless of feature size.
    towards : tuple of 3 float or None
        Parallelism only: the unit direction (part frame) the tilt is
        taken towards; None: the plane the two lines span.
    datums : tuple of DatumRef
        Position only, where the spec gives its datum reference frame: the
        datums in order of precedence, a datum feature of size at MMB or
        LMB allowing the datum shift (:mod:`.datum_shift`); empty otherwise.
    """

    id: str
    type: str
    features: tuple[str, ...]
    nominal: float
    lower_limit: float | None
    upper_limit: float | None
    source: str
    rule: str = ""
    unit: str = "mm"
    edge_break: tuple[float, float] | None = None
    material: MaterialCondition | None = None
    towards: tuple[float, float, float] | None = None
    datums: tuple = ()
    band_place: tuple[float, float] | None = None

    @property
    def feature(self):
        """The feature id, or the ids joined by "," for two-feature characteristics."""
        return ",".join(self.features)

    def to_dict(self):
        """The report.json entry (angles in degrees there, DESIGN.md conventions)."""
        conv = math.degrees if self.unit == "rad" else float
        return {
            "id": self.id,
            "feature": self.feature,
            "features": list(self.features),
            "type": self.type,
            "nominal": _round(conv(self.nominal)),
            "lower_limit": None if self.lower_limit is None else _round(conv(self.lower_limit)),
            "upper_limit": None if self.upper_limit is None else _round(conv(self.upper_limit)),
            "unit": "deg" if self.unit == "rad" else self.unit,
            "source": self.source,
            "rule": self.rule,
            **({"edge_break": {"min": self.edge_break[0], "max": self.edge_break[1]}} if self.edge_break else {}),
            **({"material": self.material.to_dict()} if self.material is not None else {}),
            **({"towards": [round(x, 12) for x in self.towards]} if self.towards is not None else {}),
            **({"datum_reference": [d.to_dict() for d in self.datums]} if self.datums else {}),
        }


@dataclass(frozen=True)
class ResolvedSpec:
    """A spec checked against a CAD model.

    Attributes
    ----------
    spec : ToleranceSpec
    features : mapping of str to str
        Every key of ``spec.features`` (id or name) to its CAD feature id.
    datums : tuple of str
        CAD feature ids the alignment uses: the spec's datums, or every
        feature when the spec names none.
    characteristics : tuple of Characteristic
        What the spec tolerances, in file order.
    path : str or None
        The spec file.
    not_evaluated : tuple
        Tolerances the part's PMI holds that no edge characteristic checks
        (``partinspect.tolerances.from_pmi.NotEvaluated``), for the report.
    datum_source : str or None
        Where the named datums come from (``"part.tol.yaml line 4"``,
        ``"part.stp PMI datums A|B|C"``); None when the alignment uses
        every feature.
    datum_frame : tuple of (str, tuple of str)
        The PMI's datum letters with their features, in letter order, when
        the datums come from the PMI; else empty.
    """

    spec: ToleranceSpec
    features: MappingProxyType
    datums: tuple[str, ...]
    characteristics: tuple[Characteristic, ...]
    path: str | None = None
    not_evaluated: tuple = ()
    datum_source: str | None = None
    datum_frame: tuple = ()

    @property
    def alignment_datums(self):
        """The CAD ids the alignment is fitted on, or None for every matched feature."""
        return None if self.datum_source is None else self.datums

    @property
    def general(self):
        return self.spec.general

    @property
    def decision_rule(self):
        return self.spec.decision_rule


def _fmt_point(p):
    return "[" + ", ".join(f"{float(x):g}" for x in p) + "]"


def select_edge(inventory, point, max_distance=MAX_SELECTOR_DISTANCE, tie=TIE_DISTANCE):
    """The CAD edge an ``at: [x, y, z]`` selector means.

    Parameters
    ----------
    inventory : partinspect.cad.features.Inventory
    point : array_like, shape (3,)
        Part frame, mm.
    max_distance : float
        The edge must pass within this distance of the point, mm.
    tie : float
        Two edges whose distances differ by no more than this are equally
        near, mm.

    Returns
    -------
    feature : partinspect.cad.features.Feature

    Raises
    ------
    ValueError
        No edge within ``max_distance``, or two edges equally near.
    """
    # The distance to an edge (segment, full circle, arc span) is defined
    # once, in the CAD module, next to the arc angle convention it relies on.
    from partinspect.cad.features import nearest_feature

    try:
        feature, distance = nearest_feature(inventory, point, tie_tolerance=tie)
    except ValueError as e:
        # One mistake is one "; "-separated item of the error line.
        raise ValueError(str(e).replace("; ", ": ")) from None
    if distance > max_distance:
        raise ValueError(
            f"no edge within {max_distance:g} mm of {_fmt_point(point)} (nearest: {feature.id} at {distance:.3g} mm)"
        )
    return feature


def _kinds_summary(features):
    counts = {}
    for f in features:
        counts[f.kind] = counts.get(f.kind, 0) + 1
    return ", ".join(f"{n} {k}s" for k, n in sorted(counts.items())) or "no edges"


def _rule_of(spec, path, loc):
    line = spec.line_of(loc)
    name = Path(path).name if path else "spec"
    return f"{name} line {line}" if line else name


def resolve_spec(spec, inventory, path=None):
    """Check a spec against the CAD feature inventory and define its characteristics.

    Parameters
    ----------
    spec : ToleranceSpec
    inventory : object with a ``features`` sequence
        The CAD feature inventory (``partinspect.cad.features``): records
        with ``id``, ``kind`` and the geometry of their kind.
    path : str or os.PathLike, optional
        The spec file for error messages; default ``spec.path``.

    Returns
    -------
    ResolvedSpec

    Raises
    ------
    partinspect.errors.InputError
        Listing every problem, each with its line in the spec: unknown
        feature ids (with a "did you mean"), ``at:`` points with no edge
        within 1 mm or with two equally near edges, characteristics that
        do not fit the kind of the selected edge, a characteristic given
        twice for one edge, unknown datums, distances between non-parallel
        lines, angles between parallel lines or non-lines, and a given
        nominal that disagrees with the CAD model by more than its
        tolerance.
    """
    path = spec.path if path is None else str(path)
    check = _Check(spec, inventory, path)
    names = _feature_targets(check)
    chars = _feature_characteristics(check, names)
    datums = _datums(check, names)
    chars += _pair_characteristics(check, names)
    if check.errors:
        raise InputError(path, join_errors(check.errors))
    source = None if spec.datums is None else check.rule(("datums",))
    return ResolvedSpec(spec, MappingProxyType(dict(names)), datums, tuple(chars), path, datum_source=source)


class _Check:
    """What the steps of :func:`resolve_spec` share: the spec, the inventory's features and the problems found."""

    def __init__(self, spec, inventory, path):
        self.spec, self.inventory, self.path = spec, inventory, path
        self.feats = list(inventory.features)
        self.by_id = {f.id: f for f in self.feats}
        self.errors = []

    def err(self, loc, msg):
        """Record a problem at a spec location, with its line."""
        self.errors.append((self.spec.line_of(loc), f"{format_loc(loc)}: {msg}"))

    def unknown_id(self, ref):
        """The message for a feature id the model lacks, with a "did you mean"."""
        best = difflib.get_close_matches(ref, list(self.by_id), n=1, cutoff=0.6)
        hint = f"did you mean {best[0]}?" if best else f"the model has {_kinds_summary(self.feats)}"
        return f"no feature {ref} in the CAD model ({hint})"

    def ref_id(self, ref, loc, names):
        """The CAD id a reference (feature id or spec name) means, or None (the problem recorded)."""
        if ref in names:
            return names[ref]
        if FEATURE_ID_RE.match(ref):
            if ref in self.by_id:
                return ref
            self.err(loc, self.unknown_id(ref))
        elif ref not in self.spec.features:
            self.err(loc, f"unknown feature {ref!r}")
        return None  # a named feature whose selector failed is reported already

    def rule(self, loc):
        return _rule_of(self.spec, self.path, loc)


def _feature_targets(check):
    """Each ``features:`` key (an id, or a name with ``at:``) to its CAD feature id; bad ones left out."""
    spec, by_id, err = check.spec, check.by_id, check.err
    names = {}
    for key, fs in spec.features.items():
        loc = ("features", key)
        target = None
        if FEATURE_ID_RE.match(key):
            if key not in by_id:
                err(loc, check.unknown_id(key))
                continue
            target = key
        if fs.at is not None:
            try:
                picked = select_edge(check.inventory, fs.at).id
            except ValueError as e:
                err(loc + ("at",), str(e))
                continue
            if target is not None and picked != target:
                err(loc + ("at",), f"the edge nearest to {_fmt_point(fs.at)} is {picked}, not {key}")
                continue
            target = picked
        if target is None:
            # parse_spec refuses a name without at:; a spec built in code may still have one.
            err(loc, f"{key!r} is not a CAD feature id and has no at: [x, y, z]")
            continue
        names[key] = target
    return names


def _feature_characteristics(check, names):
    """The characteristics of the ``features:`` section, in file order; each edge's size or form toleranced once."""
    spec, by_id, err = check.spec, check.by_id, check.err
    chars = []
    owner = {}
    for key, fs in spec.features.items():
        if key not in names:
            continue
        target = by_id[names[key]]
        for ctype, tol in fs.characteristics().items():
            loc = ("features", key, ctype)
            if target.kind not in APPLIES_TO[ctype]:
                err(loc, f"{ctype} does not apply to {target.id}, a {target.kind}")
                continue
            slot = (target.id, _SAME_AS.get(ctype, ctype))
            if slot in owner:
                err(loc, f"{target.id} already has its {slot[1]} toleranced in {format_loc(owner[slot])}")
                continue
            owner[slot] = loc
            c = _feature_characteristic(f"{key}.{ctype}", ctype, target, tol, check.rule(loc))
            if getattr(tol, "datums", None):
                c = replace(c, datums=_datum_refs(check, names, tol.datums))
            chars.append(c)
    return chars


def _datum_refs(check, names, datums):
    """A position's ``datums`` as :class:`DatumRef`, each letter's features from the spec's ``datum_features``."""
    out = []
    for text in datums:
        letter, boundary = parse_datum(text)
        refs = check.spec.datum_features.get(letter, ())
        ids = [check.ref_id(ref, ("datum_features", letter, i), names) for i, ref in enumerate(refs)]
        out.append(DatumRef(letter, boundary, tuple(fid for fid in ids if fid is not None)))
    return tuple(out)


def _datums(check, names):
    """CAD ids of the spec's datums, or of every feature when it names none."""
    if check.spec.datums is None:
        return tuple(f.id for f in check.feats)
    return tuple(d for i, ref in enumerate(check.spec.datums) if (d := check.ref_id(ref, ("datums", i), names)) is not None)


def _pair_characteristics(check, names):
    """The characteristics of the ``distances:`` and ``angles:`` sections, in file order."""
    spec, by_id, err = check.spec, check.by_id, check.err
    chars = []
    for section, items in (("distances", spec.distances), ("angles", spec.angles)):
        for i, item in enumerate(items):
            loc = (section, i)
            ids = [check.ref_id(ref, loc + ("between", j), names) for j, ref in enumerate(item.between)]
            if None in ids:
                continue
            fa, fb = by_id[ids[0]], by_id[ids[1]]
            cid = f"{section[:-1]}({item.between[0]},{item.between[1]})"
            if fa.id == fb.id:
                err(loc + ("between",), f"{item.between[0]} and {item.between[1]} are the same edge {fa.id}")
                continue
            if section == "distances":
                c = _distance_characteristic(cid, fa, fb, item, check.rule(loc), lambda m: err(loc, m))
            else:
                c = _angle_characteristic(cid, fa, fb, item, check.rule(loc), lambda m, j=None: err(loc if j is None else loc + ("between", j), m))
            if c is not None:
                chars.append(c)
    return chars


def _feature_characteristic(cid, ctype, feature, tol, rule):
    if ctype in ("diameter", "radius"):
        nominal = 2.0 * float(feature.radius) if ctype == "diameter" else float(feature.radius)
        return Characteristic(cid, ctype, (feature.id,), nominal, nominal + tol.lower, nominal + tol.upper, "spec", rule)
    material = getattr(tol, "material", None)
    return Characteristic(cid, ctype, (feature.id,), 0.0, None, tol.tolerance, "spec", rule,
                          material=None if material is None else MaterialCondition(material))


def _check_nominal(given, cad, width, unit, report):
    # A nominal far from the model's means the wrong features were named (or
    # a stale drawing); within the tolerance width it is a deliberate choice,
    # e.g. a model drawn at the middle of an asymmetric tolerance.
    if abs(given - cad) > width + 1e-9:
        report(f"nominal {given:g} {unit} disagrees with the CAD model ({cad:.6g} {unit}) by more than the tolerance")
        return False
    return True


def _distance_characteristic(cid, fa, fb, item, rule, report):
    try:
        cad = feature_distance(fa, fb)
    except ValueError as e:
        report(f"no distance between {fa.id} and {fb.id}: {e}")
        return None
    nominal = cad
    if item.nominal is not None:
        if not _check_nominal(item.nominal, cad, item.upper - item.lower, "mm", report):
            return None
        nominal = item.nominal
    return Characteristic(cid, "distance", (fa.id, fb.id), nominal, nominal + item.lower, nominal + item.upper, "spec", rule)


def _angle_characteristic(cid, fa, fb, item, rule, report):
    bad = False
    for j, f in enumerate((fa, fb)):
        if f.kind != "line":
            report(f"angles are between lines, {f.id} is a {f.kind}", j)
            bad = True
    if bad:
        return None
    if lines_parallel(fa.start, fa.end, fb.start, fb.end):
        return _parallelism_characteristic(cid, fa, fb, item, rule, report)
    if item.towards is not None:
        report("towards is for an angle between parallel lines (a parallelism); these meet")
        return None
    try:
        cad = line_angle(fa.start, fa.end, fb.start, fb.end)
    except ValueError as e:
        report(f"no angle between {fa.id} and {fb.id}: {e}")
        return None
    nominal = cad
    if item.nominal is not None:
        cad_deg = math.degrees(cad)
        if abs(item.nominal - cad_deg) > item.upper - item.lower + 1e-9:
            report(
                f"nominal {item.nominal:g} degrees disagrees with the CAD model ({cad_deg:.6g} degrees, the angle at "
                f"the lines' meeting point towards their far ends) by more than the tolerance"
            )
            return None
        nominal = math.radians(item.nominal)
    lower, upper = math.radians(item.lower), math.radians(item.upper)
    return Characteristic(cid, "angle", (fa.id, fb.id), nominal, nominal + lower, nominal + upper, "spec", rule, unit="rad")


def _parallelism_characteristic(cid, fa, fb, item, rule, report):
    # Two parallel lines have no vertex: their angle is the tilt of the first
    # in the plane the two span (geometry.line_tilt), nominal zero.
    towards = None if item.towards is None else tuple(float(x) for x in np.asarray(item.towards) / np.linalg.norm(item.towards))
    try:
        line_tilt(fa.start, fa.end, fb.start, fb.end, towards)
    except ValueError as e:
        report(f"no angle between {fa.id} and {fb.id}: {e}")
        return None
    if item.nominal is not None and abs(item.nominal) > item.upper - item.lower + 1e-9:
        report(f"nominal {item.nominal:g} degrees disagrees with the CAD model: the lines are parallel (0 degrees)")
        return None
    nominal = math.radians(item.nominal or 0.0)
    lower, upper = math.radians(item.lower), math.radians(item.upper)
    return Characteristic(cid, "parallelism", (fa.id, fb.id), nominal, nominal + lower, nominal + upper, "spec", rule,
                          unit="rad", towards=towards)


GENERAL_GAP = "no general tolerance"
"""The ``type`` of a characteristic no tolerance covers: left untoleranced where ISO 2768 sets none."""


def general_characteristics(inventory, spec, path=None, *, gaps=None):
    """The characteristics the general tolerances define for what the spec leaves out.

    For each CAD feature, every characteristic below that the spec does not
    tolerance itself:

    - circle: diameter 2r, ISO 2768-1 table 1 (linear class);
      circularity, ISO 2768-2: the diameter tolerance (the spec's when it
      gives one, else the general one), at most the circular run-out
      tolerance of table 4 (geometrical class);
    - arc: radius r, ISO 2768-1 table 1 -- ISO 2768-1 counts radii among
      linear dimensions; table 2 (broken edges) is not used because the
      inventory cannot tell an edge break from a functional radius, and
      table 1 is the stricter of the two;
    - line: straightness over its length, ISO 2768-2 table 1.

    Form tolerances need a geometrical class: with "ISO 2768-m" alone only
    sizes are generated.

    Parameters
    ----------
    inventory : object with a ``features`` sequence
    spec : ToleranceSpec or ResolvedSpec
        A ToleranceSpec is resolved against the inventory first.
    path : str or os.PathLike, optional
        The spec file for error messages.
    gaps : list, optional
        Where ISO 2768 defines no general tolerance for a characteristic
        left untoleranced (a diameter below 0.5 mm, a class-v size up to
        3 mm, a line over 3000 mm, ...), its ``(id, reason)`` is appended
        here and the rest is evaluated: the drawing leaves that
        characteristic without a tolerance (ISO 2768-1 asks for one beside
        the dimension), not the whole part. By default that is an error
        instead.

    Returns
    -------
    list of Characteristic
        In inventory order, each with ``source`` like
        "ISO 2768-mK (general tolerance)" and the table row in ``rule``.

    Raises
    ------
    partinspect.errors.InputError
        Without ``gaps``, when ISO 2768 defines no general tolerance for a
        characteristic left untoleranced: the spec must give one.
    """
    resolved = spec if isinstance(spec, ResolvedSpec) else resolve_spec(spec, inventory, path)
    path = resolved.path if path is None else str(path)
    general = resolved.spec.general_class
    lin, geo = general.linear, general.geometrical
    source = f"{general.designation} (general tolerance)"

    given = {}
    for c in resolved.characteristics:
        if len(c.features) == 1:
            given[(c.features[0], _SAME_AS.get(c.type, c.type))] = c

    out, problems, problems_by_item = [], [], []

    def size(feature, ctype, nominal):
        try:
            lo, up = iso2768.linear_tolerance(nominal, lin)
        except iso2768.NoGeneralTolerance as e:
            problems.append(f"{feature.id} ({ctype} {nominal:.4g} mm): {e}")
            problems_by_item.append((f"{feature.id}.{ctype}", f"{ctype} {nominal:.4g} mm: {e}"))
            return None
        i = iso2768.range_index(iso2768.LINEAR_RANGES, nominal)
        rule = f"ISO 2768-1 table 1, class {lin}, {iso2768.range_label(iso2768.LINEAR_RANGES, i)}"
        c = Characteristic(f"{feature.id}.{ctype}", ctype, (feature.id,), nominal, nominal + lo, nominal + up, source, rule)
        out.append(c)
        return c

    for f in inventory.features:
        if f.kind in ("circle", "arc"):
            ctype = "diameter" if f.kind == "circle" else "radius"
            nominal = 2.0 * float(f.radius) if ctype == "diameter" else float(f.radius)
            size_c = given.get((f.id, "size")) or size(f, ctype, nominal)
            if f.kind == "circle" and geo is not None and (f.id, "circularity") not in given and size_c is not None:
                width = size_c.upper_limit - size_c.lower_limit
                if size_c.type == "radius":
                    width *= 2.0  # ISO 2768-2 speaks of the diameter tolerance
                if width > 0:
                    t = iso2768.circularity_tolerance(width, geo)
                    rule = (
                        f"ISO 2768-2 class {geo}: circularity = diameter tolerance {width:.4g} mm, "
                        f"at most the circular run-out tolerance {iso2768.runout_tolerance(geo):g} mm (table 4)"
                    )
                    out.append(Characteristic(f"{f.id}.circularity", "circularity", (f.id,), 0.0, None, t, source, rule))
        elif f.kind == "line" and geo is not None and (f.id, "straightness") not in given:
            length = float(np.linalg.norm(np.asarray(f.end, float) - np.asarray(f.start, float)))
            try:
                t = iso2768.straightness_tolerance(length, geo)
            except iso2768.NoGeneralTolerance as e:
                problems.append(f"{f.id} (straightness over {length:.4g} mm): {e}")
                problems_by_item.append((f"{f.id}.straightness", f"straightness over {length:.4g} mm: {e}"))
                continue
            i = iso2768.range_index(iso2768.STRAIGHTNESS_RANGES, length)
            rule = f"ISO 2768-2 table 1, class {geo}, {iso2768.range_label(iso2768.STRAIGHTNESS_RANGES, i)}"
            out.append(Characteristic(f"{f.id}.straightness", "straightness", (f.id,), 0.0, None, t, source, rule))
    if problems and gaps is None:
        raise InputError(path, "; ".join(problems))
    if problems:
        gaps.extend(problems_by_item)
    return out


def characteristics_for(spec, inventory, path=None):
    """Every characteristic to evaluate on a part: the spec's, then the general ones.

    Parameters
    ----------
    spec : ToleranceSpec
    inventory : object with a ``features`` list
        The CAD feature inventory (``partinspect.cad.features``).
    path : str or os.PathLike, optional
        The spec file, for error messages; default the file the spec was
        read from.

    Returns
    -------
    list of Characteristic
    """
    resolved = resolve_spec(spec, inventory, path)
    chars = with_edge_breaks(list(resolved.characteristics) + general_characteristics(inventory, resolved), resolved)
    return with_material_sizes(chars, inventory, resolved.path)


def with_edge_breaks(characteristics, resolved):
    """The characteristics with each size and circularity of a rim given its edge break: the feature's own, else the spec's.

    Parameters
    ----------
    characteristics : list of Characteristic
    resolved : ResolvedSpec

    Returns
    -------
    list of Characteristic
    """
    spec = resolved.spec
    own = {resolved.features[key]: fs.edge_break for key, fs in spec.features.items()
           if fs.edge_break is not None and key in resolved.features}
    out = []
    for c in characteristics:
        eb = own.get(c.features[0], spec.edge_break) if c.type in ("diameter", "radius", "circularity") else None
        out.append(replace(c, edge_break=(float(eb.min), float(eb.max))) if eb is not None else c)
    return out


def with_material_sizes(characteristics, inventory, path=None):
    """The characteristics with each MMC/LMC position tied to its feature's size, and each datum of size to its.

    A position's bonus comes from the measured size of the same edge
    (:mod:`partinspect.tolerances.material`): its diameter or radius
    characteristic (the spec's, the PMI's or the general one, edge break
    included) gives the size at MMC or LMC, and the cylinder the edge
    bounds tells a hole from a boss. A position's datum that is a feature
    of size (the rims of one hole or boss) gets its rims' size
    characteristics the same way (:mod:`.datum_shift`).

    Parameters
    ----------
    characteristics : list of Characteristic
        With the sizes of every circle and arc (as
        :func:`general_characteristics` completes them).
    inventory : partinspect.cad.features.Inventory
    path : str or os.PathLike, optional
        The spec file, for error messages.

    Returns
    -------
    list of Characteristic

    Raises
    ------
    partinspect.errors.InputError
        A modified position on an edge that bounds no single cylinder side
        (no hole or boss to take a size from), or whose size is not
        toleranced.
    """
    sizes = {c.features[0]: c for c in characteristics if c.type in ("diameter", "radius")}
    out, problems = [], []
    for c in characteristics:
        if c.datums:
            c = replace(c, datums=tuple(_datum_size(d, sizes, inventory) for d in c.datums))
        if c.material is None or c.material.size is not None:
            out.append(c)
            continue
        fid = c.features[0]
        sides = cylinder_sides(faces_of(inventory, [fid]))
        if len(sides) != 1:
            problems.append(f"{c.id} at {c.material.modifier}: {fid} bounds "
                            f"{'no cylinder' if not sides else 'both a hole and a boss'}, so there is no size to take "
                            "the bonus from")
            continue
        if fid not in sizes:
            problems.append(f"{c.id} at {c.material.modifier}: {fid} has no size tolerance to take the bonus from")
            continue
        internal = not sides.pop()
        out.append(replace(c, material=replace(c.material, internal=internal, size=sizes[fid])))
    if problems:
        raise InputError(path, "; ".join(problems))
    return out


def _datum_size(d, sizes, inventory):
    """A datum with its size characteristics and side, where its features are the rims of one hole or one boss."""
    if d.sizes or not d.features:
        return d
    rims = [fid for fid in d.features if fid in inventory and inventory[fid].kind != "line" and fid in sizes]
    sides = cylinder_sides(faces_of(inventory, rims))
    if not rims or len(sides) != 1 or None in sides:
        return d  # a plane, or no single feature of size: no shift from it
    return replace(d, sizes=tuple(sizes[fid] for fid in rims), internal=not sides.pop())
