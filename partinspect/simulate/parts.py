"""Seeded parametric parts: valid solids of the kinds a machine shop makes, for tests and benchmarks.

Five kinds, each drawn from a seed: ``plate`` (a plate, sometimes with a
milled-down end), ``lug`` (a stepped lug: a base with a raised boss on one
end, a hole through the boss and features in the lower step), ``bracket``
(an L-bracket, features in both legs), ``flange`` (a disc with a raised hub
and bore and a bolt circle, symmetric under turns about its axis) and
``block`` (a tall block with features on its top and its front). Their
features are through, blind, counterbored and countersunk holes, slots,
rectangular pockets with rounded corners and round bosses; their outer
edges may be chamfered or filleted.

Placement rule: every feature occupies a disc on its face (its footprint:
a hole's largest radius, half a slot's length, half a pocket's diagonal, a
boss's radius), and footprints keep `WALL` of material from each other and
from the face's borders (plus the size of an edge treatment). Depths leave
at least `FLOOR` of material under a blind feature. So features never cut
into each other and every part is one valid solid; :func:`random_part`
checks ``isValid()`` all the same and draws again from the same seed if a
part is not.

Sizes keep a part within the simulator rig's field of view (about 136 x 114
mm at its 400 mm working distance, seen at 45 degrees): no side longer than
`MAX_LENGTH`.

Part frame (= STEP frame), mm: the part stands on z = 0, x along its
length, y along its width, z up; the flange is centred on the z axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["KINDS", "WALL", "FLOOR", "MAX_LENGTH", "PlacedFeature", "GeneratedPart", "random_part", "part_shape",
           "write_part", "lug", "flange", "random_pose"]

KINDS = ("plate", "lug", "bracket", "flange", "block")
"""The part kinds :func:`random_part` draws from, in the order of ``seed % 5`` when no kind is given."""

WALL = 3.0
"""Least material between two features, or a feature and a face's border, mm: thinner walls are not
machined, and a thinner web would make features touch after rounding."""

FLOOR = 2.0
"""Least material under a blind hole, pocket or counterbore, mm."""

MAX_LENGTH = 95.0
"""Longest side of a random part, mm: its diagonal then stays within the rig's 136 x 114 mm field of view
at the working distance in every pose ``inspect plan`` searches."""

_EPS = 0.5  # cutters overshoot the faces they open on by this much, mm, so that no face is coplanar


@dataclass(frozen=True)
class PlacedFeature:
    """A feature the generator placed, and the circular edges it must leave on the part.

    Attributes
    ----------
    kind : str
        ``through``, ``blind``, ``counterbore``, ``countersink`` (holes),
        ``slot``, ``pocket`` or ``boss``.
    center : tuple of 3 float
        Centre of its opening on the face it is made in, part frame, mm.
    normal : tuple of 3 float
        Outward normal of that face.
    diameter : float
        Hole or boss diameter; a slot's width; a pocket's shorter side, mm.
    length : float
        A slot's or pocket's length (end to end), mm; 0 otherwise.
    circles : tuple of ((float, float, float), float)
        ``(centre, radius)`` of every full circular edge it makes (rims of
        holes, counterbores and countersinks, a boss's foot and top).
    arcs : tuple of ((float, float, float), float)
        ``(centre, radius)`` of the half-circle ends of a slot at its face.
    """

    kind: str
    center: tuple
    normal: tuple
    diameter: float
    length: float = 0.0
    circles: tuple = ()
    arcs: tuple = ()


@dataclass(frozen=True, eq=False)
class GeneratedPart:
    """A generated part.

    Attributes
    ----------
    kind : str
        One of `KINDS`.
    seed : int
    shape : cadquery.Solid
        A valid solid, part frame, mm.
    features : tuple of PlacedFeature
    """

    kind: str
    seed: int
    shape: object
    features: tuple


@dataclass(frozen=True)
class _Face:
    """A flat rectangular face region: points ``origin + a u + b v``, a in [0, su], b in [0, sv].

    ``n`` is the outward normal, ``depth`` the material under the face along
    ``-n`` (the length of a through hole), ``margin`` the extra border kept
    clear (an edge treatment); ``exits`` False where a hole of that length
    ends inside the part (its bottom is flat).
    """

    origin: tuple
    u: tuple
    v: tuple
    n: tuple
    su: float
    sv: float
    depth: float
    margin: float = 0.0
    exits: bool = True

    def point(self, a, b):
        return np.asarray(self.origin, float) + a * np.asarray(self.u, float) + b * np.asarray(self.v, float)


# ----------------------------------------------------------------- features


def _round(x, step=0.5):
    """Sizes in steps of ``step`` mm, as a drawing would give them."""
    return float(step * round(float(x) / step))


def _draw_feature(rng, face, kinds):
    """Draw one feature's kind and sizes for a face (no position yet): a dict with its footprint radius."""
    kind = kinds[int(rng.integers(len(kinds)))]
    t = face.depth
    if kind in ("through", "blind", "counterbore", "countersink"):
        d = _round(rng.uniform(3.0, 12.0))
        spec = {"kind": kind, "d": d, "rho": d / 2}
        if kind == "blind":
            if t - FLOOR < 2.0:
                spec["kind"] = "through"
            else:
                spec["depth"] = _round(rng.uniform(min(2.0, t - FLOOR), t - FLOOR))
        elif kind == "counterbore":
            if t - FLOOR < 2.0:
                spec["kind"] = "through"
            else:
                D = _round(d * rng.uniform(1.5, 1.9))
                spec.update(D=D, depth=_round(rng.uniform(1.0, min(0.5 * t, t - FLOOR))), rho=D / 2)
        elif kind == "countersink":
            # 90 degree countersink: its cone drops (D - d) / 2; keep half the wall below it.
            D = _round(min(d + 2 * rng.uniform(1.0, 3.0), d + t))
            if D <= d:
                spec["kind"] = "through"
            else:
                spec.update(D=D, rho=D / 2)
        return spec
    if kind == "slot":
        w = _round(rng.uniform(4.0, 10.0))
        length = _round(w + rng.uniform(4.0, 16.0))
        through = bool(rng.random() < 0.5) or t - FLOOR < 2.0
        depth = t if through else _round(rng.uniform(min(2.0, t - FLOOR), t - FLOOR))
        return {"kind": "slot", "w": w, "length": length, "angle": float(rng.choice([0.0, 90.0, 30.0, -45.0])),
                "depth": depth, "through": through, "rho": length / 2}
    if kind == "pocket":
        if t - FLOOR < 2.0:
            return _draw_feature(rng, face, ["through"])
        a, b = _round(rng.uniform(8.0, 22.0)), _round(rng.uniform(6.0, 16.0))
        r = _round(rng.uniform(1.0, min(a, b) / 2 - 0.5))
        return {"kind": "pocket", "a": max(a, b), "b": min(a, b), "r": r,
                "depth": _round(rng.uniform(min(2.0, t - FLOOR), t - FLOOR)), "rho": 0.5 * math.hypot(a, b)}
    if kind == "boss":
        d = _round(rng.uniform(6.0, 16.0))
        return {"kind": "boss", "d": d, "h": _round(rng.uniform(2.0, 8.0)), "rho": d / 2}
    raise ValueError(f"unknown feature kind {kind!r}")


def _place(rng, face, specs, taken=None, tries=60):
    """Centres ``(a, b)`` for footprints on a face, clear of the borders and of each other.

    Rejection sampling: each footprint tries ``tries`` uniform centres in the
    face shrunk by its radius plus ``WALL + face.margin``; one that finds no
    room is dropped. ``taken`` are footprints already there, ``(a, b, rho)``.
    """
    placed, taken = [], list(taken or [])
    m = WALL + face.margin
    for spec in specs:
        rho = spec["rho"]
        lo_a, hi_a, lo_b, hi_b = m + rho, face.su - m - rho, m + rho, face.sv - m - rho
        if hi_a < lo_a or hi_b < lo_b:
            continue
        for _ in range(tries):
            a, b = _round(rng.uniform(lo_a, hi_a), 0.25), _round(rng.uniform(lo_b, hi_b), 0.25)
            if a < lo_a or a > hi_a or b < lo_b or b > hi_b:
                continue
            if all(math.hypot(a - ta, b - tb) >= rho + tr + WALL for ta, tb, tr in taken):
                taken.append((a, b, rho))
                placed.append((spec, a, b))
                break
    return placed


def _tuple(p):
    return tuple(round(float(x), 9) for x in p)


def _make(face, spec, a, b):
    """Cutters (cut from the part), adders (fused to it) and the PlacedFeature of one placed feature."""
    import cadquery as cq

    p = face.point(a, b)
    n = np.asarray(face.n, float)
    top = p + _EPS * n
    kind = spec["kind"]
    cut, add, circles, arcs = [], [], [], []

    def cylinder(r, depth, start=top):
        return cq.Solid.makeCylinder(r, depth, cq.Vector(*start), cq.Vector(*(-n)))

    if kind in ("through", "blind", "counterbore", "countersink"):
        r = spec["d"] / 2
        through = kind != "blind"
        depth = face.depth if through else spec["depth"]
        cut.append(cylinder(r, depth + (2 if through and face.exits else 1) * _EPS))
        circles.append((p, r))
        circles.append((p - depth * n, r))
        if kind == "counterbore":
            R = spec["D"] / 2
            cut.append(cylinder(R, spec["depth"] + _EPS))
            circles[0] = (p, R)
            circles += [(p - spec["depth"] * n, R), (p - spec["depth"] * n, r)]
        elif kind == "countersink":
            R = spec["D"] / 2
            drop = R - r
            cut.append(cq.Solid.makeCone(R + _EPS, r, drop + _EPS, cq.Vector(*top), cq.Vector(*(-n))))
            circles[0] = (p, R)
            circles.append((p - drop * n, r))
        diameter, length = spec["d"], 0.0
    elif kind == "slot":
        plane = cq.Plane(origin=cq.Vector(*top), xDir=cq.Vector(*face.u), normal=cq.Vector(*n))
        depth = spec["depth"] + (2 if spec["through"] and face.exits else 1) * _EPS
        cut.append(cq.Workplane(plane).slot2D(spec["length"], spec["w"], spec["angle"]).extrude(-depth).val())
        half = 0.5 * (spec["length"] - spec["w"])
        ang = math.radians(spec["angle"])
        # cadquery turns the slot from the plane's x towards its y = normal x xDir.
        along = math.cos(ang) * np.asarray(face.u, float) + math.sin(ang) * np.cross(n, face.u)
        arcs += [(p + half * along, spec["w"] / 2), (p - half * along, spec["w"] / 2)]
        diameter, length = spec["w"], spec["length"]
    elif kind == "pocket":
        plane = cq.Plane(origin=cq.Vector(*top), xDir=cq.Vector(*face.u), normal=cq.Vector(*n))
        box = cq.Workplane(plane).rect(spec["a"], spec["b"]).extrude(-(spec["depth"] + _EPS))
        box = box.edges(cq.selectors.ParallelDirSelector(cq.Vector(*n))).fillet(spec["r"])
        cut.append(box.val())
        diameter, length = spec["b"], spec["a"]
    elif kind == "boss":
        R = spec["d"] / 2
        add.append(cq.Solid.makeCylinder(R, spec["h"] + 1.0, cq.Vector(*(p - 1.0 * n)), cq.Vector(*n)))
        circles += [(p, R), (p + spec["h"] * n, R)]
        diameter, length = spec["d"], 0.0
    else:
        raise ValueError(f"unknown feature kind {kind!r}")
    feature = PlacedFeature(kind, _tuple(p), _tuple(n), float(diameter), float(length),
                            tuple((_tuple(c), float(r)) for c, r in circles),
                            tuple((_tuple(c), float(r)) for c, r in arcs))
    return cut, add, feature


def _apply(shape, placed_on):
    """The shape with every ``(face, spec, a, b)`` made: bosses fused first, then everything cut."""
    cuts, adds, features = [], [], []
    for face, spec, a, b in placed_on:
        c, ad, f = _make(face, spec, a, b)
        cuts += c
        adds += ad
        features.append(f)
    for s in adds:
        shape = shape.fuse(s)
    for s in cuts:
        shape = shape.cut(s)
    return shape.clean(), tuple(features)


def _solid(shape):
    """The one solid of a shape, or the shape itself if it holds several (not valid here)."""
    solids = shape.Solids()
    return solids[0] if len(solids) == 1 else shape


def _features_on(rng, face, count, kinds, taken=None):
    specs = [_draw_feature(rng, face, kinds) for _ in range(count)]
    return [(face, spec, a, b) for spec, a, b in _place(rng, face, specs, taken)]


def _edge_treatment(rng, body, *, allow_fillet=True):
    """Fillet the vertical outer edges, chamfer the top outer edges, or neither; returns (body, size mm)."""
    choice = rng.random()
    if allow_fillet and choice < 0.35:
        r = _round(rng.uniform(2.0, 8.0))
        return body.edges("|Z").fillet(r), r
    if choice < 0.7:
        c = _round(rng.uniform(0.5, 2.0))
        return body.faces(">Z").edges().chamfer(c), c
    return body, 0.0


_HOLES = ["through", "through", "blind", "counterbore", "countersink"]
_ALL = _HOLES + ["slot", "pocket", "boss"]


# -------------------------------------------------------------------- kinds


def _plate(rng):
    import cadquery as cq

    L = _round(rng.uniform(50.0, MAX_LENGTH))
    W = _round(rng.uniform(40.0, min(L, 75.0)))
    T = _round(rng.uniform(6.0, 14.0))
    body, m = _edge_treatment(rng, cq.Workplane("XY").box(L, W, T, centered=False))
    placed = []
    if rng.random() < 0.5:
        # A milled-down end, full width: two top levels.
        s = _round(rng.uniform(0.3, 0.5) * L)
        drop = _round(rng.uniform(0.3, 0.5) * T)
        body = body.cut(cq.Workplane("XY").box(s + 1, W + 2, drop + 1, centered=False)
                        .translate((L - s, -1, T - drop)))
        upper = _Face((0, 0, T), (1, 0, 0), (0, 1, 0), (0, 0, 1), L - s, W, T, m)
        lower = _Face((L - s, 0, T - drop), (1, 0, 0), (0, 1, 0), (0, 0, 1), s, W, T - drop, m)
        placed += _features_on(rng, upper, int(rng.integers(1, 5)), _ALL)
        placed += _features_on(rng, lower, int(rng.integers(1, 3)), _HOLES + ["slot"])
    else:
        top = _Face((0, 0, T), (1, 0, 0), (0, 1, 0), (0, 0, 1), L, W, T, m)
        placed += _features_on(rng, top, int(rng.integers(2, 7)), _ALL)
    return body.val(), placed


def lug(length=100.0, width=56.0, thickness=10.0, boss_length=44.0, boss_height=8.0, boss_hole=14.0,
        holes=((14.0, 13.0, 7.5), (14.0, 43.0, 7.5)), slot=(38.0, 28.0, 16.0, 8.0, 0.0)):
    """A stepped lug: a base with a raised boss on one end, a hole through it, holes and a slot in the lower step.

    The defaults are the lug of issue 46: a 100 x 56 x 10 mm base, a 44 x
    56 x 8 mm boss on its +x end with a 14 mm hole through the boss, two
    7.5 mm holes and a 16 x 8 mm slot in the lower step.

    Parameters
    ----------
    length, width, thickness : float
        The base, mm (x, y, z).
    boss_length, boss_height : float
        The boss spans the full width, from ``x = length - boss_length`` to
        the end, and rises ``boss_height`` above the base, mm.
    boss_hole : float
        Diameter of the through hole at the boss's centre, mm.
    holes : sequence of (x, y, diameter)
        Through holes in the lower step, mm.
    slot : (x, y, length, width, angle) or None
        A through slot in the lower step: centre, end-to-end length, width
        (mm) and its direction from +x (degrees).

    Returns
    -------
    GeneratedPart
        Kind ``lug``, seed -1.
    """
    import cadquery as cq

    body = cq.Workplane("XY").box(length, width, thickness + boss_height, centered=False)
    body = body.cut(cq.Workplane("XY").box(length - boss_length, width + 2, boss_height + 1, centered=False)
                    .translate((-1, -1, thickness)))
    upper = _Face((length - boss_length, 0, thickness + boss_height), (1, 0, 0), (0, 1, 0), (0, 0, 1),
                  boss_length, width, thickness + boss_height)
    lower = _Face((0, 0, thickness), (1, 0, 0), (0, 1, 0), (0, 0, 1), length - boss_length, width, thickness)
    placed = [(upper, {"kind": "through", "d": boss_hole}, boss_length / 2, width / 2)]
    placed += [(lower, {"kind": "through", "d": d}, x, y) for x, y, d in holes]
    if slot is not None:
        x, y, sl, sw, ang = slot
        placed.append((lower, {"kind": "slot", "w": sw, "length": sl, "angle": ang, "depth": thickness,
                               "through": True}, x, y))
    shape, features = _apply(body.val(), placed)
    return GeneratedPart("lug", -1, _solid(shape), features)


def _lug(rng):
    import cadquery as cq

    L = _round(rng.uniform(70.0, MAX_LENGTH))
    W = _round(rng.uniform(36.0, 60.0))
    T = _round(rng.uniform(6.0, 12.0))
    bl = _round(rng.uniform(0.3, 0.5) * L)
    bh = _round(rng.uniform(4.0, 10.0))
    body = cq.Workplane("XY").box(L, W, T + bh, centered=False)
    body = body.cut(cq.Workplane("XY").box(L - bl, W + 2, bh + 1, centered=False).translate((-1, -1, T)))
    if rng.random() < 0.5:
        body = body.faces(">Z").edges("|Y").chamfer(_round(rng.uniform(0.5, 1.5)))
    upper = _Face((L - bl, 0, T + bh), (1, 0, 0), (0, 1, 0), (0, 0, 1), bl, W, T + bh, 2.0)
    lower = _Face((0, 0, T), (1, 0, 0), (0, 1, 0), (0, 0, 1), L - bl, W, T, 2.0)
    d = _round(rng.uniform(6.0, min(18.0, bl - 2 * (WALL + 2.0), W - 2 * (WALL + 2.0))))
    placed = [(upper, {"kind": "through", "d": d, "rho": d / 2}, bl / 2, W / 2)]
    placed += _features_on(rng, lower, int(rng.integers(2, 5)), _HOLES + ["slot", "slot"])
    return body.val(), placed


def _bracket(rng):
    import cadquery as cq

    L = _round(rng.uniform(50.0, 90.0))
    W = _round(rng.uniform(30.0, 60.0))
    H = _round(rng.uniform(30.0, 60.0))
    t = _round(rng.uniform(5.0, 10.0))
    body = (cq.Workplane("XY").box(L, W, t, centered=False)
            .union(cq.Workplane("XY").box(t, W, H, centered=False)))
    rf = 0.0
    if rng.random() < 0.6:
        rf = _round(rng.uniform(2.0, 6.0))
        body = body.edges("|Y").edges(cq.selectors.NearestToPointSelector((t, W / 2, t))).fillet(rf)
    m = 0.0
    if rng.random() < 0.5:
        m = _round(rng.uniform(0.5, 1.5))
        body = body.edges("|Y").edges(cq.selectors.NearestToPointSelector((L, W / 2, t))).chamfer(m)
    foot = _Face((t + rf, 0, t), (1, 0, 0), (0, 1, 0), (0, 0, 1), L - t - rf, W, t, m)
    # The upright's outer face (x = 0, looking along -x): u along +y, v up.
    upright = _Face((0, 0, t + rf), (0, 1, 0), (0, 0, 1), (-1, 0, 0), W, H - t - rf, t)
    placed = _features_on(rng, foot, int(rng.integers(1, 4)), _HOLES + ["slot"])
    placed += _features_on(rng, upright, int(rng.integers(1, 3)), ["through", "through", "countersink", "slot"])
    return body.val(), placed


def flange(diameter=90.0, thickness=12.0, hub_diameter=50.0, hub_height=8.0, bore=24.0, bolts=6,
           bolt_diameter=9.0, bolt_circle=70.0, counterbore=None, chamfer=0.0, clocking=None):
    """A round flange: a disc, a raised hub with a bore, and a bolt circle of equal holes.

    The defaults are the flange of issue 46: a 90 mm disc 12 mm thick, a
    raised 50 mm hub with a 24 mm bore, six 9 mm bolt holes on a 70 mm
    circle. The part maps onto itself under turns of ``360 / bolts``
    degrees about its axis (the z axis), so an alignment to it is ambiguous
    by those turns, and every one of them is right. With a ``clocking``
    hole it does not: the hole sits in the disc's underside, which cameras
    above the part do not see, so the features they measure are still
    symmetric and which bolt hole is which cannot be told from them.

    Parameters
    ----------
    diameter, thickness : float
        The disc, mm; it stands on z = 0, centred on the z axis.
    hub_diameter, hub_height : float
        The hub on top of the disc, mm.
    bore : float
        Diameter of the bore through hub and disc, mm.
    bolts : int
        Number of bolt holes, equally spaced, the first on +x.
    bolt_diameter, bolt_circle : float
        Bolt hole diameter and the diameter of the circle through their
        centres, mm.
    counterbore : (float, float) or None
        ``(diameter, depth)`` of a counterbore on every bolt hole, mm.
    chamfer : float
        Chamfer on the disc's top outer edge, mm (0: none).
    clocking : (float, float) or None
        ``(diameter, depth)`` of a blind hole drilled up into the disc's
        underside on the bolt circle, half a bolt spacing from +x, mm.

    Returns
    -------
    GeneratedPart
        Kind ``flange``, seed -1.
    """
    import cadquery as cq

    body = cq.Workplane("XY").circle(diameter / 2).extrude(thickness)
    if chamfer > 0:
        body = body.faces(">Z").edges().chamfer(chamfer)
    hub = cq.Workplane("XY").workplane(offset=thickness - 1.0).circle(hub_diameter / 2).extrude(hub_height + 1.0)
    body = body.union(hub)
    top = thickness + hub_height
    hub_face = _Face((0, 0, top), (1, 0, 0), (0, 1, 0), (0, 0, 1), 0.0, 0.0, top)
    disc_face = _Face((0, 0, thickness), (1, 0, 0), (0, 1, 0), (0, 0, 1), 0.0, 0.0, thickness)
    placed = [(hub_face, {"kind": "through", "d": bore}, 0.0, 0.0)]
    for k in range(bolts):
        phi = 2 * math.pi * k / bolts
        spec = {"kind": "through", "d": bolt_diameter}
        if counterbore is not None:
            spec = {"kind": "counterbore", "d": bolt_diameter, "D": counterbore[0], "depth": counterbore[1]}
        placed.append((disc_face, spec, 0.5 * bolt_circle * math.cos(phi), 0.5 * bolt_circle * math.sin(phi)))
    if clocking is not None:
        under = _Face((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, -1), 0.0, 0.0, thickness, exits=False)
        phi = math.pi / bolts
        placed.append((under, {"kind": "blind", "d": clocking[0], "depth": clocking[1]},
                       0.5 * bolt_circle * math.cos(phi), 0.5 * bolt_circle * math.sin(phi)))
    shape, features = _apply(body.val(), placed)
    return GeneratedPart("flange", -1, _solid(shape), features)


def _flange_params(rng):
    D = _round(rng.uniform(60.0, 92.0))
    T = _round(rng.uniform(8.0, 14.0))
    Dh = _round(rng.uniform(0.4, 0.6) * D)
    bore = _round(rng.uniform(0.35, 0.65) * Dh)
    chamfer = _round(rng.uniform(0.5, 1.5)) if rng.random() < 0.5 else 0.0
    # Bolt holes between the hub and the rim, WALL clear of both.
    room = 0.5 * (D - Dh) - 2 * WALL - chamfer
    d = 0.5 * math.floor(2.0 * rng.uniform(4.0, min(11.0, room)))
    cb, d_foot = None, d
    if rng.random() < 0.3 and room - d >= 3.0:
        d_foot = 0.5 * math.floor(2.0 * (d + rng.uniform(2.0, min(6.0, room - d))))
        cb = (d_foot, _round(rng.uniform(1.0, 0.5 * T)))
    bc = 0.5 * Dh + WALL + 0.5 * d_foot + rng.uniform(0.0, max(0.0, room - d_foot))
    bc = _round(2 * bc)
    n_max = int(math.pi / math.asin(min(1.0, (d_foot + WALL) / bc))) if bc > d_foot + WALL else 3
    n = int(rng.integers(3, max(4, min(8, n_max) + 1)))
    return dict(diameter=D, thickness=T, hub_diameter=Dh, hub_height=_round(rng.uniform(4.0, 12.0)), bore=bore,
                bolts=n, bolt_diameter=d, bolt_circle=bc, counterbore=cb, chamfer=chamfer)


def _block(rng):
    import cadquery as cq

    L = _round(rng.uniform(40.0, 75.0))
    W = _round(rng.uniform(30.0, 60.0))
    H = _round(rng.uniform(20.0, 40.0))
    body = cq.Workplane("XY").box(L, W, H, centered=False)
    m = 0.0
    if rng.random() < 0.6:
        m = _round(rng.uniform(0.5, 2.0))
        body = body.faces(">Z").edges().chamfer(m)
    # Top features no deeper than 0.4 H; front holes in the lower half: the two never meet.
    top = _Face((0, 0, H), (1, 0, 0), (0, 1, 0), (0, 0, 1), L, W, 0.4 * H + FLOOR, m, exits=False)
    front = _Face((0, 0, 0), (1, 0, 0), (0, 0, 1), (0, -1, 0), L, 0.5 * H, W)
    placed = _features_on(rng, top, int(rng.integers(2, 6)), ["blind", "counterbore", "pocket", "boss", "slot"])
    placed += _features_on(rng, front, int(rng.integers(1, 3)), ["through", "blind", "countersink"])
    return body.val(), placed


_BUILDERS = {"plate": _plate, "lug": _lug, "bracket": _bracket, "block": _block}


def random_part(seed, kind=None, tries=10):
    """A seeded random part of one of `KINDS`, a valid solid.

    Parameters
    ----------
    seed : int
        Everything is drawn from ``numpy.random.default_rng(seed)``: the same
        seed gives the same part.
    kind : str, optional
        One of `KINDS`; default ``KINDS[seed % 5]``.
    tries : int
        Draws before giving up; a draw whose shape is not one valid solid
        is drawn again from the same generator.

    Returns
    -------
    GeneratedPart

    Raises
    ------
    RuntimeError
        If no draw in ``tries`` gave a valid solid.
    """
    kind = KINDS[seed % len(KINDS)] if kind is None else kind
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    rng = np.random.default_rng([int(seed), KINDS.index(kind)])
    problem = "not one valid solid"
    for _ in range(tries):
        try:
            if kind == "flange":
                part = flange(**_flange_params(rng))
                shape, features = part.shape, part.features
            else:
                body, placed = _BUILDERS[kind](rng)
                shape, features = _apply(body, placed)
        except Exception as exc:  # an OCCT fillet or boolean that fails on this draw: draw again
            problem = f"{type(exc).__name__}: {exc}"
            continue
        if shape.isValid() and len(shape.Solids()) == 1:
            return GeneratedPart(kind, int(seed), _solid(shape), features)
    raise RuntimeError(f"no valid {kind} from seed {seed} in {tries} draws (last: {problem})")


def part_shape(seed, kind=None):
    """The cadquery solid of :func:`random_part` (part frame, mm)."""
    return random_part(seed, kind).shape


def write_part(part, path):
    """Write a generated part (or the part of a seed) to a STEP AP214 file, reproducibly.

    Parameters
    ----------
    part : GeneratedPart or int
        The part, or a seed for :func:`random_part`.
    path : str or os.PathLike

    Returns
    -------
    GeneratedPart
    """
    from partinspect.cad.step import save_step

    if not isinstance(part, GeneratedPart):
        part = random_part(int(part))
    save_step(part.shape, path, name=f"{part.kind}-{part.seed}")
    return part


# -------------------------------------------------------------------- poses


def _in_view(points, P, rig, margin):
    from partinspect.vision.calibration import project_points

    X = np.asarray(points, float) @ P[:3, :3].T + P[:3, 3]
    w, h = rig.image_size
    for index in (0, 1):
        K, D, R, t = rig.camera(index)
        uv = project_points(X, K, D, R, t)
        if not np.all(np.isfinite(uv)):
            return False
        if uv[:, 0].min() < margin or uv[:, 1].min() < margin or uv[:, 0].max() > w - margin or \
                uv[:, 1].max() > h - margin:
            return False
    return True


def random_pose(rng, shape, rig, *, rotation=180.0, max_tilt=30.0, in_view=True, margin=20.0, tries=50):
    """A random pose of a part that ``inspect plan`` can reach, with the whole part in both images.

    ``inspect plan`` searches fixture poses about the default pose: turns
    about the fixture's axis within ``+-rotation`` degrees and tilts about
    its X and Y axes within ``+-max_tilt`` (see
    :mod:`partinspect.planning.search`). This draws such a pose uniformly in
    those angles and keeps it if every vertex of the part's tessellation
    falls at least ``margin`` pixels inside both images.

    Parameters
    ----------
    rng : numpy.random.Generator or int
    shape : cadquery.Shape
    rig : StereoCalibration
        With its image size.
    rotation, max_tilt : float
        The search limits, degrees (``inspect plan``'s defaults).
    in_view : bool
        Require the part in both images.
    margin : float
        Pixels.
    tries : int

    Returns
    -------
    part_to_camera : ndarray, shape (4, 4)
    angles : FixturePose
        Its fixture angles (degrees).

    Raises
    ------
    RuntimeError
        If no pose in ``tries`` draws keeps the part in view.
    """
    from partinspect.planning.search import FixturePose, fixture_pose
    from partinspect.poses import bounds_of, default_pose

    rng = np.random.default_rng(rng)
    bounds = bounds_of(shape)
    start = default_pose(bounds, rig)
    center = bounds.mean(axis=0)
    points = np.array([v.toTuple() for v in shape.tessellate(0.5)[0]]) if in_view else None
    for _ in range(tries):
        fp = FixturePose(float(np.round(rng.uniform(-rotation, rotation), 1)),
                         float(np.round(rng.uniform(-max_tilt, max_tilt), 1)),
                         float(np.round(rng.uniform(-max_tilt, max_tilt), 1)))
        P = fixture_pose(start, center, fp)
        if not in_view or _in_view(points, P, rig, margin):
            return P, fp
    raise RuntimeError(f"no pose within the search limits kept the part in view in {tries} draws")
