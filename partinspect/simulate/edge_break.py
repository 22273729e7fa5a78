"""Broken edges: the rendered solid's outer edges rounded or chamfered, as machined.

A machined part has no razor-sharp edge: deburring leaves every outer edge
rounded or chamfered by a tenth of a millimetre or so (ISO 13715 calls it
an external edge with removal, 0.05-0.3 mm being usual). The STEP model
stays sharp; only the solid that is rendered is broken.

Every *convex* edge (an external edge of ISO 13715, where the faces meet at
less than 180 degrees of material: a box's edges, a hole's rims) gets a
fillet of radius R or a symmetric chamfer of leg C, built by OCCT's
``BRepFilletAPI_MakeFillet`` / ``BRepFilletAPI_MakeChamfer`` on the loaded
shape. Concave (internal) edges and edges between tangent faces are left as
they are. Where OCCT cannot break all the edges at once (a face narrower
than the break, a corner it cannot blend) the edges are tried one by one:
each that breaks alone is kept, then the kept set is built together, and if
that still fails, edges are added one at a time in their map order while
the build succeeds. The edges left sharp are reported.

References
----------
.. [1] ISO 13715:2019 Technical product documentation - Edges of undefined
       shape - Indication and dimensioning.
.. [2] Open CASCADE Technology 7.7, Modeling Algorithms user guide:
       fillets and chamfers (BRepFilletAPI).
"""

from dataclasses import dataclass

__all__ = ["EdgeBreak", "parse_edge_break", "convex_edges", "break_edges", "mesh_min_size"]

MAX_SIZE = 10.0
"""Largest break accepted, mm."""


@dataclass(frozen=True)
class EdgeBreak:
    """How the outer edges are broken.

    Attributes
    ----------
    kind : {"fillet", "chamfer"}
    size : float
        Fillet radius or chamfer leg, mm.
    """

    kind: str
    size: float


def parse_edge_break(text):
    """``R`` or ``R0.1`` (fillet radius) or ``C0.2`` (chamfer leg), mm.

    Raises
    ------
    ValueError
        Not of that form, or a size not in (0, 10] mm.
    """
    t = str(text).strip()
    kind = "chamfer" if t[:1] in ("C", "c") else "fillet"
    number = t[1:] if t[:1] in ("C", "c", "R", "r") else t
    try:
        size = float(number)
    except ValueError:
        raise ValueError(f"expected R (a fillet radius, mm), R0.1 or C0.2 (a chamfer), got {text!r}") from None
    if not 0 < size <= MAX_SIZE:
        raise ValueError(f"the edge break must be in (0, {MAX_SIZE:g}] mm, got {text!r}")
    return EdgeBreak(kind, size)


def mesh_min_size(spec):
    """Shortest mesh segment for a broken solid, mm: an eighth of the break.

    BRepMesh's angular deflection, fine enough to keep circles round, would
    otherwise split a fillet's tiny radius into hundreds of facets (a rim's
    torus into most of a million triangles); an eighth of R still turns a
    fillet's quarter circle through steps of at most 1/8 rad.
    """
    return spec.size / 8.0


def convex_edges(shape):
    """Indices and edges of a solid's convex edges.

    Parameters
    ----------
    shape : cadquery.Shape or TopoDS_Shape

    Returns
    -------
    convex : list of (int, TopoDS_Edge)
        0-based positions in ``TopExp.MapShapes(shape, TopAbs_EDGE)`` (the
        order of :func:`partinspect.cad.features.occ_edges`).
    counts : dict
        Edges by how their faces meet: ``convex``, ``concave``,
        ``tangent`` and ``other`` (seams, free or degenerated edges).
    """
    from OCP.BRep import BRep_Tool
    from OCP.ChFi3d import ChFi3d
    from OCP.ChFiDS import ChFiDS_TypeOfConcavity
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE
    from OCP.TopExp import TopExp
    from OCP.TopoDS import TopoDS
    from OCP.TopTools import TopTools_IndexedDataMapOfShapeListOfShape, TopTools_IndexedMapOfShape

    wrapped = getattr(shape, "wrapped", shape)
    edge_map = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(wrapped, TopAbs_EDGE, edge_map)
    ancestors = TopTools_IndexedDataMapOfShapeListOfShape()
    TopExp.MapShapesAndAncestors_s(wrapped, TopAbs_EDGE, TopAbs_FACE, ancestors)
    names = {ChFiDS_TypeOfConcavity.ChFiDS_Convex: "convex", ChFiDS_TypeOfConcavity.ChFiDS_Concave: "concave",
             ChFiDS_TypeOfConcavity.ChFiDS_Tangential: "tangent"}
    convex, counts = [], {"convex": 0, "concave": 0, "tangent": 0, "other": 0}
    for i in range(1, edge_map.Extent() + 1):
        edge = TopoDS.Edge_s(edge_map.FindKey(i))
        faces = []
        if ancestors.Contains(edge):
            for f in ancestors.FindFromKey(edge):
                if not any(f.IsSame(g) for g in faces):
                    faces.append(f)
        if BRep_Tool.Degenerated_s(edge) or len(faces) != 2:
            counts["other"] += 1
            continue
        kind = names.get(ChFi3d.DefineConnectType_s(edge, TopoDS.Face_s(faces[0]), TopoDS.Face_s(faces[1]), 1e-6,
                                                    True), "other")
        counts[kind] += 1
        if kind == "convex":
            convex.append((i - 1, edge))
    return convex, counts


def _build(wrapped, spec, edges):
    """The broken solid, or None where OCCT fails or gives an invalid shape."""
    from OCP.BRepCheck import BRepCheck_Analyzer
    from OCP.BRepFilletAPI import BRepFilletAPI_MakeChamfer, BRepFilletAPI_MakeFillet

    maker = (BRepFilletAPI_MakeFillet if spec.kind == "fillet" else BRepFilletAPI_MakeChamfer)(wrapped)
    for edge in edges:
        maker.Add(spec.size, edge)
    try:
        maker.Build()
        if not maker.IsDone():
            return None
        out = maker.Shape()
    except Exception:  # OCCT raises StdFail_NotDone and kin where it cannot blend
        return None
    return out if BRepCheck_Analyzer(out).IsValid() else None


def break_edges(shape, spec, inv=None, progress=None):
    """Round or chamfer every convex edge of a solid.

    Parameters
    ----------
    shape : cadquery.Shape
        The solid as it is to be rendered (part frame, mm).
    spec : EdgeBreak
    inv : Inventory, optional
        ``inventory(shape)``, to name the edges left sharp by feature id.
    progress : callable or None

    Returns
    -------
    broken : cadquery.Shape
    record : dict
        For truth.json: the rule, ``kind``, ``size``, the edge counts,
        ``broken`` (how many) and ``unbroken``: each edge left sharp with
        its feature id (if it is one) and its midpoint.

    Raises
    ------
    ValueError
        No convex edge could be broken (the break is larger than the part
        allows everywhere), or the part has no convex edge.
    """
    import cadquery as cq

    say = progress or (lambda message: None)
    wrapped = shape.wrapped
    convex, counts = convex_edges(shape)
    if not convex:
        raise ValueError("the part has no convex edge to break")
    edges = [e for _, e in convex]
    say(f"breaking {len(edges)} edges ({spec.kind} {spec.size:g} mm)")
    out = _build(wrapped, spec, edges)
    kept = list(range(len(convex)))
    if out is None:
        say("breaking the edges one by one")
        kept = [k for k in range(len(convex)) if _build(wrapped, spec, [edges[k]]) is not None]
        out = _build(wrapped, spec, [edges[k] for k in kept]) if kept else None
        if out is None and kept:
            greedy = []
            for k in kept:
                trial = _build(wrapped, spec, [edges[j] for j in greedy + [k]])
                if trial is not None:
                    greedy, out = greedy + [k], trial
            kept = greedy
    if out is None:
        raise ValueError("no convex edge can take it: too large for this part")
    record = {
        "kind": spec.kind,
        "size": float(spec.size),
        "rule": "every convex (ISO 13715 external) edge broken; concave and tangent edges left sharp; the STEP "
                "model stays sharp",
        "edges": counts,
        "broken": len(kept),
        "unbroken": [_describe(convex[k], inv) for k in range(len(convex)) if k not in set(kept)],
    }
    return cq.Shape.cast(out), record


def _describe(item, inv):
    from OCP.BRepAdaptor import BRepAdaptor_Curve

    index, edge = item
    curve = BRepAdaptor_Curve(edge)
    p = curve.Value(0.5 * (curve.FirstParameter() + curve.LastParameter()))
    feature = None
    if inv is not None:
        feature = next((f.id for f in inv.features if index in f.edge_indices), None)
    return {"feature": feature, "midpoint": [p.X(), p.Y(), p.Z()]}
