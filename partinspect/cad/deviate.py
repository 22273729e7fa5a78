"""Make a deviated copy of a part: holes and bosses with changed size or place.

Synthetic test renders need parts that are *not* as drawn, with the true
deviation known exactly. This module changes whole cylindrical features of
the solid by real CAD booleans, so the hole's rims on both sides, its wall
and every face it cuts change together, exactly as a machining error would
change them.

Deviations are written ``<feature-id>.<param>=<value>`` (mm), e.g.
``circle-3.diameter=0.08`` or ``circle-2.center=0.1,0,0``, where the feature
is a circle or arc of the part's inventory and ``param`` is one of

- ``radius``, ``diameter``: added to the nominal radius or diameter;
- ``center``: a shift (dx, dy, dz) of the axis, part frame;
- ``x``, ``y``, ``z``: a shift of the axis along one part axis.

A shift must be perpendicular to the hole's axis: moving a through hole
along its own axis changes nothing, and moving a blind one would change its
depth, which is not what the parameter says.
"""

import math
import re

import numpy as np

from partinspect.errors import InputError

__all__ = ["DeviationError", "PARAMS", "deviate", "parse_deviation"]

PARAMS = ("radius", "diameter", "center", "x", "y", "z")
_AXES = {"x": 0, "y": 1, "z": 2}
_SYNTAX = re.compile(r"^\s*([A-Za-z][\w-]*)\s*\.\s*([A-Za-z]+)\s*=\s*(.+?)\s*$")
# Two cylinders are the same feature's wall when their axes and radii agree
# this closely (mm).
_SAME = 1e-6


class DeviationError(InputError, ValueError):
    """A deviation that is malformed or cannot be applied to this part.

    Both an `InputError` (the command line reports it in one line, exit
    code 2) and a `ValueError` (for library callers).
    """

    def __init__(self, problem):
        super().__init__(None, problem)


def parse_deviation(text, inventory=None):
    """Parse ``"<feature-id>.<param>=<value>"`` into a deviation tuple.

    Parameters
    ----------
    text : str
        E.g. ``"circle-3.diameter=0.08"``, ``"circle-2.center=0.1,0,0"``,
        ``"arc-1.x=-0.05"``. Values in mm, part frame.
    inventory : partinspect.cad.features.Inventory, optional
        If given, the feature id must be a circle or arc of it.

    Returns
    -------
    (feature_id, param, delta) : tuple
        ``delta`` is a float, or for ``center`` an ndarray of shape (3,).

    Raises
    ------
    DeviationError
        (an InputError and a ValueError) for bad syntax, an unknown
        parameter, a value that is not a finite number (or three for
        ``center``), or, with ``inventory``, an unknown id or a line.
    """
    match = _SYNTAX.match(str(text))
    if not match:
        raise DeviationError(f"deviation {text!r}: expected FEATURE.PARAM=VALUE, e.g. circle-3.diameter=0.08")
    fid, param, value = match.groups()
    param = param.lower()
    if param not in PARAMS:
        raise DeviationError(f"deviation {text!r}: unknown parameter {param!r} (use {', '.join(PARAMS)})")
    parts = [v.strip() for v in value.split(",")]
    try:
        numbers = [float(v) for v in parts]
    except ValueError:
        numbers = None
    wanted = 3 if param == "center" else 1
    if numbers is None or len(numbers) != wanted or not all(math.isfinite(v) for v in numbers):
        what = "three numbers dx,dy,dz" if wanted == 3 else "one number"
        raise DeviationError(f"deviation {text!r}: {param} needs {what} in mm, got {value!r}")
    delta = np.array(numbers) if param == "center" else numbers[0]
    if inventory is not None:
        _check_feature(inventory, fid)
    return fid, param, delta


def deviate(shape, inventory, deviations):
    """A copy of the part with holes or bosses resized or moved.

    Parameters
    ----------
    shape : cadquery.Shape
        The nominal part (solid), part frame, mm.
    inventory : partinspect.cad.features.Inventory
        ``inventory(shape)``; names the features.
    deviations : iterable of (feature_id, param, delta)
        As `parse_deviation` returns (strings are parsed too). The feature
        must be a circle or arc bounding a complete cylindrical wall (a full
        hole or boss, possibly split into several faces). ``radius`` /
        ``diameter`` in mm; ``center`` a (3,) shift, part frame, mm; ``x`` /
        ``y`` / ``z`` a shift along that axis. At most one size and one
        position change per hole.

    Returns
    -------
    cadquery.Shape
        The deviated solid. The original is not changed.

    Raises
    ------
    DeviationError
        For an unknown id, a line, an arc of a partial cylinder (a slot's
        round end cannot change alone), a feature that bounds no cylinder, a
        shift along the axis, a radius that would become <= 0, or two size
        (or two position) changes of the same hole.
    RuntimeError
        If OCCT's booleans fail or give an invalid solid.

    Notes
    -----
    A hole is removed with OCCT's defeaturing (or, failing that, filled with
    its exact cylinder), then the new cylinder is cut over the same axial
    extent; a boss is cut away and the new one fused on. Other features keep
    their geometry, so their ids survive unless a change reorders the
    geometric sort; face ids may change. Only the cylindrical part changes: a
    blind hole's drill-point cone keeps its size, and a bored boss loses its
    bore.
    """
    import cadquery as cq

    plan = _plan(shape, inventory, deviations)
    result = shape
    for hole in plan:
        result = _apply(result, hole)
    solids = result.Solids()
    if len(solids) != 1 or not result.isValid():
        raise RuntimeError(f"the deviated part is not one valid solid ({len(solids)} solids)")
    return cq.Solid(solids[0].wrapped)


# --- planning --------------------------------------------------------------


def _check_feature(inventory, fid):
    if fid not in inventory:
        raise DeviationError(f"deviation: no feature {fid!r} in this part")
    feature = inventory[fid]
    kind = getattr(feature, "kind", None)
    if kind not in ("circle", "arc"):
        what = f"a {kind}" if kind else "a face"
        raise DeviationError(f"deviation: {fid} is {what}; only circles and arcs (holes, bosses) can be deviated")
    return feature


def _plan(shape, inventory, deviations):
    """Resolve deviations to one change per cylindrical feature."""
    holes = {}
    for item in deviations:
        fid, param, delta = parse_deviation(item) if isinstance(item, str) else item
        if param not in PARAMS:
            raise DeviationError(f"deviation {fid}.{param}: unknown parameter (use {', '.join(PARAMS)})")
        feature = _check_feature(inventory, fid)
        wall = _wall_of(shape, inventory, feature)
        hole = holes.setdefault(wall["key"], dict(wall, size=None, shift=None))
        if param in ("radius", "diameter"):
            if hole["size"] is not None:
                raise DeviationError(f"deviation {fid}.{param}: this hole's size is already changed ({hole['size'][0]})")
            dr = float(delta) / (2.0 if param == "diameter" else 1.0)
            if hole["radius"] + dr <= 0:
                raise DeviationError(f"deviation {fid}.{param}={delta}: radius {hole['radius']:g} mm would become <= 0")
            hole["size"] = (f"{fid}.{param}", dr)
        else:
            shift = np.zeros(3)
            if param == "center":
                shift = np.asarray(delta, dtype=float).reshape(3)
            else:
                shift[_AXES[param]] = float(delta)
            axial = shift @ hole["direction"]
            if abs(axial) > 1e-9:
                raise DeviationError(
                    f"deviation {fid}.{param}: the shift has {axial:.6g} mm along the axis of {fid}; "
                    "only shifts perpendicular to the axis are supported"
                )
            if hole["shift"] is not None:
                raise DeviationError(f"deviation {fid}.{param}: this hole's position is already changed ({hole['shift'][0]})")
            hole["shift"] = (f"{fid}.{param}", shift)
    return list(holes.values())


def _wall_of(shape, inventory, feature):
    """The complete cylindrical wall a circle or arc bounds.

    Returns a dict: axis ``point`` and unit ``direction``, ``radius``, the
    axial extent ``t0 < t1`` along ``direction`` from ``point``, ``convex``
    (a boss) and a hashable ``key``.
    """
    candidates = [
        inventory[fid]
        for fid in feature.faces
        if inventory[fid].surface == "cylinder"
        and abs(inventory[fid].radius - feature.radius) <= _SAME * max(1.0, feature.radius)
        and _on_axis(feature.center, inventory[fid])
        and np.linalg.norm(np.cross(inventory[fid].axis_direction, feature.normal)) <= 1e-6
    ]
    if not candidates:
        raise DeviationError(f"deviation: {feature.id} bounds no cylindrical face (it is no hole or boss edge)")
    seed = candidates[0]
    # The wall may be split into several faces (half cylinders from other
    # CAD systems): gather every face on the same cylinder.
    wall = [f for f in inventory.faces if f.surface == "cylinder" and _same_cylinder(f, seed)]
    occ_faces = shape.Faces()
    turn = 0.0
    extent = []
    for info in wall:
        u0, u1, v0, v1, axis_origin, axis_dir = _cylinder_params(occ_faces[info.shape_index])
        turn += u1 - u0
        for v in (v0, v1):
            extent.append((axis_origin + v * axis_dir - seed.axis_point) @ seed.axis_direction)
    if turn < 2 * math.pi - 1e-9:
        raise DeviationError(
            f"deviation: {feature.id} bounds a partial cylinder ({math.degrees(turn):.1f} degrees, "
            "e.g. a slot's round end); only complete holes and bosses can be deviated"
        )
    convex = {bool(f.convex) for f in wall}
    if len(convex) != 1:
        raise DeviationError(f"deviation: {feature.id}: its cylinder is partly hole, partly boss")
    return {
        "key": tuple(sorted(f.id for f in wall)),
        "point": np.array(seed.axis_point),
        "direction": np.array(seed.axis_direction),
        "radius": float(seed.radius),
        "t0": min(extent),
        "t1": max(extent),
        "convex": convex.pop(),
        "name": feature.id,
    }


def _on_axis(point, face):
    v = point - face.axis_point
    return np.linalg.norm(v - (v @ face.axis_direction) * face.axis_direction) <= _SAME * max(1.0, face.radius)


def _same_cylinder(a, b):
    return (
        abs(a.radius - b.radius) <= _SAME * max(1.0, a.radius)
        and np.linalg.norm(np.cross(a.axis_direction, b.axis_direction)) <= 1e-9
        and _on_axis(a.axis_point, b)
    )


def _cylinder_params(face):
    """UV bounds of a cylindrical face and its surface's axis (origin, unit dir)."""
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepTools import BRepTools

    u0, u1, v0, v1 = BRepTools.UVBounds_s(face.wrapped)
    axis = BRepAdaptor_Surface(face.wrapped).Cylinder().Axis()
    origin = np.array([axis.Location().X(), axis.Location().Y(), axis.Location().Z()])
    direction = np.array([axis.Direction().X(), axis.Direction().Y(), axis.Direction().Z()])
    return u0, u1, v0, v1, origin, direction


# --- booleans --------------------------------------------------------------


def _cylinder(point, direction, radius, t0, t1):
    import cadquery as cq

    base = point + t0 * direction
    return cq.Solid.makeCylinder(radius, t1 - t0, cq.Vector(*base), cq.Vector(*direction))


def _apply(shape, hole):
    """One hole or boss changed; the rest of the shape as it was."""
    from partinspect.cad.features import face_inventory

    dr = 0.0 if hole["size"] is None else hole["size"][1]
    shift = np.zeros(3) if hole["shift"] is None else hole["shift"][1]
    point, direction, r = hole["point"], hole["direction"], hole["radius"]
    old = _cylinder(point, direction, r, hole["t0"], hole["t1"])
    new = _cylinder(point + shift, direction, r + dr, hole["t0"], hole["t1"])
    try:
        if hole["convex"]:
            out = shape.cut(old).clean().fuse(new).clean()
        else:
            # Earlier changes renumber faces: find this wall again by geometry.
            wall = [
                f
                for f in face_inventory(shape)
                if f.surface == "cylinder"
                and abs(f.radius - r) <= _SAME * max(1.0, r)
                and np.linalg.norm(np.cross(f.axis_direction, direction)) <= 1e-9
                and _on_axis(point, f)
            ]
            filled = _defeature(shape, [shape.Faces()[f.shape_index] for f in wall])
            if filled is None:
                filled = shape.fuse(old).clean()
            out = filled.cut(new).clean()
    except Exception as exc:
        raise RuntimeError(f"OCCT booleans failed while deviating {hole['name']}: {exc}") from None
    return out


def _defeature(shape, faces):
    """The shape with these faces removed and the gap closed, or None."""
    import cadquery as cq
    from OCP.BRepAlgoAPI import BRepAlgoAPI_Defeaturing

    if not faces:
        return None
    algo = BRepAlgoAPI_Defeaturing()
    algo.SetShape(shape.wrapped)
    for face in faces:
        algo.AddFaceToRemove(face.wrapped)
    algo.SetRunParallel(False)
    algo.Build()
    if not algo.IsDone():
        return None
    out = cq.Shape.cast(algo.Shape())
    return out if out.isValid() else None
