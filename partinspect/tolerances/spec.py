"""The tolerance spec file (part.tol.yaml): reading, validating, writing.

The format is the one of DESIGN.md, "Tolerance spec" (``units``,
``general``, ``decision_rule``, ``datums``, ``features``, ``distances``,
``angles`` in degrees). Every key is optional; an empty spec means ISO
2768-mK for everything. A mistake is never silently dropped: unknown keys,
wrong types, negative tolerances, limits in the wrong order, a
characteristic on a feature kind it does not apply to, and duplicate keys
(which PyYAML would resolve to the last one) are reported together, each
with its line number, as one :class:`partinspect.errors.InputError`.

Characteristics a feature may carry (mm):

============  ==================  ============================================
name          applies to          meaning
============  ==================  ============================================
diameter      circle, arc         size, ``{upper, lower}`` limit deviations
radius        circle, arc         size, ``{upper, lower}`` limit deviations
position      circle, arc         ``{tolerance}``: diameter of the centre's
                                  true-position zone; ``material: MMC`` or
                                  ``LMC`` adds the bonus from the measured
                                  size (:mod:`.material`; a zero tolerance
                                  is allowed then); ``datums: [A, B(M)]``
                                  the frame, a datum at MMB/LMB shifting
                                  the pattern (:mod:`.datum_shift`)
straightness  line                ``{tolerance}``: width of the zone
circularity   circle              ``{tolerance}``: radial width of the zone
profile       line, circle, arc   ``{tolerance}``: width of the line-profile
                                  zone about the nominal edge
============  ==================  ============================================

References
----------
.. [1] ISO 14253-1:2017, Geometrical product specifications (GPS) --
       Inspection by measurement of workpieces and measuring equipment --
       Part 1: Decision rules for verifying conformity or nonconformity with
       specifications (the ``iso14253`` decision rule).
.. [2] ISO 2768-1:1989 and ISO 2768-2:1989, general tolerances (the
       ``general`` class).
.. [3] ISO 1101:2017, Geometrical tolerancing (the meaning of position,
       straightness, circularity and line profile).
"""

from __future__ import annotations

import difflib
import math
import re
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, PrivateAttr, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError

from partinspect.errors import InputError
from partinspect.tolerances.iso2768 import GeneralClass, parse_general

__all__ = [
    "FEATURE_ID_RE",
    "APPLIES_TO",
    "Limits",
    "Zone",
    "PositionZone",
    "FeatureSpec",
    "DistanceSpec",
    "AngleSpec",
    "ToleranceSpec",
    "parse_spec",
    "load_spec",
    "default_spec",
    "spec_to_dict",
    "dump_spec",
]

FEATURE_ID_RE = re.compile(r"^(line|circle|arc)-([0-9]+)$")

# Which characteristic a feature kind can carry; see the module docstring.
APPLIES_TO = {
    "diameter": ("circle", "arc"),
    "radius": ("circle", "arc"),
    "position": ("circle", "arc"),
    "straightness": ("line",),
    "circularity": ("circle",),
    "profile": ("line", "circle", "arc"),
}

_MAX_SHOWN = 40


def _show(value):
    """A short, YAML-flavoured rendering of a bad value for an error line."""
    if value is None:
        return "nothing (null)"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, (list, tuple)):
        return "a list"
    text = repr(value) if isinstance(value, str) else str(value)
    return text if len(text) <= _MAX_SHOWN else text[: _MAX_SHOWN - 3] + "..."


def _number(value):
    # YAML 1.1 reads "1e-3" (no dot) as a string and "yes" as a boolean: take
    # the first as the number it plainly is, refuse the second.
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise PydanticCustomError("number", "expected a number, got {got}", {"got": _show(value)})
    try:
        x = float(value)
    except (ValueError, OverflowError):
        raise PydanticCustomError("number", "expected a number, got {got}", {"got": _show(value)}) from None
    if not math.isfinite(x):
        raise PydanticCustomError("number", "expected a finite number, got {got}", {"got": _show(value)})
    return x


Number = Annotated[float, BeforeValidator(_number)]


def _check_order(model):
    if model.lower > model.upper:
        raise PydanticCustomError(
            "limits_order", "lower {lower} is above upper {upper}", {"lower": model.lower, "upper": model.upper}
        )
    return model


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Limits(_Model):
    """Limit deviations of a size, mm: the size may lie in [nominal + lower, nominal + upper]."""

    upper: Number
    lower: Number

    @model_validator(mode="after")
    def _ordered(self):
        return _check_order(self)


class Zone(_Model):
    """A geometrical tolerance: width (or diameter, for position) of the tolerance zone, mm."""

    tolerance: Number

    @field_validator("tolerance")
    @classmethod
    def _positive(cls, v):
        if not v > 0:
            raise PydanticCustomError("positive", "expected a positive number, got {got}", {"got": _show(v)})
        return v


class PositionZone(Zone):
    """A position tolerance: the zone's diameter, mm, and an optional material modifier.

    ``material`` MMC or LMC (ISO 2692 (M), (L)) gives the zone the bonus
    from the measured size's departure from that condition
    (:mod:`partinspect.tolerances.material`); with it the tolerance may be
    zero (all of the zone is then the bonus). ``datums``, the datum
    reference frame as the drawing writes it (``[A, B(M), C(M)]``): a datum
    feature of size at MMB or LMB (its features under the spec's
    ``datum_features``) lets the features toleranced with the same frame
    shift together (:mod:`partinspect.tolerances.datum_shift`).
    """

    material: Literal["MMC", "LMC"] | None = None
    datums: tuple[str, ...] | None = None

    @field_validator("datums")
    @classmethod
    def _datum_letters(cls, v):
        from partinspect.tolerances.datum_shift import parse_datum

        letters = []
        for text in v or ():
            try:
                letters.append(parse_datum(text)[0])
            except ValueError as e:
                raise PydanticCustomError("datum", str(e)) from None
        twice = sorted({x for x in letters if letters.count(x) > 1})
        if twice:
            raise PydanticCustomError("datum", "datum {got} named twice", {"got": ", ".join(twice)})
        return v

    @field_validator("tolerance")
    @classmethod
    def _positive(cls, v):
        if not v >= 0:  # zero is for the model check: allowed with a material modifier
            raise PydanticCustomError("positive", "expected a positive number, got {got}", {"got": _show(v)})
        return v

    @model_validator(mode="after")
    def _zero_needs_material(self):
        if self.tolerance == 0 and self.material is None:
            raise PydanticCustomError("zero_position", "tolerance {got} needs material: MMC or LMC (all of the zone is "
                                      "then the bonus)", {"got": 0})
        return self


class EdgeBreak(_Model):
    """An edge state (ISO 13715): material removed from the ideal sharp edge, mm along each face.

    A plain number in the file is ``max`` with ``min`` 0 ("-0.1": up to
    0.1 mm); ``{min: 0.1, max: 0.3}`` a range.
    """

    max: Number
    min: Number = 0.0

    @model_validator(mode="after")
    def _range(self):
        if not (0 <= self.min <= self.max and self.max > 0):
            raise PydanticCustomError("edge_break", "expected 0 <= min <= max and max > 0 mm, got min {lo}, max {hi}",
                                      {"lo": _show(self.min), "hi": _show(self.max)})
        return self


def _edge_break(value):
    return {"max": value} if isinstance(value, (int, float)) and not isinstance(value, bool) else value


EdgeBreakField = Annotated[EdgeBreak | None, BeforeValidator(_edge_break)]


def _point(value):
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise PydanticCustomError("point", "expected a point [x, y, z] in mm, got {got}", {"got": _show(value)})
    return value


def _direction(value):
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise PydanticCustomError("direction", "expected a direction [x, y, z], got {got}", {"got": _show(value)})
    if all(isinstance(x, (int, float)) and not isinstance(x, bool) and x == 0 for x in value):
        raise PydanticCustomError("direction", "expected a direction [x, y, z], got the zero vector")
    return value


def _pair(value):
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise PydanticCustomError("pair", "expected two features [a, b], got {got}", {"got": _show(value)})
    return value


def _none_is_empty(empty):
    # "features:" with nothing under it is YAML null; it plainly means none.
    return BeforeValidator(lambda v: empty if v is None else v)


class FeatureSpec(_Model):
    """The characteristics toleranced on one feature.

    Attributes
    ----------
    at : tuple of 3 float or None
        For a named feature: a point (part frame, mm) on the wanted CAD edge.
    diameter, radius : Limits or None
        Size limit deviations, mm.
    position : PositionZone or None
        Position tolerance, mm, with its material modifier.
    straightness, circularity, profile : Zone or None
        Geometrical tolerances, mm.
    edge_break : EdgeBreak or None
        This edge's break, overriding the spec's general one.
    """

    at: Annotated[tuple[Number, Number, Number], BeforeValidator(_point)] | None = None
    diameter: Limits | None = None
    radius: Limits | None = None
    position: PositionZone | None = None
    straightness: Zone | None = None
    circularity: Zone | None = None
    profile: Zone | None = None
    edge_break: EdgeBreakField = None

    def characteristics(self):
        """``{name: Limits or Zone}`` of the characteristics given, in the documented order."""
        return {name: getattr(self, name) for name in APPLIES_TO if getattr(self, name) is not None}


class DistanceSpec(_Model):
    """A toleranced distance between two features, mm.

    Attributes
    ----------
    between : tuple of 2 str
        Feature ids or names.
    upper, lower : float
        Limit deviations from the nominal, mm.
    nominal : float or None
        Nominal distance, mm; None takes it from the CAD model.
    """

    between: Annotated[tuple[str, str], BeforeValidator(_pair)]
    upper: Number
    lower: Number
    nominal: Number | None = None

    @field_validator("nominal")
    @classmethod
    def _non_negative(cls, v):
        if v is not None and v < 0:
            raise PydanticCustomError("non_negative", "expected a distance >= 0, got {got}", {"got": _show(v)})
        return v

    @model_validator(mode="after")
    def _ordered(self):
        return _check_order(self)


class AngleSpec(_Model):
    """A toleranced angle between two lines, in degrees (as drawings give it).

    Attributes
    ----------
    between : tuple of 2 str
        Line ids or names.
    upper, lower : float
        Limit deviations from the nominal, degrees.
    nominal : float or None
        Nominal angle in degrees, in (0, 180); None takes it from the CAD
        model (see :func:`partinspect.tolerances.geometry.line_angle` for
        which of the two supplementary angles that is).

    towards : tuple of 3 float or None
        Between parallel lines only: the direction (part frame, e.g. a
        datum plane's normal) the tilt is taken towards.

    Between two parallel lines the angle is the first line's tilt towards
    ``towards``, by default in the plane the two span, nominal 0 (a
    parallelism over the first line's length L within a zone t is limits
    +- atan(t / L); :func:`partinspect.tolerances.geometry.line_tilt`).
    """

    between: Annotated[tuple[str, str], BeforeValidator(_pair)]
    upper: Number
    lower: Number
    nominal: Number | None = None
    towards: Annotated[tuple[Number, Number, Number], BeforeValidator(_direction)] | None = None

    @field_validator("nominal")
    @classmethod
    def _in_range(cls, v):
        if v is not None and not 0 < v < 180:
            raise PydanticCustomError("angle", "expected an angle in degrees between 0 and 180, got {got}", {"got": _show(v)})
        return v

    @model_validator(mode="after")
    def _ordered(self):
        return _check_order(self)


class ToleranceSpec(_Model):
    """A validated tolerance spec.

    Attributes
    ----------
    units : "mm"
    general : str
        General-tolerance class as ISO writes it, e.g. "ISO 2768-mK".
    decision_rule : {"iso14253", "simple"}
        ``iso14253``: conformity is proven only when the measured value +- U
        lies inside the limits (ISO 14253-1); ``simple``: the measured value
        alone decides.
    datums : tuple of str or None
        Features the alignment uses; None means all.
    datum_features : dict of str to tuple of str
        The drawing's datum letters to their features (ids or names), for
        the ``datums`` of a position tolerance.
    features : dict of str to FeatureSpec
        Keyed by CAD feature id (line-N, circle-N, arc-N) or by a name
        whose FeatureSpec has ``at``.
    distances : tuple of DistanceSpec
    angles : tuple of AngleSpec
    edge_break : EdgeBreak or None
        The edge state of every outer edge (ISO 13715's general note), unless
        a feature states its own; None: sharp.
    """

    units: Literal["mm"] = "mm"
    general: str = "ISO 2768-mK"
    decision_rule: Literal["iso14253", "simple"] = "iso14253"
    datums: tuple[str, ...] | None = None
    datum_features: Annotated[dict[str, tuple[str, ...]], _none_is_empty({})] = {}
    features: Annotated[dict[str, FeatureSpec], _none_is_empty({})] = {}
    distances: Annotated[tuple[DistanceSpec, ...], _none_is_empty(())] = ()
    angles: Annotated[tuple[AngleSpec, ...], _none_is_empty(())] = ()
    edge_break: EdgeBreakField = None

    _path: str | None = PrivateAttr(default=None)
    _lines: dict = PrivateAttr(default_factory=dict)

    @field_validator("general", mode="before")
    @classmethod
    def _general(cls, v):
        try:
            return parse_general(v).designation
        except ValueError as e:
            raise PydanticCustomError("general", str(e)) from None

    @property
    def general_class(self) -> GeneralClass:
        """The parsed general-tolerance class."""
        return parse_general(self.general)

    @property
    def path(self):
        """The file the spec was read from, or None."""
        return self._path

    def line_of(self, loc):
        """Line number (1-based) in the spec file of the key at ``loc``, or None.

        ``loc`` is a path of keys and list indices, e.g.
        ``("features", "circle-3", "diameter")`` or ``("distances", 0)``;
        the deepest part of it found in the file counts.
        """
        loc = tuple(loc)
        while loc:
            if loc in self._lines:
                return self._lines[loc]
            loc = loc[:-1]
        return self._lines.get(())


_TOP_KEYS = tuple(ToleranceSpec.model_fields)


def _model_at(loc):
    """The model class that validates the mapping at ``loc``, for listing its keys."""
    if len(loc) == 0:
        return ToleranceSpec
    if loc[-1] == "edge_break" and len(loc) in (1, 3):
        return EdgeBreak
    if loc[0] == "features":
        if len(loc) == 2:
            return FeatureSpec
        if len(loc) == 3:
            return FeatureSpec.model_fields[loc[2]].annotation.__args__[0] if loc[2] in APPLIES_TO else None
    if len(loc) == 2 and loc[0] == "distances":
        return DistanceSpec
    if len(loc) == 2 and loc[0] == "angles":
        return AngleSpec
    return None


def format_loc(loc):
    """``("distances", 0, "upper")`` -> ``"distances[0].upper"``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _did_you_mean(word, choices):
    best = difflib.get_close_matches(str(word), list(choices), n=1, cutoff=0.6)
    return f" (did you mean {best[0]!r}?)" if best else ""


def _error_message(err):
    """(loc, message) for one pydantic error, in the words of this file format."""
    kind, loc, value = err["type"], tuple(err["loc"]), err.get("input")
    if kind == "extra_forbidden":
        parent, key = loc[:-1], loc[-1]
        model = _model_at(parent)
        allowed = list(model.model_fields) if model is not None else []
        what = "characteristic" if parent[:1] == ("features",) and len(parent) == 2 else "key"
        if what == "characteristic":
            allowed = [k for k in allowed if k != "at"]
            msg = f"unknown {what} {key!r}, expected at or one of {', '.join(allowed)}"
        else:
            msg = f"unknown {what} {key!r}, expected one of {', '.join(allowed)}"
        return parent + (key,), msg + _did_you_mean(key, allowed)
    if kind == "missing":
        return loc[:-1], f"missing key {loc[-1]!r}"
    if kind == "invalid_key":
        return loc[:-1], f"keys must be text, got {_show(loc[-1])}"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return loc, f"expected a mapping, got {_show(value)}"
    if kind in ("tuple_type", "list_type"):
        return loc, f"expected a list, got {_show(value)}"
    if kind == "string_type":
        return loc, f"expected text, got {_show(value)}"
    if kind == "literal_error":
        return loc, f"expected {err['ctx']['expected']}, got {_show(value)}"
    if kind in ("too_short", "too_long"):
        return loc, f"{err['msg'][0].lower()}{err['msg'][1:]}"
    if isinstance(err.get("ctx"), dict) and kind not in ("value_error",):
        # Our own PydanticCustomError messages are already in the file's words.
        return loc, err["msg"]
    msg = err["msg"]
    return loc, f"{msg[0].lower()}{msg[1:]}, got {_show(value)}"


# -- YAML with line numbers -------------------------------------------------


def _key_text(node):
    return node.value if isinstance(node, yaml.ScalarNode) else None


def _index_lines(node, loc, lines, errors, seen_nodes=None):
    """Record the line of every key / item under ``node``; find duplicate keys."""
    # An alias makes the node graph a DAG or even a cycle (&a [*a]): visit each node once.
    seen_nodes = set() if seen_nodes is None else seen_nodes
    if id(node) in seen_nodes:
        return
    seen_nodes.add(id(node))
    if isinstance(node, yaml.MappingNode):
        seen = {}
        for key_node, value_node in node.value:
            key = _key_text(key_node)
            if key is None or key == "<<":
                continue
            line = key_node.start_mark.line + 1
            if key in seen:
                errors.append((line, f"{format_loc(loc + (key,))}: duplicate key {key!r} (first at line {seen[key]})"))
                continue
            seen[key] = line
            lines[loc + (key,)] = line
            _index_lines(value_node, loc + (key,), lines, errors, seen_nodes)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            lines[loc + (i,)] = item.start_mark.line + 1
            _index_lines(item, loc + (i,), lines, errors, seen_nodes)


def _yaml_problem(e):
    if isinstance(e, yaml.reader.ReaderError):
        return f"not valid YAML: {e.reason} ({e.character!r} at character {e.position})"
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    problem = getattr(e, "problem", None) or str(e)
    where = f"line {mark.line + 1}: " if mark is not None else ""
    return f"{where}not valid YAML: {problem}"


def _compose(text, path):
    """(data, lines, duplicate-key errors) of a YAML text; InputError if it is not YAML."""
    try:
        # The reader already checks the characters when the loader is made.
        loader = yaml.SafeLoader(text)
    except yaml.YAMLError as e:
        raise InputError(path, _yaml_problem(e)) from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None, {}, []
        lines = {(): node.start_mark.line + 1}
        errors = []
        # Before construction: SafeConstructor flattens merge keys in place.
        _index_lines(node, (), lines, errors)
        data = loader.construct_document(node)
    except yaml.YAMLError as e:
        raise InputError(path, _yaml_problem(e)) from None
    except RecursionError:
        raise InputError(path, "not valid YAML: nested too deeply") from None
    finally:
        loader.dispose()
    return data, lines, errors


# -- checks pydantic cannot make: across keys and on feature kinds ----------


def _cross_checks(data):
    """(loc, message) for mistakes that need more than one key to see."""
    errors = []
    features = data.get("features")
    features = features if isinstance(features, dict) else {}
    names = {k for k, v in features.items() if isinstance(k, str) and not FEATURE_ID_RE.match(k) and isinstance(v, dict) and "at" in v}
    known_words = sorted(names | {k for k in features if isinstance(k, str)})

    for name, body in features.items():
        if not isinstance(name, str):
            continue
        m = FEATURE_ID_RE.match(name)
        if m is None and not (isinstance(body, dict) and "at" in body):
            errors.append(
                ((("features", name)), f"{name!r} is not a CAD feature id (line-N, circle-N or arc-N) "
                 "and has no at: [x, y, z] to name an edge")
            )
        if not isinstance(body, dict):
            continue
        if m is not None:
            kind = m.group(1)
            for char in body:
                if char in APPLIES_TO and kind not in APPLIES_TO[char]:
                    takes = [c for c, kinds in APPLIES_TO.items() if kind in kinds]
                    errors.append(
                        (("features", name, char), f"{char} does not apply to a {kind} (a {kind} takes {', '.join(takes)})")
                    )
        if "diameter" in body and "radius" in body:
            errors.append((("features", name, "radius"), "give diameter or radius, not both"))

    def check_ref(ref, loc):
        if not isinstance(ref, str):
            return None  # pydantic reports the type
        if FEATURE_ID_RE.match(ref) or ref in names:
            return ref
        errors.append(
            (loc, f"unknown feature {ref!r}: expected a CAD feature id (line-N, circle-N, arc-N) or a name "
             f"defined with at: under features{_did_you_mean(ref, known_words)}")
        )
        return None

    datums = data.get("datums")
    if isinstance(datums, list):
        if not datums:
            errors.append((("datums",), "expected at least one feature (leave datums out to use all features)"))
        seen = {}
        for i, ref in enumerate(datums):
            if check_ref(ref, ("datums", i)) is not None:
                if ref in seen:
                    errors.append((("datums", i), f"{ref!r} is already a datum (datums[{seen[ref]}])"))
                seen.setdefault(ref, i)

    letters = data.get("datum_features")
    if isinstance(letters, dict):
        for letter, refs in letters.items():
            if not (isinstance(letter, str) and re.match(r"^[A-Z][A-Z0-9]*$", letter)):
                errors.append((("datum_features", letter), f"expected a datum letter (A, B, ...), got {_show(letter)}"))
            for i, ref in enumerate(refs if isinstance(refs, list) else ()):
                check_ref(ref, ("datum_features", letter, i))

    for section in ("distances", "angles"):
        items = data.get(section)
        if not isinstance(items, list):
            continue
        pairs = {}
        for i, item in enumerate(items):
            if not isinstance(item, dict) or not isinstance(item.get("between"), list) or len(item["between"]) != 2:
                continue
            refs = [check_ref(r, (section, i, "between", j)) for j, r in enumerate(item["between"])]
            if None in refs:
                continue
            if refs[0] == refs[1]:
                errors.append(((section, i, "between"), f"expected two different features, got {refs[0]!r} twice"))
                continue
            if section == "angles":
                for j, ref in enumerate(refs):
                    m = FEATURE_ID_RE.match(ref)
                    if m is not None and m.group(1) != "line":
                        errors.append(((section, i, "between", j), f"angles are between lines, {ref} is a {m.group(1)}"))
            key = frozenset(refs)
            if key in pairs:
                errors.append(((section, i, "between"), f"the same pair is already toleranced in {section}[{pairs[key]}]"))
            pairs.setdefault(key, i)
    return errors


# -- public API -------------------------------------------------------------


def parse_spec(text, path=None):
    """Parse and validate the text of a tolerance spec.

    Parameters
    ----------
    text : str or bytes
        YAML text (UTF-8 when bytes).
    path : str or os.PathLike, optional
        The file it came from, named in error messages.

    Returns
    -------
    ToleranceSpec

    Raises
    ------
    partinspect.errors.InputError
        On any mistake; the message lists every mistake found, each as
        ``line N: key.path: what was expected``, joined by "; ".

    Examples
    --------
    >>> spec = parse_spec("general: mK\\nfeatures:\\n  circle-1:\\n    diameter: {upper: 0.1, lower: 0}\\n")
    >>> spec.general, spec.features["circle-1"].diameter.upper
    ('ISO 2768-mK', 0.1)
    """
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as e:
            raise InputError(path, f"not UTF-8 text (byte {e.start})") from None
    if "\x00" in text:
        # PyYAML would report an unprintable character; a NUL means a binary file.
        raise InputError(path, "not a text file (contains NUL bytes)")
    data, lines, errors = _compose(text, path)
    expected = f"expected a mapping with keys {', '.join(_TOP_KEYS)}"
    if data is None:
        raise InputError(path, f"empty file, {expected}")
    if not isinstance(data, dict):
        raise InputError(path, f"line {lines[()]}: {expected}, got {_show(data)}")

    spec = None
    try:
        spec = ToleranceSpec.model_validate(data)
    except ValidationError as e:
        for err in e.errors():
            loc, msg = _error_message(err)
            errors.append((_line(lines, loc), f"{format_loc(loc)}: {msg}" if loc else msg))
    except (RecursionError, TypeError, ValueError) as e:
        # Cyclic YAML aliases (&a [*a]) and the like: not a tolerance spec.
        errors.append((lines[()], f"cannot be read as a tolerance spec ({type(e).__name__})"))
    for loc, msg in _cross_checks(data):
        errors.append((_line(lines, loc), f"{format_loc(loc)}: {msg}"))
    if errors:
        raise InputError(path, join_errors(errors))
    spec._path = None if path is None else str(path)
    spec._lines = lines
    return spec


def _line(lines, loc):
    loc = tuple(loc)
    while loc and loc not in lines:
        loc = loc[:-1]
    return lines.get(loc)


def join_errors(errors):
    """One line from ``[(line or None, message), ...]``: sorted by line, duplicates dropped."""
    seen, parts = set(), []
    for line, msg in sorted(errors, key=lambda e: (e[0] is None, e[0] or 0)):
        text = msg if line is None else f"line {line}: {msg}"
        if text not in seen:
            seen.add(text)
            parts.append(text)
    return "; ".join(parts)


def load_spec(path):
    """Read and validate a tolerance spec file.

    Parameters
    ----------
    path : str or os.PathLike
        The YAML file.

    Returns
    -------
    ToleranceSpec

    Raises
    ------
    partinspect.errors.InputError
        If the file is missing or unreadable, or has any mistake (see
        :func:`parse_spec`).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(path, "tolerance file not found") from None
    except IsADirectoryError:
        raise InputError(path, "not a regular file") from None
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None
    return parse_spec(raw, path)


def default_spec():
    """The spec that applies without a file: ISO 2768-mK for everything, ISO 14253-1 decisions."""
    return ToleranceSpec()


def spec_to_dict(spec):
    """The spec as plain data that :func:`parse_spec` reads back to an equal spec.

    Keys at their default value are left out; numbers stay floats.
    """

    def clean(v):
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items() if x is not None}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v

    out = {"units": spec.units, "general": spec.general, "decision_rule": spec.decision_rule}
    if spec.datums is not None:
        out["datums"] = list(spec.datums)
    if spec.datum_features:
        out["datum_features"] = {k: list(v) for k, v in spec.datum_features.items()}
    if spec.edge_break is not None:
        out["edge_break"] = spec.edge_break.model_dump()
    if spec.features:
        out["features"] = {name: clean(f.model_dump()) for name, f in spec.features.items()}
    if spec.distances:
        out["distances"] = [clean(d.model_dump()) for d in spec.distances]
    if spec.angles:
        out["angles"] = [clean(a.model_dump()) for a in spec.angles]
    return out


def dump_spec(spec):
    """The spec as YAML text in the file format."""
    return yaml.safe_dump(spec_to_dict(spec), sort_keys=False, default_flow_style=None)
