"""The feature inventory of a CAD part: its straight and circular edges.

A *feature* is an edge the cameras can see and the vision chain can fit: a
straight ``line``, a full ``circle`` or a circular ``arc``. Features and
faces get ids (``line-3``, ``circle-1``, ``arc-2``, ``face-7``) that depend
on the geometry alone, not on the order in which the STEP file or OCCT lists
entities, so that the tolerance spec can name them. Each kind is numbered in
the order of a geometric key (lines by midpoint, length, direction; circles
and arcs by centre, radius, normal, arcs then by midpoint; faces by
centroid, area, surface type), compared within 1e-6 mm so that rounding in a
re-exported file does not reorder them.

Only LINE and CIRCLE edges become features (others are counted in
``Inventory.skipped_edges``), and neither seams nor degenerated edges.
CIRCLE edges on one circle are merged where their ranges touch: into one
``circle`` when they close the turn (many CAD systems split a rim into two
half arcs), else one ``arc`` per run (`_circle_features`). Collinear lines
stay separate features.

Conventions (part frame = STEP frame, mm, radians): a circle's ``normal``
has the sign `canonical_direction` gives, reproducible but meaningless;
angles run counter-clockwise about it from ``reference_direction(normal)``
(the world x axis projected into the plane, or y when |n_x| > 0.9), built
from the normal alone so that the vision side can rebuild it; an arc runs
from ``angle_start`` in [0, 2 pi) to ``angle_end`` in (angle_start,
angle_start + 2 pi); a line's ``start`` is the end that sorts first by x,
then y, then z.
"""

import math
from dataclasses import dataclass, field
from functools import cmp_to_key
from types import MappingProxyType
from typing import Mapping

import numpy as np

from partinspect.frames import orthonormal_frame

__all__ = [
    "AmbiguousFeatureError",
    "FaceInfo",
    "Feature",
    "Inventory",
    "canonical_direction",
    "cylinder_sides",
    "face_inventory",
    "faces_of",
    "inventory",
    "nearest_feature",
    "occ_edges",
]

LENGTH_TOL = 1e-6  # mm: positions, lengths and radii equal within this are equal
DIRECTION_TOL = 1e-6  # unit vectors: |n1 x n2| below this are parallel
SMOOTH_ANGLE = 1e-3  # rad: faces meeting at less than this form no crease

_CURVE_NAMES = {
    "GeomAbs_Line": "line",
    "GeomAbs_Circle": "circle",
    "GeomAbs_Ellipse": "ellipse",
    "GeomAbs_Hyperbola": "hyperbola",
    "GeomAbs_Parabola": "parabola",
    "GeomAbs_BezierCurve": "bezier",
    "GeomAbs_BSplineCurve": "bspline",
    "GeomAbs_OffsetCurve": "offset",
    "GeomAbs_OtherCurve": "other",
}
_SURFACE_NAMES = {
    "GeomAbs_Plane": "plane",
    "GeomAbs_Cylinder": "cylinder",
    "GeomAbs_Cone": "cone",
    "GeomAbs_Sphere": "sphere",
    "GeomAbs_Torus": "torus",
    "GeomAbs_BezierSurface": "bezier",
    "GeomAbs_BSplineSurface": "bspline",
    "GeomAbs_SurfaceOfRevolution": "revolution",
    "GeomAbs_SurfaceOfExtrusion": "extrusion",
    "GeomAbs_OffsetSurface": "offset",
    "GeomAbs_OtherSurface": "other",
}
_SURFACE_RANK = {name: i for i, name in enumerate(_SURFACE_NAMES.values())}


class AmbiguousFeatureError(ValueError):
    """Two or more features are equally near a selector point."""


@dataclass(frozen=True, eq=False)
class FaceInfo:
    """One face of the part's boundary.

    Attributes
    ----------
    id : str
        ``"face-N"``; N - 1 is the face's position in ``Inventory.faces``.
    surface : str
        ``"plane"``, ``"cylinder"``, ``"cone"``, ``"sphere"``, ``"torus"``,
        ``"bspline"``, ``"bezier"``, ``"revolution"``, ``"extrusion"``,
        ``"offset"`` or ``"other"``.
    area : float
        mm^2.
    centroid : ndarray, shape (3,)
        Centre of area, part frame, mm (need not lie on the face).
    normal : ndarray, shape (3,) or None
        Planes only: the outward unit normal (pointing out of the material).
    axis_point : ndarray, shape (3,) or None
        Cylinders, cones, tori: the point of the surface's axis nearest to the
        centroid; spheres: the centre. mm.
    axis_direction : ndarray, shape (3,) or None
        Cylinders, cones, tori: the axis as a unit vector, sign by
        `canonical_direction`.
    radius : float or None
        Cylinders and spheres: the radius, mm.
    convex : bool or None
        Cylinders, cones, spheres: True when the material is on the axis side
        (a shaft, boss or ball), False when it is outside (a hole or bore).
    shape_index : int
        0-based position of the face in ``shape.Faces()`` of the shape the
        inventory was made from. Not stable across files; use ``id``.
    """

    id: str
    surface: str
    area: float
    centroid: np.ndarray
    normal: np.ndarray | None = None
    axis_point: np.ndarray | None = None
    axis_direction: np.ndarray | None = None
    radius: float | None = None
    convex: bool | None = None
    shape_index: int = -1

    def to_dict(self):
        d = {"id": self.id, "surface": self.surface, "area": float(self.area), "centroid": _list(self.centroid)}
        for name in ("normal", "axis_point", "axis_direction"):
            value = getattr(self, name)
            if value is not None:
                d[name] = _list(value)
        if self.radius is not None:
            d["radius"] = float(self.radius)
        if self.convex is not None:
            d["convex"] = bool(self.convex)
        return d


@dataclass(frozen=True, eq=False)
class Feature:
    """A straight or circular edge of the part (part frame, mm, radians).

    Attributes
    ----------
    id : str
        ``"line-N"``, ``"circle-N"`` or ``"arc-N"``.
    kind : {"line", "circle", "arc"}
    length : float
        Length of the edge, mm (2 pi r for a circle).
    faces : tuple of str
        Ids of the faces this edge bounds (usually two), in id order.
    start, end : ndarray, shape (3,) or None
        Lines and arcs: the end points (see the module notes for their
        order). None for circles.
    center : ndarray, shape (3,) or None
        Circles and arcs.
    normal : ndarray, shape (3,) or None
        Circles and arcs: unit normal of the circle's plane.
    radius : float or None
        Circles and arcs, mm.
    angle_start, angle_end : float or None
        Arcs: the angular range, radians, counter-clockwise about ``normal``
        from ``reference_direction(normal)``.
    smooth : bool
        True when the faces on both sides meet tangentially (within 1e-3 rad
        at the edge's middle), as where a slot's flat side runs into its
        round end. Such an edge is no crease and shows no image edge of its
        own; for merged circles, True only if every piece is smooth.
    edge_indices : tuple of int
        The OCCT edges merged into this feature, as 0-based positions in the
        shape's edge map (``TopExp.MapShapes(shape, TopAbs_EDGE)``; this map
        holds degenerated edges too, which ``shape.Edges()`` leaves out, so
        index `occ_edges`, not ``shape.Edges()``). Not stable across files;
        use ``id``.
    """

    id: str
    kind: str
    length: float
    faces: tuple
    start: np.ndarray | None = None
    end: np.ndarray | None = None
    center: np.ndarray | None = None
    normal: np.ndarray | None = None
    radius: float | None = None
    angle_start: float | None = None
    angle_end: float | None = None
    smooth: bool = False
    edge_indices: tuple = ()

    @property
    def n_edges(self):
        """Number of OCCT edges merged into this feature."""
        return len(self.edge_indices)

    @property
    def direction(self):
        """Lines: unit vector from ``start`` to ``end``."""
        if self.kind != "line":
            raise AttributeError(f"{self.id} is a {self.kind}, it has no direction")
        d = self.end - self.start
        return d / np.linalg.norm(d)

    def frame(self):
        """Circles and arcs: the (3, 3) matrix whose rows are x, y, normal.

        Angles are measured in this frame: a point at angle t is
        ``center + radius * (cos t * x + sin t * y)``.
        """
        if self.kind == "line":
            raise AttributeError(f"{self.id} is a line, it has no circle frame")
        return orthonormal_frame(self.normal)

    def to_dict(self):
        d = {"id": self.id, "kind": self.kind, "length": float(self.length), "faces": list(self.faces)}
        for name in ("start", "end", "center", "normal"):
            value = getattr(self, name)
            if value is not None:
                d[name] = _list(value)
        for name in ("radius", "angle_start", "angle_end"):
            value = getattr(self, name)
            if value is not None:
                d[name] = float(value)
        d["smooth"] = bool(self.smooth)
        d["n_edges"] = self.n_edges
        return d


@dataclass(frozen=True, eq=False)
class Inventory:
    """All features and faces of a part, with counts of what was left out.

    Attributes
    ----------
    features : tuple of Feature
        Lines, then circles, then arcs, each in id order.
    faces : tuple of FaceInfo
        In id order: ``faces[i].id == f"face-{i + 1}"``.
    edge_counts : Mapping[str, int]
        Every distinct edge of the shape that is not degenerated, by curve
        type (``"line"``, ``"circle"``, ``"bspline"``, ...), seams included:
        the count ``len(shape.Edges())`` splits into (cadquery leaves
        degenerated edges out of ``Edges()``).
    seam_edges : Mapping[str, int]
        Seam edges by curve type (not features).
    degenerated_edges : int
        Degenerated edges (not features).
    skipped_edges : Mapping[str, int]
        Edges that would be features but for their curve type, by type.
    """

    features: tuple
    faces: tuple
    edge_counts: Mapping[str, int] = field(default_factory=lambda: MappingProxyType({}))
    seam_edges: Mapping[str, int] = field(default_factory=lambda: MappingProxyType({}))
    degenerated_edges: int = 0
    skipped_edges: Mapping[str, int] = field(default_factory=lambda: MappingProxyType({}))

    def __post_init__(self):
        for name in ("edge_counts", "seam_edges", "skipped_edges"):
            object.__setattr__(self, name, MappingProxyType(dict(getattr(self, name))))
        index = {f.id: f for f in self.features}
        index.update({f.id: f for f in self.faces})
        object.__setattr__(self, "_index", index)

    def __reduce__(self):
        # MappingProxyType does not pickle: plain dicts go in, __post_init__ wraps them again.
        return (Inventory, (self.features, self.faces, dict(self.edge_counts), dict(self.seam_edges),
                            self.degenerated_edges, dict(self.skipped_edges)))

    def __getitem__(self, id):
        """The Feature or FaceInfo with this id; KeyError if there is none."""
        try:
            return self._index[id]
        except KeyError:
            raise KeyError(f"no feature or face {id!r} in this part") from None

    def __contains__(self, id):
        return id in self._index

    def of_kind(self, kind):
        """The features of one kind, ``"line"``, ``"circle"`` or ``"arc"``."""
        return tuple(f for f in self.features if f.kind == kind)

    def to_dict(self):
        """JSON-ready: plain lists, floats, ints and strings."""
        counts = {k: 0 for k in ("line", "circle", "arc")}
        for f in self.features:
            counts[f.kind] += 1
        return {
            "schema": "inventory/1",
            "units": "mm",
            "counts": counts,
            "features": [f.to_dict() for f in self.features],
            "faces": [f.to_dict() for f in self.faces],
            "edges": dict(sorted(self.edge_counts.items())),
            "seams": dict(sorted(self.seam_edges.items())),
            "degenerated": int(self.degenerated_edges),
            "skipped": dict(sorted(self.skipped_edges.items())),
        }


def faces_of(inv, feature_ids):
    """The faces (``FaceInfo``) the features bound, those ``inv`` holds, in the features' order."""
    return [inv[x] for fid in feature_ids for x in inv[fid].faces if x in inv]


def cylinder_sides(faces):
    """The material sides of the cylinders among ``faces``: the set of their ``FaceInfo.convex``.

    ``{False}`` one hole, ``{True}`` one boss (a STEP file often splits one
    wall into half cylinders, which share a side); empty, no cylinder; two
    elements, a hole and a boss both; None in it, a cylinder whose side is
    unknown. What depends on a size's side (a broken rim's correction, a
    material condition's bonus) asks for exactly one.
    """
    return {f.convex for f in faces if f.surface == "cylinder"}


def canonical_direction(v):
    """The sign of a direction that does not depend on how it was stored.

    Parameters
    ----------
    v : array_like, shape (3,)
        A non-zero direction.

    Returns
    -------
    ndarray, shape (3,)
        ``v`` normalised and flipped if needed so that its first component
        with absolute value above 1e-9 is positive.
    """
    v = np.asarray(v, dtype=float)
    v = v / np.linalg.norm(v)
    for c in v:
        if abs(c) > 1e-9:
            return v if c > 0 else -v
    return v


def inventory(shape):
    """List the line, circle and arc features and the faces of a part.

    Parameters
    ----------
    shape : cadquery.Shape
        A solid or compound in its part frame, mm (as `load_step` returns).

    Returns
    -------
    Inventory
        See the module notes for what becomes a feature and how ids are
        given.
    """
    from OCP.BRep import BRep_Tool
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE
    from OCP.TopExp import TopExp
    from OCP.TopoDS import TopoDS
    from OCP.TopTools import TopTools_IndexedDataMapOfShapeListOfShape, TopTools_IndexedMapOfShape

    wrapped = getattr(shape, "wrapped", shape)
    face_map = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(wrapped, TopAbs_FACE, face_map)
    edge_map = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(wrapped, TopAbs_EDGE, edge_map)
    ancestors = TopTools_IndexedDataMapOfShapeListOfShape()
    TopExp.MapShapesAndAncestors_s(wrapped, TopAbs_EDGE, TopAbs_FACE, ancestors)

    face_infos = face_inventory(wrapped)
    face_id = {info.shape_index: info.id for info in face_infos}

    edge_counts, seams, skipped = {}, {}, {}
    degenerated = 0
    lines, circle_edges = [], []
    for i in range(1, edge_map.Extent() + 1):
        edge = TopoDS.Edge_s(edge_map.FindKey(i))
        if BRep_Tool.Degenerated_s(edge):  # a cone's apex: no curve at all
            degenerated += 1
            continue
        curve = BRepAdaptor_Curve(edge)
        ctype = _CURVE_NAMES.get(curve.GetType().name, "other")
        edge_counts[ctype] = edge_counts.get(ctype, 0) + 1
        adjacent = []  # (shape index, oriented face)
        if ancestors.Contains(edge):
            for face in ancestors.FindFromKey(edge):
                face = TopoDS.Face_s(face)
                k = face_map.FindIndex(face) - 1
                if all(k != j for j, _ in adjacent):
                    adjacent.append((k, face))
        if any(BRep_Tool.IsClosed_s(edge, face) for _, face in adjacent):
            seams[ctype] = seams.get(ctype, 0) + 1
            continue
        if ctype not in ("line", "circle"):
            skipped[ctype] = skipped.get(ctype, 0) + 1
            continue
        record = {
            "index": i - 1,
            "faces": sorted((face_id[k] for k, _ in adjacent), key=_id_number),
            "smooth": _is_smooth(edge, [f for _, f in adjacent]),
        }
        if ctype == "line":
            lines.append(_line_record(curve, record))
        else:
            circle_edges.append(_circle_record(curve, edge, record))

    features = _number("line", lines, _line_key) + _circle_features(circle_edges)
    return Inventory(
        features=tuple(features),
        faces=tuple(face_infos),
        edge_counts=MappingProxyType(dict(sorted(edge_counts.items()))),
        seam_edges=MappingProxyType(dict(sorted(seams.items()))),
        degenerated_edges=degenerated,
        skipped_edges=MappingProxyType(dict(sorted(skipped.items()))),
    )


def face_inventory(shape):
    """The faces of a part with their ids, without the edge features.

    Parameters
    ----------
    shape : cadquery.Shape or OCP.TopoDS.TopoDS_Shape

    Returns
    -------
    tuple of FaceInfo
        The same as ``inventory(shape).faces``, for less work.
    """
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp
    from OCP.TopoDS import TopoDS
    from OCP.TopTools import TopTools_IndexedMapOfShape

    face_map = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(getattr(shape, "wrapped", shape), TopAbs_FACE, face_map)
    return tuple(_face_infos([TopoDS.Face_s(face_map.FindKey(i)) for i in range(1, face_map.Extent() + 1)]))


def occ_edges(shape):
    """The OCCT edges of a shape in the order ``Feature.edge_indices`` uses.

    Parameters
    ----------
    shape : cadquery.Shape or OCP.TopoDS.TopoDS_Shape

    Returns
    -------
    list of OCP.TopoDS.TopoDS_Edge
        Every distinct edge, degenerated ones included, in the order of
        ``TopExp.MapShapes(shape, TopAbs_EDGE)``.
    """
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp
    from OCP.TopoDS import TopoDS
    from OCP.TopTools import TopTools_IndexedMapOfShape

    edge_map = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(getattr(shape, "wrapped", shape), TopAbs_EDGE, edge_map)
    return [TopoDS.Edge_s(edge_map.FindKey(i)) for i in range(1, edge_map.Extent() + 1)]


def nearest_feature(inv, point, tie_tolerance=LENGTH_TOL):
    """The feature nearest to a point: the tolerance spec's ``at:`` selector.

    Parameters
    ----------
    inv : Inventory
    point : array_like, shape (3,)
        Part frame, mm.
    tie_tolerance : float
        mm. If another feature is no farther than the nearest plus this, the
        choice is ambiguous.

    Returns
    -------
    feature : Feature
    distance : float
        Shortest distance from ``point`` to the feature's edge (the segment,
        the full circle or the arc), mm.

    Raises
    ------
    AmbiguousFeatureError
        (a ValueError) when two or more features are equally near, as at a
        corner where edges meet; the message names them. Pick a point along
        the wanted edge instead.
    ValueError
        If the inventory has no features or the point is not 3 finite
        numbers.
    """
    p = np.asarray(point, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"point must be 3 finite numbers (x, y, z in mm), got {point!r}")
    if not inv.features:
        raise ValueError("the part has no line, circle or arc features")
    d = np.array([_distance(f, p) for f in inv.features])
    order = np.argsort(d, kind="stable")
    best = order[0]
    tied = [inv.features[i].id for i in order if d[i] <= d[best] + tie_tolerance]
    if len(tied) > 1:
        raise AmbiguousFeatureError(
            f"point {_fmt(p)} is {d[best]:.6g} mm from each of {', '.join(tied)}; give a point nearer to one edge"
        )
    return inv.features[best], float(d[best])


# --- faces -----------------------------------------------------------------


def _face_infos(faces):
    """FaceInfo records in id order, from OCCT faces in shape order."""
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps

    raw = []
    for k, face in enumerate(faces):
        props = GProp_GProps()
        BRepGProp.SurfaceProperties_s(face, props)
        area = props.Mass()
        centroid = _xyz(props.CentreOfMass())
        surf = BRepAdaptor_Surface(face)
        surface = _SURFACE_NAMES.get(surf.GetType().name, "other")
        extra = _surface_details(face, surf, surface, centroid)
        raw.append(dict(surface=surface, area=area, centroid=centroid, shape_index=k, **extra))
    keys = [(*r["centroid"], r["area"], _SURFACE_RANK[r["surface"]]) for r in raw]
    tols = [(LENGTH_TOL,) * 3 + (LENGTH_TOL * max(1.0, r["area"]), 0.5) for r in raw]
    order = _tolerant_order(keys, tols)
    infos = []
    for n, i in enumerate(order, start=1):
        r = raw[i]
        for name in ("centroid", "normal", "axis_point", "axis_direction"):
            if r.get(name) is not None:
                r[name] = _frozen(r[name])
        infos.append(FaceInfo(id=f"face-{n}", **r))
    return infos


def _surface_details(face, surf, surface, centroid):
    """Normal, axis, radius and convexity where the surface type has them."""
    out = {}
    if surface == "plane":
        out["normal"] = _outward_normal(face, surf)
    elif surface in ("cylinder", "cone", "torus"):
        geom = {"cylinder": surf.Cylinder, "cone": surf.Cone, "torus": surf.Torus}[surface]()
        axis = geom.Axis()
        origin, direction = _xyz(axis.Location()), canonical_direction(_xyz(axis.Direction()))
        foot = origin + ((centroid - origin) @ direction) * direction
        out["axis_point"], out["axis_direction"] = foot, direction
        if surface == "cylinder":
            out["radius"] = geom.Radius()
        if surface != "torus":
            out["convex"] = _points_away_from_axis(face, surf, foot, direction)
    elif surface == "sphere":
        sphere = surf.Sphere()
        centre = _xyz(sphere.Location())
        out["axis_point"], out["radius"] = centre, sphere.Radius()
        out["convex"] = _points_away_from_axis(face, surf, centre, None)
    return out


def _surface_point_normal(face, surf):
    """A point of the face's surface and its outward normal, at the UV middle."""
    from OCP.BRepLProp import BRepLProp_SLProps
    from OCP.BRepTools import BRepTools
    from OCP.TopAbs import TopAbs_REVERSED

    u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
    props = BRepLProp_SLProps(surf, 0.5 * (u0 + u1), 0.5 * (v0 + v1), 1, 1e-9)
    if not props.IsNormalDefined():
        return None, None
    n = _xyz(props.Normal())
    if face.Orientation() == TopAbs_REVERSED:
        n = -n
    return _xyz(props.Value()), n


def _outward_normal(face, surf):
    _, n = _surface_point_normal(face, surf)
    return n


def _points_away_from_axis(face, surf, axis_point, axis_direction):
    p, n = _surface_point_normal(face, surf)
    if p is None:
        return None
    radial = p - axis_point
    if axis_direction is not None:
        radial = radial - (radial @ axis_direction) * axis_direction
    return bool(radial @ n > 0)


# --- edges -----------------------------------------------------------------


def _is_smooth(edge, faces):
    """Do the two faces of an edge meet tangentially at its middle?"""
    if len(faces) != 2:
        return False
    from OCP.BRepAdaptor import BRepAdaptor_Curve2d, BRepAdaptor_Surface
    from OCP.BRepLProp import BRepLProp_SLProps
    from OCP.TopAbs import TopAbs_REVERSED

    normals = []
    for face in faces:
        try:
            pcurve = BRepAdaptor_Curve2d(edge, face)
            uv = pcurve.Value(0.5 * (pcurve.FirstParameter() + pcurve.LastParameter()))
            props = BRepLProp_SLProps(BRepAdaptor_Surface(face), uv.X(), uv.Y(), 1, 1e-9)
        except Exception:  # no pcurve: cannot tell, so call it a crease
            return False
        if not props.IsNormalDefined():
            return False
        n = _xyz(props.Normal())
        normals.append(-n if face.Orientation() == TopAbs_REVERSED else n)
    return bool(np.arccos(np.clip(normals[0] @ normals[1], -1.0, 1.0)) < SMOOTH_ANGLE)


def _line_record(curve, record):
    a = _xyz(curve.Value(curve.FirstParameter()))
    b = _xyz(curve.Value(curve.LastParameter()))
    if _tolerant_cmp(tuple(b), tuple(a), (LENGTH_TOL,) * 3) < 0:
        a, b = b, a
    record.update(start=a, end=b, length=float(np.linalg.norm(b - a)))
    return record


def _line_key(r):
    mid = 0.5 * (r["start"] + r["end"])
    direction = (r["end"] - r["start"]) / max(r["length"], 1e-300)
    return (*mid, r["length"], *direction), (LENGTH_TOL,) * 4 + (DIRECTION_TOL,) * 3


def _circle_record(curve, edge, record):
    """A CIRCLE edge as (centre, canonical normal, radius, ccw angular range)."""
    from OCP.BRep import BRep_Tool

    circ = curve.Circle()
    c = _xyz(circ.Location())
    n = canonical_direction(_xyz(circ.Axis().Direction()))
    r = circ.Radius()
    t0, t1 = curve.FirstParameter(), curve.LastParameter()
    # A circle's parameter is its angle, so the span survives any placement;
    # the sense of travel is read from points, which also covers mirrored
    # locations where the stored frame is left-handed.
    span = min(t1 - t0, 2 * math.pi)
    x, y = orthonormal_frame(n)[:2]
    p0 = _xyz(curve.Value(t0)) - c
    p1 = _xyz(curve.Value(t0 + min(0.5 * span, 0.5 * math.pi))) - c
    ccw = np.cross(p0, p1) @ n > 0
    a0 = math.atan2(p0 @ y, p0 @ x)
    start = a0 if ccw else a0 - span
    record.update(
        center=c,
        normal=n,
        radius=r,
        start_angle=start % (2 * math.pi),
        span=span,
        tolerance=BRep_Tool.Tolerance_s(edge),
    )
    return record


def _circle_features(edges):
    """Merge co-circular CIRCLE edges into circle and arc features.

    Pieces are one circle when radii and centres agree within `_merge_tol` and
    the normals are parallel up to sign (``r |n1 x n2| <= t``); they join where
    the gap between their angular ranges is at most t. The merged centre and
    radius are the span-weighted means of the pieces'.
    """
    groups = _cocircular_groups(edges)
    circles, arcs = [], []
    for members in groups:
        members = sorted(members, key=lambda m: (m["start_angle"], m["span"]))
        weights = np.array([m["span"] for m in members])
        c = weights @ np.array([m["center"] for m in members]) / weights.sum()
        r = float(weights @ np.array([m["radius"] for m in members]) / weights.sum())
        n = members[0]["normal"]
        gap = _merge_tol(r, max(m["tolerance"] for m in members)) / r
        for run, lo, hi in _angular_runs(members, gap):
            merged = {
                "index": tuple(sorted(m["index"] for m in run)),
                "faces": sorted({f for m in run for f in m["faces"]}, key=_id_number),
                "smooth": all(m["smooth"] for m in run),
                "center": c,
                "normal": n,
                "radius": r,
            }
            if lo is None:
                merged["length"] = 2 * math.pi * r
                circles.append(merged)
            else:
                frame = orthonormal_frame(n)
                merged.update(
                    angle_start=lo,
                    angle_end=hi,
                    length=r * (hi - lo),
                    start=_on_circle(c, r, frame, lo),
                    end=_on_circle(c, r, frame, hi),
                    mid=_on_circle(c, r, frame, 0.5 * (lo + hi)),
                )
                arcs.append(merged)
    return _number("circle", circles, _circle_key) + _number("arc", arcs, _arc_key)


def _cocircular_groups(edges):
    """Partition circle edges into groups lying on one geometric circle."""
    groups, centres, normals, radii, tols = [], [], [], [], []
    for e in edges:
        if groups:
            C, N, R, T = np.array(centres), np.array(normals), np.array(radii), np.array(tols)
            t = _merge_tol(np.maximum(R, e["radius"]), np.maximum(T, e["tolerance"]))
            same = (
                (np.abs(R - e["radius"]) <= t)
                & (np.linalg.norm(C - e["center"], axis=1) <= t)
                & (R * np.linalg.norm(np.cross(N, e["normal"]), axis=1) <= t)
            )
            hit = np.flatnonzero(same)
            if hit.size:
                groups[hit[0]].append(e)
                continue
        groups.append([e])
        centres.append(e["center"])
        normals.append(e["normal"])
        radii.append(e["radius"])
        tols.append(e["tolerance"])
    return groups


def _merge_tol(radius, edge_tolerance):
    """Length within which two circle pieces are the same circle, mm.

    ``1e-6 max(r, 1 mm) + 2 max(edge tolerances)``: the edge tolerances are
    OCCT's, the file's own statement of how far apart its geometry may be and
    still meet, so a file written with a coarse uncertainty still closes its
    rims.
    """
    return LENGTH_TOL * np.maximum(radius, 1.0) + 2 * edge_tolerance


def _angular_runs(members, gap):
    """Connected runs of angular intervals on one circle.

    Yields ``(edges, lo, hi)``: ``lo = hi = None`` when the run closes the
    full turn, else the run's range, lo in [0, 2 pi), hi in (lo, lo + 2 pi].
    """
    two_pi = 2 * math.pi
    items = sorted(members, key=lambda m: (m["start_angle"], -m["span"]))
    if any(m["span"] >= two_pi - gap for m in items):
        yield items, None, None
        return
    runs = []  # [members, lo, hi] with hi possibly beyond 2 pi
    for m in items:
        lo, hi = m["start_angle"], m["start_angle"] + m["span"]
        if runs and lo <= runs[-1][2] + gap:
            runs[-1][0].append(m)
            runs[-1][2] = max(runs[-1][2], hi)
        else:
            runs.append([[m], lo, hi])
    # The last run may wrap past 2 pi into the first.
    if len(runs) > 1 and runs[-1][2] >= runs[0][1] + two_pi - gap:
        last = runs.pop()
        runs[0] = [last[0] + runs[0][0], last[1], max(last[2], runs[0][2] + two_pi)]
    for run_members, lo, hi in runs:
        if hi - lo >= two_pi - gap:
            yield run_members, None, None
        else:
            yield run_members, lo, hi


def _circle_key(r):
    return (*r["center"], r["radius"], *r["normal"]), (LENGTH_TOL,) * 4 + (DIRECTION_TOL,) * 3


def _arc_key(r):
    return (*r["center"], r["radius"], *r["normal"], *r["mid"]), (LENGTH_TOL,) * 4 + (DIRECTION_TOL,) * 3 + (
        LENGTH_TOL,
    ) * 3


def _number(kind, records, key):
    """Features of one kind with ids in the order of a geometric key."""
    keyed = [key(r) for r in records]
    order = _tolerant_order([k for k, _ in keyed], [t for _, t in keyed])
    out = []
    for n, i in enumerate(order, start=1):
        r = records[i]
        index = r["index"] if isinstance(r["index"], tuple) else (r["index"],)
        geometry = {
            name: _frozen(r[name]) if isinstance(r.get(name), np.ndarray) else r.get(name)
            for name in ("start", "end", "center", "normal")
        }
        out.append(
            Feature(
                id=f"{kind}-{n}",
                kind=kind,
                length=float(r["length"]),
                faces=tuple(r["faces"]),
                radius=None if r.get("radius") is None else float(r["radius"]),
                angle_start=None if r.get("angle_start") is None else float(r["angle_start"]),
                angle_end=None if r.get("angle_end") is None else float(r["angle_end"]),
                smooth=bool(r["smooth"]),
                edge_indices=index,
                **geometry,
            )
        )
    return out


# --- distances -------------------------------------------------------------


def _distance(f, p):
    """Shortest distance from point p (3,) to the feature's edge, mm."""
    if f.kind == "line":
        d = f.end - f.start
        t = np.clip((p - f.start) @ d / (d @ d), 0.0, 1.0)
        return float(np.linalg.norm(p - (f.start + t * d)))
    x, y, n = orthonormal_frame(f.normal)
    v = p - f.center
    h = v @ n
    u, w = v @ x, v @ y
    rho = math.hypot(u, w)
    to_circle = math.hypot(h, rho - f.radius)
    if f.kind == "circle":
        return to_circle
    angle = math.atan2(w, u) % (2 * math.pi)
    if rho > 0 and (
        f.angle_start <= angle <= f.angle_end or f.angle_start <= angle + 2 * math.pi <= f.angle_end
    ):
        return to_circle
    return float(min(np.linalg.norm(p - f.start), np.linalg.norm(p - f.end)))


# --- small helpers ---------------------------------------------------------


def _on_circle(c, r, frame, angle):
    return c + r * (math.cos(angle) * frame[0] + math.sin(angle) * frame[1])


def _tolerant_cmp(a, b, tols):
    for x, y, t in zip(a, b, tols):
        if abs(x - y) > t:
            return -1 if x < y else 1
    return 0


def _tolerant_order(keys, tols):
    """Indices sorting ``keys`` lexicographically, equal within ``tols``.

    A plain sort first makes the result independent of the input order
    whenever the tolerant comparison is consistent; the stable tolerant sort
    then keeps noise below the tolerance from reordering.
    """
    exact = sorted(range(len(keys)), key=lambda i: keys[i])
    return sorted(exact, key=cmp_to_key(lambda i, j: _tolerant_cmp(keys[i], keys[j], _pairwise_tol(tols, i, j))))


def _pairwise_tol(tols, i, j):
    return tuple(max(a, b) for a, b in zip(tols[i], tols[j]))


def _id_number(fid):
    return int(fid.rsplit("-", 1)[1])


def _xyz(p):
    return np.array([p.X(), p.Y(), p.Z()], dtype=float)


def _frozen(a):
    a = np.array(a, dtype=float) + 0.0  # no negative zeros in the output
    a.flags.writeable = False
    return a


def _list(a):
    return [float(v) for v in a]


def _fmt(p):
    return "(" + ", ".join(f"{v:.6g}" for v in p) + ")"
