"""Where the apparent edge of a broken (rounded or chamfered) edge lies, and what that does to a size.

A machined outer edge is broken: deburred, rounded or chamfered, by an
amount a drawing states as an edge state (ISO 13715, e.g. "-0.1": up to
0.1 mm of material removed from the ideal sharp edge, along each face).
The STEP model keeps the sharp edge, but the camera sees the break: the
grey-level step the detector finds lies somewhere across the break's band,
between the two lines where it meets its faces, depending on the light,
the view and the surface. Across a hole's rim that band runs from the top
face, ``b`` outside the wall, down to the wall itself, so the rim seen is
larger than the hole by ``2 s b`` with ``s`` in [0, 1] unknown; on a boss it
is smaller by as much.

The rule here: the break's size ``b`` is uniform between the stated ``min``
and ``max``, the apparent edge's place ``s`` across the band uniform in
[0, 1] and independent of it; their product's mean is removed from the size
measured on the rim (the size reported is the wall's, which is what the
drawing's diameter means) and its standard deviation is carried as a Type B
standard uncertainty (JCGM 100, 4.3.7: a rectangular distribution where
nothing better is known). A break of 0.1 mm states a hole's diameter to
``0.1 / sqrt(3) = 0.058`` mm standard uncertainty from the break alone: a
camera that cannot see where on a rounded rim the wall begins cannot
judge a hole more finely than that, and the decision says so. (That is a
break of exactly 0.1 mm; "up to 0.1 mm", ``min`` 0, gives 0.044 mm.)

References
----------
.. [1] ISO 13715:2019, Technical product documentation -- Edges of
       undefined shape -- Indication and dimensioning.
.. [2] JCGM 100:2008 (GUM), 4.3.7 (rectangular distribution), 4.3.9.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from partinspect.cad.features import cylinder_sides, faces_of

__all__ = ["band_offset", "band_rms", "size_on_broken_rim", "apparent_edge_rms", "broken_rims", "broken_lines",
           "with_band_places", "cylinder_side", "seen_from_its_face"]


def band_offset(b_min, b_max, place=None):
    """Mean and standard deviation of the apparent edge's offset ``s b`` across a break's band, mm.

    Parameters
    ----------
    b_min, b_max : float
        The break's size range, mm, ``0 <= b_min <= b_max``.
    place : (float, float), optional
        The band place ``s`` predicted for this rim and its standard
        uncertainty (:mod:`partinspect.vision.band_place`); by default ``s``
        is uniform in [0, 1].

    Returns
    -------
    mean, std : float
        ``s`` and ``b ~ U(b_min, b_max)`` independent: ``E[s b] = E[s]
        E[b]``, ``E[(s b)^2] = E[s^2] E[b^2]``; uniform ``s`` has ``E[s] =
        1/2``, ``E[s^2] = 1/3``.
    """
    eb = 0.5 * (b_min + b_max)
    eb2 = (b_min * b_min + b_min * b_max + b_max * b_max) / 3.0
    es, es2 = (0.5, 1.0 / 3.0) if place is None else (place[0], place[0] ** 2 + place[1] ** 2)
    mean = es * eb
    return mean, math.sqrt(max(es2 * eb2 - mean * mean, 0.0))


def band_rms(b_min, b_max):
    """RMS of the apparent edge's offset ``s b`` across the band about zero, mm.

    The Type B of what the band's place, changing around a rim, does to the
    rim's circularity: the out-of-roundness seen lies between zero and the
    break, and nothing tells where.
    """
    mean, std = band_offset(b_min, b_max)
    return math.hypot(mean, std)


def size_on_broken_rim(radius, radius_u, convex, b_min, b_max, place=None):
    """The radius of a hole's wall (or a boss's) from the radius measured on its broken rim.

    Parameters
    ----------
    radius, radius_u : float
        The rim's fitted radius and its standard uncertainty, mm.
    convex : bool or None
        The cylinder's material side (``FaceInfo.convex``): False a hole
        (the rim seen is larger than the wall), True a boss (smaller); None
        unknown, when only the Type B is added.
    b_min, b_max : float
        The edge break's size range, mm.
    place : (float, float), optional
        The predicted band place and its standard uncertainty
        (:func:`band_offset`); by default uniform across the band.

    Returns
    -------
    radius, u : float
        The wall's radius and its standard uncertainty, mm.
    correction : float
        What was added to the measured radius, mm.
    u_break : float
        The break's Type B part of ``u``, mm.
    """
    mean, std = band_offset(b_min, b_max, place)
    if convex is None:
        correction, u_break = 0.0, band_rms(b_min, b_max)
    else:
        correction, u_break = (mean if convex else -mean), std
    return radius + correction, math.hypot(radius_u, u_break), correction, u_break


def apparent_edge_rms(b_min, b_max):
    """RMS distance, mm, of a broken edge's apparent step from the sharp edge.

    Across a chamfer of size ``b`` between two faces at right angles the
    step lies at ``b ((1 - s) u1 + s u2)`` from the sharp edge (u1, u2 unit
    vectors along the faces, s uniform in [0, 1]), whose mean square is
    ``2 b^2 / 3``; a fillet's band lies between that chamfer and the edge,
    so this bounds it. With ``b`` uniform in ``[b_min, b_max]``: ``sqrt(2
    E[b^2] / 3)``. The stereo chain carries it as a Type B of every edge
    (:func:`partinspect.vision.band_modes.edge_band`: one offset along a
    line, the place's mean and longest waves round a rim): it covers both
    where the step lies on average and how far the two cameras' steps may
    differ.

    Parameters
    ----------
    b_min, b_max : float
        mm.

    Returns
    -------
    float
    """
    eb2 = (b_min * b_min + b_min * b_max + b_max * b_max) / 3.0
    return math.sqrt(2.0 * eb2 / 3.0)


def broken_rims(characteristics, inventory, part_to_camera):
    """The rims whose size is judged through a stated edge break and whose face the left camera sees.

    Parameters
    ----------
    characteristics : sequence of Characteristic
    inventory : partinspect.cad.features.Inventory
    part_to_camera : ndarray, shape (4, 4)
        The registered pose.

    Returns
    -------
    dict
        CAD feature id to ``(center, face_normal, radius, hole, size)``:
        the rim's centre (part frame, mm), its planar face's outward unit
        normal, its radius, True for a hole (False a boss) and the break's
        expected size ``(min + max) / 2``, mm. Only circles bounding one
        plane and one cylinder (split into several faces or not, one
        material side): what :mod:`partinspect.vision.band_place` can
        predict.
    """
    out = {}
    for c in characteristics:
        sizes = [c] + ([c.material.size] if getattr(c.material, "size", None) is not None else [])
        for s in sizes:
            if s.edge_break is None or s.type not in ("diameter", "radius") or s.features[0] in out:
                continue
            f = inventory[s.features[0]]
            planes = [g for g in faces_of(inventory, [s.features[0]]) if g.surface == "plane"]
            # A STEP file often splits a hole's wall into two half cylinders: one wall still, if one side.
            side = cylinder_side(inventory, s.features[0])
            if len(planes) == 1 and side is not None and seen_from_its_face(inventory, s.features[0], part_to_camera):
                out[s.features[0]] = (np.asarray(f.center, float), np.asarray(planes[0].normal, float),
                                      float(f.radius), not side, 0.5 * sum(s.edge_break))
    return out


def _inward(mesh, label, start, end):
    """Unit vector from a straight edge into one of its faces, perpendicular to it: None if the mesh has no such triangle.

    The face's triangles with two vertices on the edge have their third on
    the face's side of it.
    """
    e = (end - start) / np.linalg.norm(end - start)
    tri = mesh.faces[np.asarray(mesh.face_attributes["cad_face"]) == label]
    if not len(tri):
        return None
    v = np.asarray(mesh.vertices)[tri]  # (T, 3, 3)
    rel = v - start
    off = rel - np.einsum("tvk,k->tv", rel, e)[..., None] * e
    on = np.linalg.norm(off, axis=2) < 1e-6 * max(1.0, float(np.linalg.norm(end - start)))
    pick = on.sum(axis=1) == 2
    if not pick.any():
        return None
    t = off[pick][~on[pick]]
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    mean = t.mean(axis=0)
    return mean / np.linalg.norm(mean)


def broken_lines(inventory, mesh, line_ids, b_min, b_max):
    """The straight edges whose break :mod:`partinspect.vision.line_band` can predict: convex, between two planes.

    Parameters
    ----------
    inventory : partinspect.cad.features.Inventory
    mesh : trimesh.Trimesh
        The part's mesh with ``face_attributes["cad_face"]``
        (:func:`partinspect.cad.mesh.tessellate`).
    line_ids : iterable of str
        The CAD lines wanted (those measured).
    b_min, b_max : float
        The stated edge break, mm.

    Returns
    -------
    dict of str to tuple
        Line id -> ``(start, end, (face1, face2), (n1, n2), (t1, t2),
        size)``: end points, the faces' ids, their outward unit normals and
        the unit vectors from the edge into each face (part frame), the
        break's expected size ``(min + max) / 2``, mm. Only edges whose
        faces meet at a crease and turn away from each other (``t1 . n2 <
        0``: an external edge, which ISO 13715 breaks by removing material).
    """
    labels = {f.id: i for i, f in enumerate(inventory.faces)}
    out = {}
    for cid in line_ids:
        f = inventory[cid]
        if f.kind != "line" or f.smooth or len(f.faces) != 2:
            continue
        planes = [inventory[fid] for fid in f.faces if fid in inventory]
        if len(planes) != 2 or any(p.surface != "plane" for p in planes):
            continue
        start, end = np.asarray(f.start, float), np.asarray(f.end, float)
        inward = [_inward(mesh, labels[p.id], start, end) for p in planes]
        if any(t is None for t in inward):
            continue
        n1, n2 = (np.asarray(p.normal, float) for p in planes)
        if not (inward[0] @ n2 < -0.05 and inward[1] @ n1 < -0.05):
            continue
        out[cid] = (start, end, tuple(p.id for p in planes), (n1, n2), tuple(inward), 0.5 * (b_min + b_max))
    return out


def with_band_places(characteristics, places):
    """The characteristics with each broken rim's size given its predicted band place.

    Parameters
    ----------
    characteristics : list of Characteristic
    places : dict
        CAD feature id to an object with ``s`` and ``u``
        (:class:`partinspect.vision.band_place.BandPlace`).

    Returns
    -------
    list of Characteristic
        Sizes of those rims with ``band_place = (s, u)``, and positions at
        MMC/LMC with their size characteristic likewise.
    """
    def placed(c):
        p = places.get(c.features[0]) if c.edge_break is not None and c.type in ("diameter", "radius") else None
        return c if p is None else replace(c, band_place=(float(p.s), float(p.u)))

    out = []
    for c in characteristics:
        c = placed(c)
        if getattr(c.material, "size", None) is not None:
            c = replace(c, material=replace(c.material, size=placed(c.material.size)))
        out.append(c)
    return out


def cylinder_side(inventory, feature_id):
    """``FaceInfo.convex`` of the cylinder a circle bounds (False a hole, True a boss), None if none or several."""
    sides = cylinder_sides(faces_of(inventory, [feature_id]))
    return sides.pop() if len(sides) == 1 else None


def seen_from_its_face(inventory, feature_id, part_to_camera):
    """Whether the rim's planar face looks towards the left camera (a near rim), not away (seen through the hole).

    True when the circle bounds no planar face (nothing to tell by).
    """
    T = np.asarray(part_to_camera, float)
    camera = -T[:3, :3].T @ T[:3, 3]  # the left camera's centre, part frame
    f = inventory[feature_id]
    planes = [inventory[fid] for fid in f.faces if fid in inventory and inventory[fid].surface == "plane"]
    return not planes or any(float((camera - f.center) @ p.normal) > 0 for p in planes)
