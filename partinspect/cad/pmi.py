"""Semantic PMI of a STEP file: dimensions, geometric tolerances and datums.

STEP AP242 (and some AP203/AP214 files) carry *semantic* product and
manufacturing information: each dimension and geometric tolerance is an
entity with its value, limits, modifiers and datum reference frame, linked
to the faces and edges it applies to. `read_pmi` reads it with OCCT's XCAF
(``STEPCAFControl_Reader`` with GD&T mode on, ``XCAFDoc_DimTolTool``) and
returns plain records: values in mm and radians, attached faces by their
geometric ids (``face-N``, the same ids `partinspect.cad.features` gives),
attached edges by their mid-points (part frame, mm).

OCCT 7.9 reads most of it but not all, and these gaps are repaired here,
each one noted on the item it touched:

- a tolerance magnitude written as a compound entity
  ``(LENGTH_MEASURE_WITH_UNIT() MEASURE_REPRESENTATION_ITEM() ...)``
  comes back as 0; the value is then read from the file's own text, by the
  tolerance's name (`step_tolerance_values`);
- a dimension's nominal is not converted to mm when its limits are (a
  0.234 in diameter with mm limits): when every diameter and radius
  matches its cylinder only after scaling by 25.4, the nominals are inch
  (`_nominal_unit`);
- ``GetLowerTolValue`` returns the size of the lower deviation, positive:
  it is negated;
- graphics-only entries (presentation, common labels) sit among the
  dimensions: they are counted, not listed;
- datum labels repeat for every tolerance that uses them: datums are
  merged by their letter;
- some tolerances are not read at all: the text's ones left over are
  listed as ``Pmi.unread``.

References
----------
.. [1] ISO 10303-242:2020, Managed model-based 3D engineering (AP242).
.. [2] CAx-IF, Recommended Practices for the Representation and Presentation
       of Product Manufacturing Information (PMI), AP242, version 4.0.
.. [3] NIST MBE PMI Validation and Conformance Testing: combined and fully
       toleranced test cases (CTC, FTC), https://go.usa.gov/mGVm
"""

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from partinspect.cad.step import check_step_file, quiet_occt
from partinspect.cad.step_text import INCH, step_tolerance_values
from partinspect.errors import InputError

__all__ = ["INCH", "PmiItem", "Pmi", "has_semantic_pmi", "read_pmi", "step_tolerance_values"]

# A nominal that agrees with the CAD size within this relative amount is
# taken as the size it names.
_SIZE_MATCH = 1e-3


@dataclass(frozen=True, eq=False)
class PmiItem:
    """One semantic PMI entry.

    Attributes
    ----------
    id : str
        ``"dim-N"`` (dimensions), ``"gtol-N"`` (geometric tolerances), in
        the order OCCT lists them, or ``"datum-A"``.
    kind : {"dimension", "tolerance", "datum"}
    type : str
        Dimensions: ``"diameter"``, ``"radius"``, ``"linear_distance"``,
        ``"angle"``, ``"thickness"``, ``"curve_length"``, ... or
        ``"unknown"`` when OCCT read no type. Tolerances: ``"position"``,
        ``"flatness"``, ``"straightness"``, ``"circularity"``,
        ``"cylindricity"``, ``"perpendicularity"``, ``"parallelism"``,
        ``"angularity"``, ``"profile_of_line"``, ``"profile_of_surface"``,
        ``"symmetry"``, ``"concentricity"``, ``"coaxiality"``,
        ``"circular_runout"``, ``"total_runout"``. Datums: ``"datum"``.
    name : str
        The name the file gives it ("Position.1", "diameter"), or "".
    value : float or None
        Dimensions: the nominal; tolerances: the zone width (diameter for a
        diameter zone). mm, or radians for angles. None when unknown.
    upper, lower : float or None
        Dimensions: the limit deviations from ``value`` (lower <= upper),
        same unit. None when the dimension has no tolerance.
    modifiers : tuple of str
        Dimension and tolerance modifiers as OCCT names them
        ("All_Around", "Maximum_Material_Requirement", ...), plus the
        material condition ("MMC"/"LMC") and zone ("diameter_zone",
        "projected_zone") where given, and ``"datum_B_MMB"`` (or ``_LMB``)
        for a datum referenced at its material boundary.
    datums : tuple of str
        Tolerances: the datum reference frame, datum letters in order of
        precedence (primary first). Datums: the letter itself.
    faces, faces2 : tuple of str
        Ids (``face-N``) of the faces the item is attached to; ``faces2``
        holds the second side of a location dimension.
    edges : tuple of ndarray, shape (3,)
        Mid-points of the edges the item is attached to, part frame, mm.
    notes : tuple of str
        What was repaired or could not be read.
    """

    id: str
    kind: str
    type: str
    name: str = ""
    value: float | None = None
    upper: float | None = None
    lower: float | None = None
    modifiers: tuple = ()
    datums: tuple = ()
    faces: tuple = ()
    faces2: tuple = ()
    edges: tuple = ()
    notes: tuple = ()

    @property
    def unit(self):
        """``"rad"`` for angles, else ``"mm"``."""
        return "rad" if self.type == "angle" and self.kind == "dimension" else "mm"

    def to_dict(self):
        d = {"id": self.id, "kind": self.kind, "type": self.type, "name": self.name}
        for key in ("value", "upper", "lower"):
            v = getattr(self, key)
            d[key] = None if v is None else float(v)
        d["unit"] = self.unit
        d.update(modifiers=list(self.modifiers), datums=list(self.datums), faces=list(self.faces),
                 faces2=list(self.faces2), edges=[[float(x) for x in p] for p in self.edges], notes=list(self.notes))
        return d


@dataclass(frozen=True, eq=False)
class Pmi:
    """All semantic PMI of a STEP file.

    Attributes
    ----------
    items : tuple of PmiItem
        Dimensions, then geometric tolerances, then datums.
    labels : dict of str to int
        How many dimension, geometric tolerance and datum labels OCCT found
        (``"dimensions"``, ``"tolerances"``, ``"datums"``), graphics-only
        and repeated ones included.
    presentation_only : int
        Dimension labels that carry graphics only (no semantics).
    unread : tuple of (str, str, float or None)
        Geometric tolerances the file's text holds but OCCT did not read
        (name, STEP entity type, value in mm), as `step_tolerance_values`
        gives them.
    seconds : float
        Wall time of the read (XCAF parse and transfer), s.
    faces : tuple of partinspect.cad.features.FaceInfo
        The faces of the part's solids as XCAF holds them, in id order:
        the ids the items use, the same as the feature inventory's.
    """

    items: tuple = ()
    labels: dict = field(default_factory=dict)
    presentation_only: int = 0
    unread: tuple = ()
    seconds: float = 0.0
    faces: tuple = ()

    def __bool__(self):
        return bool(self.items)

    def of_kind(self, kind):
        return tuple(i for i in self.items if i.kind == kind)

    def __getitem__(self, id):
        for item in self.items:
            if item.id == id:
                return item
        raise KeyError(f"no PMI item {id!r}")

    def to_dict(self):
        return {"schema": "pmi/1", "units": "mm", "labels": dict(self.labels),
                "presentation_only": self.presentation_only, "items": [i.to_dict() for i in self.items],
                "unread": [{"name": n, "entity": e, "value": v} for n, e, v in self.unread]}


def read_pmi(path):
    """Read the semantic PMI of a STEP file.

    Parameters
    ----------
    path : str or os.PathLike
        A STEP Part 21 file.

    Returns
    -------
    Pmi
        Empty (``bool(pmi)`` is False) when the file carries no semantic
        PMI, as AP203/AP214 files of geometry alone.

    Raises
    ------
    partinspect.errors.InputError
        If the file is not a readable STEP file (the same checks as
        `partinspect.cad.step.load_step`).

    Notes
    -----
    This is a second parse of the file, through XCAF; on the NIST test
    files (0.2-2 MB) it takes 0.2-1.3 s. A file whose text names no PMI
    entity (`has_semantic_pmi`) is not parsed again.
    """
    import time

    path = Path(path)
    check_step_file(path)
    t0 = time.perf_counter()
    if not has_semantic_pmi(path):
        return Pmi((), {"dimensions": 0, "tolerances": 0, "datums": 0}, 0, (), time.perf_counter() - t0)
    doc = _read_document(path)
    from OCP.TDF import TDF_LabelSequence
    from OCP.XCAFDoc import XCAFDoc_DocumentTool

    dimtol = XCAFDoc_DocumentTool.DimTolTool_s(doc.Main())
    shape_tool = XCAFDoc_DocumentTool.ShapeTool_s(doc.Main())
    sequences = {}
    for key, getter in (("dimensions", dimtol.GetDimensionLabels), ("tolerances", dimtol.GetGeomToleranceLabels),
                        ("datums", dimtol.GetDatumLabels)):
        seq = TDF_LabelSequence()
        getter(seq)
        sequences[key] = [seq.Value(i) for i in range(1, seq.Length() + 1)]
    labels = {k: len(v) for k, v in sequences.items()}
    seconds = time.perf_counter() - t0
    if not any(labels.values()):
        return Pmi((), labels, 0, seconds)

    targets = _Targets(shape_tool)
    text_values = step_tolerance_values(path)
    dims, n_graphic = _dimensions(sequences["dimensions"], targets)
    tols = _tolerances(sequences["tolerances"], targets, text_values)
    datums = _datums(sequences["datums"], targets)
    return Pmi(tuple(dims + tols + datums), labels, n_graphic, _unread(text_values, tols), time.perf_counter() - t0,
               tuple(targets.infos))


def _unread(text_values, tols):
    """The text's tolerances left over once each read one has taken one of its name."""
    left = list(text_values)
    for t in tols:
        for k, (name, _, _) in enumerate(left):
            if name == t.name:
                del left[k]
                break
    return tuple(left)


# Entity names only semantic PMI uses (ISO 10303-47 shape tolerances).
_PMI_MARKERS = (b"DIMENSIONAL_SIZE", b"DIMENSIONAL_LOCATION", b"ANGULAR_LOCATION", b"ANGULAR_SIZE",
                b"_TOLERANCE", b"DATUM_FEATURE", b"DATUM(")


def has_semantic_pmi(path):
    """Does the file's text name any semantic PMI entity? (The XCAF parse is skipped when not.)"""
    data = Path(path).read_bytes()
    return any(marker in data for marker in _PMI_MARKERS)


def _read_document(path):
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPCAFControl import STEPCAFControl_Reader
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDocStd import TDocStd_Document

    doc = TDocStd_Document(TCollection_ExtendedString("pmi"))
    reader = STEPCAFControl_Reader()
    reader.SetGDTMode(True)
    reader.SetNameMode(True)
    reader.SetPropsMode(True)
    with quiet_occt():
        try:
            status = reader.ReadFile(os.fspath(path))
        except Exception as exc:
            raise InputError(path, f"OCCT could not parse the STEP file ({exc})") from None
        if status != IFSelect_RetDone:
            raise InputError(path, "OCCT could not parse the STEP file (syntax error or unsupported content)")
        try:
            ok = reader.Transfer(doc)
        except Exception as exc:
            raise InputError(path, f"OCCT could not read the STEP file's PMI ({exc})") from None
    if not ok:
        raise InputError(path, "OCCT could not transfer the STEP file's shapes and PMI")
    return doc


class _Targets:
    """Faces and edges a PMI label points at, as face ids and edge mid-points."""

    def __init__(self, shape_tool):
        from OCP.BRep import BRep_Builder
        from OCP.TDF import TDF_LabelSequence
        from OCP.TopAbs import TopAbs_FACE, TopAbs_SOLID
        from OCP.TopExp import TopExp, TopExp_Explorer
        from OCP.TopoDS import TopoDS_Compound
        from OCP.TopTools import TopTools_IndexedMapOfShape

        from partinspect.cad.features import face_inventory

        self.shape_tool = shape_tool
        free = TDF_LabelSequence()
        shape_tool.GetFreeShapes(free)
        # The solids alone, as load_step keeps them: faces of loose shells
        # (supplemental geometry, such as a datum's centre plane) would shift
        # the geometric face ids away from the inventory's.
        whole, builder = TopoDS_Compound(), BRep_Builder()
        builder.MakeCompound(whole)
        for i in range(1, free.Length() + 1):
            explorer = TopExp_Explorer(shape_tool.GetShape_s(free.Value(i)), TopAbs_SOLID)
            while explorer.More():
                builder.Add(whole, explorer.Current())
                explorer.Next()
        self.face_map = TopTools_IndexedMapOfShape()
        TopExp.MapShapes_s(whole, TopAbs_FACE, self.face_map)
        self.infos = face_inventory(whole)
        self.face_id = {info.shape_index: info.id for info in self.infos}
        self.by_id = {info.id: info for info in self.infos}

    def of(self, label):
        """(faces, faces2, edge mid-points, number of targets not found)."""
        from OCP.TDF import TDF_LabelSequence
        from OCP.XCAFDoc import XCAFDoc_DimTolTool

        first, second = TDF_LabelSequence(), TDF_LabelSequence()
        XCAFDoc_DimTolTool.GetRefShapeLabel_s(label, first, second)
        out, edges, missing = [], [], 0
        for seq in (first, second):
            faces = []
            for i in range(1, seq.Length() + 1):
                shape = self.shape_tool.GetShape_s(seq.Value(i))
                f, e, m = self._resolve(shape)
                faces += [x for x in f if x not in faces]
                edges += e
                missing += m
            out.append(tuple(faces))
        return out[0], out[1], tuple(edges), missing

    def _resolve(self, shape):
        from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE
        from OCP.TopExp import TopExp_Explorer

        if shape.IsNull():
            return [], [], 1
        faces, edges, missing = [], [], 0
        kind = shape.ShapeType()
        if kind == TopAbs_EDGE:
            return [], [_edge_midpoint(shape)], 0
        explorer = TopExp_Explorer(shape, TopAbs_FACE)
        while explorer.More():
            k = self.face_map.FindIndex(explorer.Current())
            if k == 0:
                missing += 1
            else:
                faces.append(self.face_id[k - 1])
            explorer.Next()
        if kind != TopAbs_FACE and not faces:
            explorer = TopExp_Explorer(shape, TopAbs_EDGE)
            while explorer.More():
                edges.append(_edge_midpoint(explorer.Current()))
                explorer.Next()
        return faces, edges, missing


def _edge_midpoint(edge):
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.TopoDS import TopoDS

    curve = BRepAdaptor_Curve(TopoDS.Edge_s(edge))
    p = curve.Value(0.5 * (curve.FirstParameter() + curve.LastParameter()))
    return np.array([p.X(), p.Y(), p.Z()])


def _snake(name):
    return re.sub(r"(?<=[a-z])(?=[A-Z])", "_", name).lower()


def _enum_tail(value, prefix):
    return value.name[len(prefix):]


_DIM_TYPES = {
    "Size_Diameter": "diameter", "Size_Radius": "radius", "Size_SphericalDiameter": "spherical_diameter",
    "Size_SphericalRadius": "spherical_radius", "Size_Thickness": "thickness", "Size_Angular": "angle",
    "Location_Angular": "angle", "Size_CurveLength": "curve_length", "Location_CurvedDistance": "curved_distance",
    "Location_Oriented": "oriented_distance", "Size_WithPath": "size_with_path", "Location_WithPath": "location_with_path",
}
_GRAPHIC_DIMS = ("CommonLabel", "DimensionPresentation")


def _dimensions(labels, targets):
    from OCP.XCAFDoc import XCAFDoc_Dimension

    raw, graphic = [], 0
    for label in labels:
        obj = XCAFDoc_Dimension.Set_s(label).GetObject()
        tail = _enum_tail(obj.GetType(), "XCAFDimTolObjects_DimensionType_")
        if tail in _GRAPHIC_DIMS:
            graphic += 1
            continue
        raw.append((label, obj, tail, targets.of(label)))
    factor = _nominal_unit(raw, targets)
    items = []
    for n, (label, obj, tail, (faces, faces2, edges, missing)) in enumerate(raw, start=1):
        dtype = _DIM_TYPES.get(tail) or ("linear_distance" if tail.startswith("Location_LinearDistance") else "unknown")
        name = _text(obj.GetSemanticName())
        notes = []
        value = float(obj.GetValue())
        if obj.IsDimWithRange():
            lower_abs, upper_abs = float(obj.GetLowerBound()), float(obj.GetUpperBound())
            value = 0.5 * (lower_abs + upper_abs) if value == 0 else value
            upper, lower = upper_abs - value, lower_abs - value
        elif obj.IsDimWithPlusMinusTolerance():
            upper, lower = float(obj.GetUpperTolValue()), -abs(float(obj.GetLowerTolValue()))
        else:
            upper = lower = None
        if obj.IsDimWithClassOfTolerance():
            notes.append("class of tolerance (ISO 286 fit) not converted to limits")
        if dtype == "unknown":
            notes.append(f"no type and no value read (the file names it {name!r})")
            value = None
        elif dtype == "angle":
            value, upper, lower = (None if v is None else math.radians(_clean(v)) for v in (value, upper, lower))
        elif factor != 1.0:
            notes.append(f"nominal {value:g} in inch (OCCT converts the limits, not the nominal) taken as "
                         f"{value * factor:.6g} mm")
            value *= factor
        if dtype in ("diameter", "radius") and value:
            note = _size_check(value, upper, lower, dtype, faces, targets)
            if note:
                notes.append(note)
        if missing:
            notes.append(f"{missing} attached face(s) not on the part's solid (supplemental geometry)")
        modifiers = tuple(_enum_tail(m, "XCAFDimTolObjects_DimensionModif_") for m in obj.GetModifiers())
        if dtype != "angle":  # angles were rounded in degrees, as the file gives them
            value, upper, lower = _clean(value), _clean(upper), _clean(lower)
        items.append(PmiItem(f"dim-{n}", "dimension", dtype, name, value, upper, lower, modifiers, (), faces, faces2,
                             edges, tuple(notes)))
    return items, graphic


def _clean(x):
    # Rounding off the float noise of unit conversions (0.12700000000050798)
    # keeps written specs readable; 1e-9 mm is far below any tolerance.
    return None if x is None else round(float(x), 9) + 0.0


def _cad_size(dtype, faces, targets):
    radii = [targets.by_id[f].radius for f in faces if targets.by_id[f].radius is not None]
    if not radii:
        return None
    return 2 * radii[0] if dtype == "diameter" else radii[0]


def _nominal_unit(raw, targets):
    """mm per unit of the dimension nominals OCCT returns: 1, or 25.4 for inch.

    OCCT 7.9 converts a dimension's limits to mm but leaves its nominal in
    the file's PMI unit. The diameters and radii tell which unit that is:
    their nominals are compared with the sizes of the cylinders they are
    attached to, and inch is taken when every one of them is nearer to its
    cylinder after scaling by 25.4 than before.
    """
    votes = []
    for _, obj, tail, (faces, _, _, _) in raw:
        dtype = _DIM_TYPES.get(tail)
        value = float(obj.GetValue())
        if dtype not in ("diameter", "radius") or value <= 0:
            continue
        size = _cad_size(dtype, faces, targets)
        if size:
            votes.append(abs(math.log(value * INCH / size)) < abs(math.log(value / size)))
    return INCH if votes and all(votes) else 1.0


def _size_check(value, upper, lower, dtype, faces, targets):
    """A note when a size's nominal differs from the CAD size by more than its tolerance."""
    size = _cad_size(dtype, faces, targets)
    if size is None:
        return None
    width = (upper - lower) if upper is not None else _SIZE_MATCH * size
    if abs(value - size) > width + 1e-9:
        return f"nominal {value:.6g} mm disagrees with the attached face's {dtype} {size:.6g} mm"
    return None


_TOL_TYPES = {"CircularityOrRoundness": "circularity"}


def _tolerances(labels, targets, text_values):
    from OCP.TDF import TDF_LabelSequence
    from OCP.XCAFDoc import XCAFDoc_Datum, XCAFDoc_DimTolTool, XCAFDoc_GeomTolerance

    used = {}
    items = []
    for n, label in enumerate(labels, start=1):
        obj = XCAFDoc_GeomTolerance.Set_s(label).GetObject()
        tail = _enum_tail(obj.GetType(), "XCAFDimTolObjects_GeomToleranceType_")
        ttype = _TOL_TYPES.get(tail) or _snake(tail)
        name = _text(obj.GetSemanticName())
        faces, faces2, edges, missing = targets.of(label)
        notes = []
        value = float(obj.GetValue())
        if value == 0:
            candidates = [v for v in text_values if v[0] == name]
            k = used.get(name, 0)
            if k < len(candidates):
                used[name] = k + 1
                value = _clean(candidates[k][2])
                if value is None:
                    notes.append("its magnitude entity is missing or not a length")
                elif value == 0:
                    notes.append("the file gives a zero tolerance")
                else:
                    notes.append("value read from the file's text (OCCT read 0 from a compound measure entity)")
                if len({c[2] for c in candidates}) > 1:
                    notes.append(f"{len(candidates)} tolerances named {name!r} with different values: "
                                 "matched by their order in the file")
            else:
                value = None
                notes.append("no tolerance value in the file")
        modifiers = [_enum_tail(m, "XCAFDimTolObjects_GeomToleranceModif_") for m in obj.GetModifiers()]
        material = _enum_tail(obj.GetMaterialRequirementModifier(), "XCAFDimTolObjects_GeomToleranceMatReqModif_")
        if material in ("M", "L"):
            modifiers.append({"M": "MMC", "L": "LMC"}[material])
        zone = _enum_tail(obj.GetTypeOfValue(), "XCAFDimTolObjects_GeomToleranceTypeValue_")
        if zone != "None":
            modifiers.append(_snake(zone) + "_zone")
        zmod = _enum_tail(obj.GetZoneModifier(), "XCAFDimTolObjects_GeomToleranceZoneModif_")
        if zmod != "None":
            modifiers.append(zmod.lower() + "_zone")
        refs = TDF_LabelSequence()
        XCAFDoc_DimTolTool.GetDatumWithObjectOfTolerLabels_s(label, refs)
        drf = []
        for i in range(1, refs.Length() + 1):
            d = XCAFDoc_Datum.Set_s(refs.Value(i)).GetObject()
            drf.append((d.GetPosition(), _text(d.GetName())))
            letter, mods = _text(d.GetName()), d.GetModifiers()
            for k in range(1, mods.Length() + 1):
                boundary = _DATUM_BOUNDARY.get(_enum_tail(mods.Value(k), "XCAFDimTolObjects_DatumSingleModif_"))
                if letter and boundary and f"datum_{letter}_{boundary}" not in modifiers:
                    modifiers.append(f"datum_{letter}_{boundary}")
                    notes.append(f"datum {letter} at {boundary}: the toleranced features may shift as a pattern "
                                 "within the datum feature's departure from that boundary")
        datums = tuple(dict.fromkeys(letter for _, letter in sorted(drf) if letter))
        if missing:
            notes.append(f"{missing} attached face(s) not on the part's solid (supplemental geometry)")
        items.append(PmiItem(f"gtol-{n}", "tolerance", ttype, name, _clean(value), None, None, tuple(modifiers), datums, faces,
                             faces2, edges, tuple(notes)))
    return items


# A datum feature of size referenced at its maximum or least material
# boundary (ASME Y14.5 MMB/LMB, ISO 2692's (M)/(L) after a datum letter).
_DATUM_BOUNDARY = {"MaximumMaterialRequirement": "MMB", "LeastMaterialRequirement": "LMB"}


def _datums(labels, targets):
    from OCP.XCAFDoc import XCAFDoc_Datum

    merged = {}
    for label in labels:
        obj = XCAFDoc_Datum.Set_s(label).GetObject()
        letter = _text(obj.GetName())
        faces, _, edges, _ = targets.of(label)
        entry = merged.setdefault(letter, {"faces": [], "edges": []})
        entry["faces"] += [f for f in faces if f not in entry["faces"]]
        entry["edges"] += list(edges)
    items = []
    for letter in sorted(merged):
        entry = merged[letter]
        notes = () if entry["faces"] or entry["edges"] else ("attached to no face or edge in the file",)
        items.append(PmiItem(f"datum-{letter}", "datum", "datum", letter, datums=(letter,),
                             faces=tuple(entry["faces"]), edges=tuple(entry["edges"]), notes=notes))
    return items


def _text(handle):
    # OCP hands a null handle over as None.
    return "" if handle is None else handle.ToCString()
