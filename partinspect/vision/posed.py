"""Measurement guided by the registered pose: what knowing where each CAD edge lies adds.

The first pass measures the images blind. Once the part's pose is
registered, every CAD edge's image is known (as polylines in distorted
pixels, :func:`partinspect.cad.projection.edge_polylines`), and three
things the blind pass cannot do become possible:

- a registered line's or arc's end points near another edge's image are
  left out and the feature refitted (a faint edge displaces a neighbour's
  points without giving points of its own; a rim running into the edge
  that hides it is pushed off by it), a rim the registration left
  unmatched too when its image lies along an unmatched CAD rim's (its
  crowded ends can push its circle past the registration's gates);
- a registered line all of whose points in one image lie on another edge's
  image, and that disagrees with the pose, is taken out with the reason;
- collinear CAD edges, one straight line in each image, are measured on
  their own stretches of it.

The inventory and registration are taken as arguments (objects with the
attributes used here); this module imports nothing of :mod:`partinspect.cad`.
"""

__all__ = ["merged_stereo", "image_owners", "posed_stereo", "cleared_stereo", "meeting", "guided_stereo"]


def merged_stereo(base, new, registration, ids):
    """``base`` (a StereoResult) with the features of ``new`` that ``registration`` assigned to ``ids`` added.

    The added 3D features' image features are appended to ``base``'s of
    each image (their indices renumbered); each carries its own edge data
    and filter scale (:class:`~partinspect.vision.stereo.EdgeFeature`), so
    the result is measured, drawn and Monte Carlo sampled as one. Edges,
    segments, matching and failures stay ``base``'s: what the report says
    of unmatched image features is said of the base round's.
    """
    from dataclasses import replace

    picks = [registration.measured_feature(kind, i) for kind in ("circle", "line")
             for i, cid in sorted(registration.assignment[kind].items()) if cid in ids]
    nl, nr = len(base.left.features), len(base.right.features)
    left = replace(base.left, features=list(base.left.features) + [new.left.features[f.left] for f in picks])
    right = replace(base.right, features=list(base.right.features) + [new.right.features[f.right] for f in picks])
    added = tuple(replace(f, left=nl + j, right=nr + j) for j, f in enumerate(picks))
    return replace(base, left=left, right=right, features=tuple(base.features) + added)


def image_owners(stereo, registration):
    """(side, image feature index) -> the CAD id its 3D feature was registered as."""
    owners = {}
    for kind in ("circle", "line"):
        for i, cid in registration.assignment[kind].items():
            f = registration.measured_feature(kind, i)
            owners[("left", f.left)] = owners[("right", f.right)] = cid
    return owners


def posed_stereo(stereo, registration, seen, inv, calib, polylines, outlines=None):
    """What the registered pose adds to ``stereo``: :func:`cleared_stereo`, then :func:`guided_stereo`.

    ``seen`` as theirs; ``polylines``: every CAD edge's image at the
    registered pose (:func:`partinspect.cad.projection.edge_polylines`),
    shared by both; ``outlines`` as :func:`cleared_stereo`'s.

    Returns
    -------
    stereo : StereoResult
    found : dict of str to int
        Of :func:`guided_stereo`.
    cleared, withdrawn : dict
        Of :func:`cleared_stereo`.
    """
    cleared, ends, withdrawn = cleared_stereo(stereo, registration, seen, inv, calib, polylines, outlines)
    more, found = guided_stereo(cleared, registration, seen, inv, calib, polylines)
    return more, found, ends, withdrawn


def cleared_stereo(stereo, registration, seen, inv, calib, polylines, outlines=None):
    """``stereo`` with its registered lines and arcs fitted again clear of the other edges' images.

    Under the registered pose every CAD edge's image is known, faint ones
    too, whose grey step displaces a line's points (at its ends, or along a
    stretch where a face seen near grazing incidence runs beside it)
    without giving edge points of its own
    (:func:`partinspect.vision.guided.clear_line_ends`),
    and the occluding edge a rim runs into where it passes out of sight
    (:func:`partinspect.vision.guided.clear_arc_ends`). A measured rim the
    registration left unmatched is cleared as the CAD rim whose image it
    lies along, if that rim is unmatched too
    (:func:`partinspect.vision.guided.rims_along`): a short arc's circle
    follows its ends, and crowded ends can push it past the registration's
    gates, which judge it again once it is cleared.
    ``seen``: the visibility of each CAD feature, to take in each image
    only the edges it sees; None to take every edge (more points left out
    near hidden edges' images, never fewer). ``polylines``: every CAD
    edge's image at the registered pose
    (:func:`partinspect.cad.projection.edge_polylines`). ``outlines``: the
    curved faces' occluding contours in sight at that pose
    (:func:`partinspect.cad.outlines.outline_images`), grey steps that are
    no CAD edge but crowd the edges they run into all the same; None for
    none.

    A line that disagrees with the pose the other features give (a
    registration outlier) and all of whose points in one image lie on
    another edge's image is taken out, with the reason: that image's
    feature is the other edge's, paired with this one's in the other
    image (a face seen nearly edge-on puts two edges on one image line,
    and the "line" measured would lie between two edges). So is a rim
    that one image sees only crowded by another edge's image
    (:func:`partinspect.vision.guided.clear_arc_ends`'s ``crowded``).

    Returns
    -------
    stereo : StereoResult
        ``withdrawn`` holds the lines taken out and why.
    cleared : dict of str to (int, int)
        CAD id -> points left out in the left and the right image.
    withdrawn : dict of str to str
        CAD id -> why its line was taken out.
    """
    from dataclasses import replace

    from partinspect.vision.guided import clear_arc_ends, clear_line_ends, rims_along

    lines = registration.cad_ids(stereo.features, "line")
    arcs = registration.cad_ids(stereo.features, "circle")
    if not lines and not arcs:
        return stereo, {}, {}
    by_id = {f.id: f for f in inv.features}
    images = {}
    for f in inv.features:
        shown = (1.0, 1.0) if seen is None else seen[f.id].seen
        if max(shown) > 0:
            images[f.id] = tuple(uv if v > 0 else uv[:0] for uv, v in zip(polylines[f.id], shown))
    # A smooth edge (tangent faces) shows no grey step of its own: it crowds no rim.
    steps = {fid: uv for fid, uv in images.items() if not by_id[fid].smooth or fid in arcs.values()}
    images.update(outlines or {})
    steps.update(outlines or {})
    # A rim whose crowded ends pushed its circle past the registration's
    # gates is cleared too: the registration judges it again.
    at = [k for k, f in enumerate(stereo.features) if f.kind != "line"]
    free = {f.id for f in inv.features if f.kind != "line" and f.id not in arcs.values()}
    arcs = {**arcs, **rims_along(stereo, [at[i] for i in registration.unmatched["circle"]], free, steps)}
    stereo, arc_cleared, crowded = clear_arc_ends(stereo, calib, arcs, steps,
                                                  meets={cid: meeting(by_id[cid], inv.features) for cid in arcs.values()})
    stereo, cleared, covered = clear_line_ends(stereo, calib, lines, images)
    cleared = {**arc_cleared, **cleared}
    withdrawn = dict(crowded)
    for cid, (side, other) in covered.items():
        if cid in registration.outliers and other is not None:
            c2, n = registration.outliers[cid]
            withdrawn[cid] = (f"its points in the {side} image all lie on the image of {other}, and its 3D line "
                              f"disagreed with the pose the other features give (chi-square {c2:.0f} over {n} "
                              f"residuals): {other}'s image paired with its own in the other image")
    if not withdrawn:
        return stereo, cleared, {}
    gone = {k for k, cid in (*lines.items(), *arcs.items()) if cid in withdrawn}
    stereo = replace(stereo, features=tuple(f for k, f in enumerate(stereo.features) if k not in gone),
                     withdrawn=tuple(withdrawn.items()))
    return stereo, cleared, withdrawn


def meeting(feature, features, tol=1e-3):
    """Ids of the edges with an end point within ``tol`` mm of one of ``feature``'s (none for a whole circle)."""
    import numpy as np

    if feature.start is None:
        return set()
    ends = np.array([feature.start, feature.end], float)
    out = set()
    for g in features:
        if g.id == feature.id or g.start is None:
            continue
        d = np.linalg.norm(ends[:, None, :] - np.array([g.start, g.end], float)[None], axis=2)
        if d.min() < tol:
            out.add(g.id)
    return out


def guided_stereo(stereo, registration, seen, inv, calib, polylines):
    """``stereo`` with the unmeasured line edges in view measured on their stretches of longer image lines.

    Collinear edges of a part merge into one line in each image, whose 3D
    line then matches no single CAD edge; under the registered pose each
    edge's image picks its own stretch
    (:func:`partinspect.vision.guided.guided_lines`). ``seen``: the
    visibility of each CAD feature (:func:`partinspect.cad.visibility.visibility`),
    or None to look for every unmeasured line edge: a hidden one takes no
    points where a seen edge's image runs near its own (every line edge's
    image is given to ``guided_lines`` to keep them apart). ``polylines``:
    every CAD edge's image at the registered pose
    (:func:`partinspect.cad.projection.edge_polylines`).

    Returns
    -------
    stereo : StereoResult
    found : dict of str to int
        CAD id -> index of the 3D line measured for it (empty: ``stereo``
        returned unchanged).
    """
    from partinspect.vision.guided import guided_lines

    done = {cid for kind in ("circle", "line") for cid in registration.assignment[kind].values()}
    todo = [f for f in inv.features if f.kind == "line" and f.id not in done and (seen is None or seen[f.id].in_view)]
    if not todo:
        return stereo, {}
    # Every line edge's image, hidden ones too: a point near two edges' images is either's.
    others = {f.id: polylines[f.id] for f in inv.features if f.kind == "line"}
    expected = {f.id: others[f.id] for f in todo}
    more, found, _ = guided_lines(stereo, calib, expected, set(image_owners(stereo, registration)), others=others)
    return more, found
