"""A tolerance spec from a STEP file's semantic PMI.

PMI attaches each tolerance to faces; partinspect measures edges. Each PMI
item is carried over to the edges that bound its faces, where that edge
characteristic checks the same requirement, and listed as not evaluated,
with the reason, where it does not.

======================  ======================================================
PMI                     characteristic (edges of the toleranced faces)
======================  ======================================================
diameter, radius        diameter / radius of each rim circle or arc of the
                        cylinder (a hole's or a boss's two ends)
linear distance         ``distances``: the pair of parallel lines, or
                        circle centres, one on each side, whose CAD distance
                        is the nominal
angle                   ``angles``: a pair of lines, one on each face, whose
                        CAD angle is the nominal
position (cylinder)     position of each rim circle, zone = the tolerance;
                        an MMC/LMC modifier becomes ``material``: the bonus
                        from the rim's measured size (:mod:`.material`),
                        a zero tolerance at MMC/LMC included; a datum at
                        MMB/LMB in its frame, ``datums: [A, B(M), C(M)]``
                        (the datum shift, :mod:`.datum_shift`), the
                        datums' features under ``datum_features``
circularity             circularity of each rim circle
cylindricity            circularity of each rim circle (a necessary part)
flatness, straightness  straightness of each straight boundary edge of the
                        plane, zone = the tolerance
profile of a line       profile of each boundary edge
perpendicularity,       ``angles``: a boundary line of the toleranced plane
angularity (plane)      across the line where it meets the datum plane,
                        against a datum plane line across it too (their
                        angle is the dihedral angle), nominal from the CAD
                        model, limits +- atan(t / L) over the line's
                        length L
parallelism (plane)     ``angles`` between parallel lines: the longest
                        boundary line of the toleranced plane against the
                        longest datum plane line parallel to it,
                        ``towards`` the datum's normal; the value is the
                        line's tilt towards it (its distance from the
                        datum plane spreads by L sin(tilt) over its length
                        L), nominal 0, limits +- atan(t / L)
======================  ======================================================

Everything else (surface profile, parallelism of an axis, symmetry, run-out, an
orientation of an axis, thickness, items without a value or without a face
in the model, tolerances OCCT did not read) is *not evaluated*, each with
its reason. Datums the PMI names become the spec's ``datums``: the
boundary lines of a datum plane and the rim circles of a datum cylinder.

Flatness carried to edge straightness is a partial check: it sees the
face's boundary only, and a boundary edge's straightness zone also bounds
its bending within the plane, which flatness does not; a part that fails
it may still be flat, never the other way round.

References
----------
.. [1] ISO 1101:2017, Geometrical product specifications (GPS) --
       Geometrical tolerancing.
.. [2] ASME Y14.5-2018, Dimensioning and Tolerancing.
.. [3] NIST, "MBE PMI Validation and Conformance Testing", combined and
       fully toleranced test cases (CTC, FTC), https://go.usa.gov/mGVm
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from partinspect.cad.features import cylinder_sides
from partinspect.tolerances.geometry import feature_distance, line_angle, line_gap, lines_parallel
from partinspect.tolerances.material import MODIFIERS

__all__ = ["NotEvaluated", "PmiSpec", "datum_entry", "load_pmi_spec", "merge_pmi", "spec_from_pmi"]

# A CAD distance or angle is the one a PMI dimension names when it agrees
# with the nominal within this part of the tolerance width (and 1e-3 mm or
# 1e-4 rad at least: the PMI nominal is rounded to the drawing's decimals).
_NOMINAL_SHARE = 0.5
_MIN_MATCH = {"mm": 1e-3, "rad": 1e-4}
# Within this angle a line runs along a direction, rad.
_ALONG = 1e-6
# Below this part of their length apart two lines meet.
_MEET = 1e-6


@dataclass(frozen=True)
class NotEvaluated:
    """A PMI item no edge measurement checks, and why."""

    item: str
    type: str
    reason: str

    def to_dict(self):
        return {"item": self.item, "type": self.type, "reason": self.reason}


@dataclass
class PmiSpec:
    """What the PMI defines, in the tolerance spec's terms.

    Attributes
    ----------
    data : dict
        A spec as plain data (``parse_spec`` / ``ToleranceSpec.model_validate``
        read it): ``datums``, ``features``, ``distances``, ``angles``.
    sources : dict
        Spec location (``("features", "circle-3", "diameter")``,
        ``("distances", 0)``) to the PMI item id it comes from.
    applies_to : dict
        PMI item id to the feature ids it was carried to.
    not_evaluated : list of NotEvaluated
    datums : dict
        Datum letter to the feature ids of its faces (``data["datums"]`` is
        their union), in letter order: the PMI's datum reference frame as
        the alignment sees it.
    """

    data: dict = field(default_factory=dict)
    sources: dict = field(default_factory=dict)
    applies_to: dict = field(default_factory=dict)
    not_evaluated: list = field(default_factory=list)
    datums: dict = field(default_factory=dict)

    def spec(self):
        """The data as a validated ToleranceSpec."""
        from partinspect.tolerances.spec import ToleranceSpec

        return ToleranceSpec.model_validate(self.data)


def spec_from_pmi(pmi, inventory):
    """Carry a part's PMI over to its edge features.

    Parameters
    ----------
    pmi : partinspect.cad.pmi.Pmi
    inventory : partinspect.cad.features.Inventory
        Of the same STEP file (face ids are geometric, so any load of it).

    Returns
    -------
    PmiSpec
        The module table says which item becomes what; every item that
        becomes nothing is in ``not_evaluated`` with its reason.
    """
    m = _Mapper(inventory)
    # Datums first: an orientation tolerance needs its datum's faces.
    for item in pmi.items:
        if item.kind == "datum":
            m.datum(item)
    for item in pmi.items:
        if item.kind == "dimension":
            m.dimension(item)
        elif item.kind == "tolerance":
            m.tolerance(item)
    for name, etype, value in pmi.unread:
        what = etype.lower().removesuffix("_tolerance")
        shown = "" if value is None else f" {value:.4g} mm"
        m.skip(name or "(unnamed)", what, f"not read by OCCT (the file's {etype}{shown})")
    return m.result()


class _Mapper:
    def __init__(self, inventory):
        self.inv = inventory
        self.faces = {f.id: f for f in inventory.faces}
        self.edges_of = {}
        for f in inventory.features:
            if f.smooth:
                continue  # a tangent edge shows no image edge
            for fid in f.faces:
                self.edges_of.setdefault(fid, []).append(f)
        self.out = PmiSpec(data={"features": {}, "distances": [], "angles": []})
        self.datums = {}
        self.datum_faces = {}
        self.shifted = False

    # -- bookkeeping ----------------------------------------------------------

    def skip(self, item_id, ctype, reason):
        self.out.not_evaluated.append(NotEvaluated(item_id, ctype, reason))

    def put(self, item, feature_id, ctype, value):
        slot = "size" if ctype in ("diameter", "radius") else ctype
        body = self.out.data["features"].setdefault(feature_id, {})
        taken = [c for c in body if ("size" if c in ("diameter", "radius") else c) == slot]
        if taken:
            return self.out.sources[("features", feature_id, taken[0])]
        body[ctype] = value
        self.out.sources[("features", feature_id, ctype)] = item.id
        self.out.applies_to.setdefault(item.id, []).append(feature_id)
        return None

    def put_all(self, item, features, ctype, value):
        clashes = [c for f in features if (c := self.put(item, f.id, ctype, value)) is not None]
        if not self.out.applies_to.get(item.id):
            self.skip(item.id, item.type, f"its edges already carry a {ctype} from {', '.join(sorted(set(clashes)))}")

    def result(self):
        data = self.out.data
        self.out.datums = {letter: list(self.datums[letter]) for letter in sorted(self.datums)}
        ids = list(dict.fromkeys(fid for fids in self.out.datums.values() for fid in fids))
        if ids:
            data["datums"] = ids
        if self.shifted and self.out.datums:
            # A position's datums at MMB/LMB name letters: say which features they are.
            data["datum_features"] = {letter: ids for letter, ids in self.out.datums.items()}
        for key in ("features", "distances", "angles"):
            if not data[key]:
                del data[key]
        return self.out

    # -- faces to edges -------------------------------------------------------

    def _known_faces(self, item, faces):
        missing = [f for f in faces if f not in self.faces]
        if missing:
            self.skip(item.id, item.type, f"attached to {', '.join(missing)}, not a face of the model")
            return None
        return [self.faces[f] for f in faces]

    def rims(self, faces):
        """Circles and arcs bounding cylinder faces, on the cylinder itself."""
        out = []
        for face in faces:
            if face.surface != "cylinder":
                continue
            for f in self.edges_of.get(face.id, ()):
                if f.kind != "line" and abs(f.radius - face.radius) <= 1e-6 * max(1.0, face.radius) and f not in out:
                    out.append(f)
        return out

    def lines(self, faces):
        out = []
        for face in faces:
            out += [f for f in self.edges_of.get(face.id, ()) if f.kind == "line" and f not in out]
        return out

    def boundary(self, faces):
        out = []
        for face in faces:
            out += [f for f in self.edges_of.get(face.id, ()) if f not in out]
        return out

    # -- items ----------------------------------------------------------------

    def datum(self, item):
        faces = self._known_faces(item, item.faces) if item.faces else []
        if faces is None:
            return
        self.datum_faces[item.name] = faces
        features = self.lines([f for f in faces if f.surface == "plane"]) + self.rims(faces)
        if not features:
            reason = "attached to no face in the file" if not item.faces else "no straight or circular edge bounds its faces"
            self.skip(item.id, "datum", reason)
            return
        self.datums[item.name] = [f.id for f in features]
        self.out.applies_to[item.id] = [f.id for f in features]

    def dimension(self, item):
        if item.value is None:
            self.skip(item.id, item.type, "no value in the file's semantic PMI")
            return
        if item.upper is None:
            self.skip(item.id, item.type, "no tolerance given (a basic or reference dimension)")
            return
        faces = self._known_faces(item, item.faces + item.faces2)
        if faces is None:
            return
        if item.type in ("diameter", "radius"):
            rims = self.rims(faces)
            if not rims:
                self.skip(item.id, item.type, "no circular edge bounds the toleranced cylinder")
                return
            self.put_all(item, rims, item.type, {"upper": item.upper, "lower": item.lower})
        elif item.type == "linear_distance":
            self.pair(item, "distances")
        elif item.type == "angle":
            self.pair(item, "angles")
        else:
            self.skip(item.id, item.type, f"a {item.type.replace('_', ' ')} is not a quantity between measured edges")

    def pair(self, item, section):
        side_a = self._known_faces(item, item.faces)
        side_b = self._known_faces(item, item.faces2)
        if side_a is None or side_b is None:
            return
        if not side_a or not side_b:
            self.skip(item.id, item.type, "attached to edges, not to two faces")
            return
        unit = "rad" if section == "angles" else "mm"
        tol = max(_NOMINAL_SHARE * (item.upper - item.lower), _MIN_MATCH[unit])
        best = None
        for fa in (self.lines(side_a) if section == "angles" else self.boundary(side_a)):
            for fb in (self.lines(side_b) if section == "angles" else self.boundary(side_b)):
                if fa is fb:
                    continue
                try:
                    if section == "angles":
                        cad = line_angle(fa.start, fa.end, fb.start, fb.end)
                    else:
                        cad = feature_distance(fa, fb)
                except ValueError:
                    continue
                if abs(cad - item.value) <= tol:
                    # Of edge pairs at the angle, one that meets at a corner
                    # first: the drawing's angle, seen in one view.
                    meets = section == "angles" and line_gap(fa.start, fa.end, fb.start, fb.end) <= _MEET * max(
                        1.0, fa.length, fb.length)
                    score = (meets, min(fa.length, fb.length))
                    if best is None or score > best[0]:
                        best = (score, fa, fb)
        if best is None:
            what = "angle" if section == "angles" else "distance"
            shown = f"{math.degrees(item.value):.4g} degrees" if unit == "rad" else f"{item.value:.4g} mm"
            self.skip(item.id, item.type, f"no pair of edges of its faces is at the {what} of {shown}")
            return
        _, fa, fb = best
        conv = math.degrees if unit == "rad" else float
        entry = {"between": [fa.id, fb.id], "upper": _r(conv(item.upper)), "lower": _r(conv(item.lower))}
        if any(set(e["between"]) == {fa.id, fb.id} for e in self.out.data[section]):
            self.skip(item.id, item.type, f"{fa.id} and {fb.id} are already toleranced by another item")
            return
        self.out.sources[(section, len(self.out.data[section]))] = item.id
        self.out.data[section].append(entry)
        self.out.applies_to[item.id] = [fa.id, fb.id]

    def tolerance(self, item):
        if item.value is None:
            self.skip(item.id, item.type, "no tolerance value in the file" + (f" ({item.notes[-1]})" if item.notes else ""))
            return
        faces = self._known_faces(item, item.faces + item.faces2)
        if faces is None:
            return
        if not faces:
            self.skip(item.id, item.type, "attached to no face of the model")
            return
        t = item.type
        material = [m for m in item.modifiers if m in MODIFIERS] if t == "position" else []
        if item.value <= 0 and not material:
            self.skip(item.id, t, "zero tolerance")
            return
        zone = {"tolerance": item.value}
        if t in ("position", "circularity", "cylindricity"):
            rims = [f for f in self.rims(faces) if t == "position" or f.kind == "circle"]
            if not rims:
                surfaces = ", ".join(sorted({f.surface for f in faces}))
                self.skip(item.id, t, f"attached to {surfaces} faces with no circular edge of their own: the spec's "
                          "position is a circle centre's" if t == "position" else
                          "no full circular edge bounds the toleranced cylinder")
                return
            if material:
                sides = cylinder_sides(faces)
                if len(sides) != 1 or None in sides:
                    self.skip(item.id, t, f"at {material[0]}, but its faces are not one hole or one boss: no size to "
                              "take the bonus from")
                    return
                zone["material"] = material[0]
            if t == "position" and any(m.startswith("datum_") for m in item.modifiers):
                marks = {"MMB": "(M)", "LMB": "(L)"}
                zone["datums"] = [d + "".join(marks[b] for b in marks if f"datum_{d}_{b}" in item.modifiers)
                                  for d in item.datums]
                self.shifted = True
            self.put_all(item, rims, "position" if t == "position" else "circularity", zone)
        elif t in ("flatness", "straightness"):
            lines = self.lines([f for f in faces if f.surface == "plane"] if t == "flatness" else faces)
            if not lines:
                self.skip(item.id, t, "no straight edge bounds the toleranced face")
                return
            self.put_all(item, lines, "straightness", zone)
        elif t == "profile_of_line":
            edges = self.boundary(faces)
            if not edges:
                self.skip(item.id, t, "no straight or circular edge bounds the toleranced face")
                return
            self.put_all(item, edges, "profile", zone)
        elif t in ("perpendicularity", "angularity"):
            self.orientation(item, faces)
        elif t == "profile_of_surface":
            self.skip(item.id, t, "a surface profile needs the surface; its boundary edges do not sample it")
        elif t == "parallelism":
            self.parallelism(item, faces)
        else:
            self.skip(item.id, t, f"{t.replace('_', ' ')} is not checked from edges")

    def _planes(self, item, faces, how):
        """The toleranced planes and the datum's planes of an orientation tolerance, or None (skipped, with why)."""
        planes = [f for f in faces if f.surface == "plane"]
        if not planes or len(planes) != len(faces):
            self.skip(item.id, item.type, "an axis's orientation is not an edge characteristic (only a plane's is, "
                      f"as {how} between edges)")
            return None
        dplanes = self._datum_planes(item)
        return None if dplanes is None else (planes, dplanes)

    def orientation(self, item, faces):
        found = self._planes(item, faces, "an angle")
        if found is None:
            return
        planes, dplanes = found
        # Both edges must run across the planes' line of intersection: the
        # angle between them is then the dihedral angle the tolerance bounds.
        n_face, n_datum = np.asarray(planes[0].normal, float), np.asarray(dplanes[0].normal, float)
        axis = np.cross(n_face, n_datum)
        if np.linalg.norm(axis) < _ALONG:
            self.skip(item.id, item.type, "the face is parallel to its datum plane: parallel edges have no angle")
            return
        axis /= np.linalg.norm(axis)

        def across(lines):
            return [f for f in lines if abs(np.asarray(f.direction) @ axis) < _ALONG]

        best = None
        for line in across(self.lines(planes)):
            for dl in across(self.lines(dplanes)):
                if best is None or (line.length, dl.length) > (best[0].length, best[1].length):
                    best = (line, dl)
        if best is None:
            self.skip(item.id, item.type, "no edge of the face, or none of its datum plane, runs across the line "
                      "where the two planes meet")
            return
        self.tilt_entry(item, *best)

    def parallelism(self, item, faces):
        found = self._planes(item, faces, "the tilt")
        if found is None:
            return
        planes, dplanes = found
        n = np.asarray(dplanes[0].normal, float)
        if np.linalg.norm(np.cross(np.asarray(planes[0].normal, float), n)) > _ALONG:
            self.skip(item.id, item.type, "the face is not parallel to its datum plane in the model")
            return
        # The longest face line against the longest datum-plane line
        # parallel to it; the tilt is taken towards the datum's normal, so
        # it is the tilt out of the datum plane that the zone bounds.
        best = None
        for line in self.lines(planes):
            for dl in self.lines(dplanes):
                if lines_parallel(line.start, line.end, dl.start, dl.end):
                    if best is None or (line.length, dl.length) > (best[0].length, best[1].length):
                        best = (line, dl)
        if best is None:
            what = "edge of the face has" if self.lines(planes) else "straight edge bounds the face, so none has"
            self.skip(item.id, item.type, f"no {what} an edge of its datum plane parallel to it")
            return
        self.tilt_entry(item, *best, towards=n)

    def _datum_planes(self, item):
        datum = item.datums[0] if item.datums else None
        dplanes = [f for f in self.datum_faces.get(datum, ()) if f.surface == "plane"]
        if not dplanes:
            self.skip(item.id, item.type, f"its datum {datum or '(none)'} is not a plane attached to the model")
            return None
        return dplanes

    def tilt_entry(self, item, line, dl, towards=None):
        """An ``angles`` entry of ``line`` against datum line ``dl``: +- atan(t / L) over the line's length."""
        half = math.degrees(math.atan(item.value / line.length))
        entry = {"between": [line.id, dl.id], "upper": _r(half), "lower": _r(-half)}
        if towards is not None:
            entry["towards"] = [_r(x) for x in towards]
        if any(set(e["between"]) == {line.id, dl.id} for e in self.out.data["angles"]):
            self.skip(item.id, item.type, f"{line.id} and {dl.id} are already toleranced by another item")
            return
        self.out.sources[("angles", len(self.out.data["angles"]))] = item.id
        self.out.data["angles"].append(entry)
        self.out.applies_to[item.id] = [line.id, dl.id]


def _r(x):
    return round(float(x), 9) + 0.0


# -- the PMI of a STEP file, merged with a spec -------------------------------


def load_pmi_spec(part, inventory):
    """Read a STEP file's PMI and carry it over to its edges.

    Parameters
    ----------
    part : str or os.PathLike
        The STEP file.
    inventory : partinspect.cad.features.Inventory
        Its feature inventory.

    Returns
    -------
    pmi : partinspect.cad.pmi.Pmi
    pmi_spec : PmiSpec
    """
    from partinspect.cad.pmi import read_pmi

    pmi = read_pmi(part)
    return pmi, spec_from_pmi(pmi, inventory)


def merge_pmi(resolved, inventory, part, pmi=None):
    """A resolved spec with the PMI's characteristics added where it has none.

    Item by item, the spec (file) wins: a PMI characteristic is dropped when
    the spec tolerances the same size, form or location of the same edge,
    or the same pair of edges. Without a spec file, the PMI's datums are
    the alignment's, the features `inspect spec` writes as the spec's
    ``datums`` (ASME Y14.5 and ISO 5459 measure every tolerance from the
    datum reference frame); a spec file keeps its own datums, every
    feature when it names none, so deleting the key of the spec `inspect
    spec` wrote aligns on every feature.

    Parameters
    ----------
    resolved : partinspect.tolerances.resolve.ResolvedSpec
        The spec file's (or the default spec's), resolved.
    inventory : partinspect.cad.features.Inventory
    part : str or os.PathLike
        The STEP file.
    pmi : partinspect.cad.pmi.Pmi, optional
        Its PMI, if already read; else it is read here.

    Returns
    -------
    ResolvedSpec
        Its characteristics: the spec's, then the PMI's, each PMI one with
        ``source`` "PMI" and ``rule`` naming the item; ``not_evaluated``
        lists what the PMI holds that no edge characteristic checks. A PMI
        that cannot be read or carried over is one entry there, and the
        run goes on without it (ISO 2768 for the rest).
    """
    from dataclasses import replace
    from pathlib import Path

    from partinspect.tolerances.pmi_text import describe_item
    from partinspect.tolerances.resolve import resolve_spec

    name = Path(part).name
    try:
        if pmi is None:
            pmi, ps = load_pmi_spec(part, inventory)
        else:
            ps = spec_from_pmi(pmi, inventory)
        if not ps.sources and not ps.not_evaluated:
            return resolved
        pmi_resolved = resolve_spec(ps.spec(), inventory, None)
    except Exception as e:  # noqa: BLE001  the PMI is an optional input: a bad one must not stop the run
        text = " ".join(str(e).split()) or type(e).__name__
        why = NotEvaluated(name, "PMI", f"the PMI could not be used ({text}); the spec and ISO 2768 apply instead")
        return replace(resolved, not_evaluated=resolved.not_evaluated + (why,))
    by_id = {i.id: i for i in pmi.items}
    rules = {}
    for loc, item_id in ps.sources.items():
        item = by_id[item_id]
        label = f"{name} PMI {item_id} ({describe_item(item)}{', ' + repr(item.name) if item.name else ''})"
        if loc[0] == "features":
            rules[f"{loc[1]}.{loc[2]}"] = label
        else:
            entry = ps.data[loc[0]][loc[1]]
            rules[f"{loc[0][:-1]}({entry['between'][0]},{entry['between'][1]})"] = label
    taken = {_slot(c) for c in resolved.characteristics}
    added = tuple(replace(c, source="PMI", rule=rules.get(c.id, f"{name} PMI"))
                  for c in pmi_resolved.characteristics if _slot(c) not in taken)
    merged = replace(resolved, characteristics=resolved.characteristics + added,
                     not_evaluated=resolved.not_evaluated + tuple(ps.not_evaluated))
    if resolved.path is None and ps.datums:
        merged = replace(merged, datums=pmi_resolved.datums, datum_frame=tuple((k, tuple(v)) for k, v in ps.datums.items()),
                         datum_source=f"{name} PMI datums {'|'.join(ps.datums)}")
    return merged


def datum_entry(resolved, used):
    """report.json's ``registration.datum_reference``: where the alignment's datums come from.

    Parameters
    ----------
    resolved : partinspect.tolerances.resolve.ResolvedSpec
    used : sequence of str
        The CAD ids the registration was fitted on (``Registration.datums``).

    Returns
    -------
    dict or None
        ``source`` (the spec line or the PMI datums), ``frame`` (each PMI
        datum letter with its features, and which of them were measured and
        fitted), ``applied``: False when the registration had to use every
        matched feature instead (the named datums, as measured, leave the
        pose free), with ``reason``. None when no datums are named.
    """
    if resolved.datum_source is None:
        return None
    used = set(used)
    applied = used <= set(resolved.datums)
    entry = {"source": resolved.datum_source, "applied": applied}
    if resolved.datum_frame:
        entry["frame"] = [{"datum": letter, "features": list(ids), "fitted": [f for f in ids if f in used and applied]}
                          for letter, ids in resolved.datum_frame]
    if not applied:
        entry["reason"] = ("the datums' edges, as measured, leave the pose free in some direction; "
                           "aligned on every matched feature")
    return entry


def _slot(c):
    kind = "size" if c.type in ("diameter", "radius") else c.type
    return (kind, frozenset(c.features)) if len(c.features) > 1 else (kind, c.features[0])
