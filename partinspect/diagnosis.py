"""Why a CAD edge was not measured, in words a quality engineer can act on.

A feature without a measurement is either out of view (outside an image,
hidden behind the part), shows too little grey-level step to be detected,
was measured and then taken out, or was seen and lost somewhere in the
chain: found only as part of a longer collinear edge, found as edge points
too few for a fit, its image feature not matched to the other image, or
measured but too far from its nominal place to be assigned to it (a hole
displaced beyond the registration's match gate; the grey-level step and
the edge points are looked for along the nominal edge, where a displaced
hole leaves none, so this is asked first).
The reason names which, so the user knows whether to re-fixture, relight
or accept it.
"""

import numpy as np

from partinspect.vision.posed import image_owners

__all__ = ["COVERED_FRACTION", "displaced_circle", "SATURATED_FRACTION", "image_feature_reasons", "edge_points_along",
           "saturation_level", "saturated_along", "unmeasured_reason", "unmeasured_reasons", "edges_found",
           "split_unseen"]

COVERED_FRACTION = 0.5
"""An image feature that runs along at least this fraction of a CAD edge's
image (within 2 px) but mostly elsewhere found that edge as part of a
longer one: collinear edges of the part (a step's two lips, a slot's two
sides in line) merge into one line in the images."""


SATURATED_FRACTION = 0.2
"""An edge with saturated pixels within ``SATURATION_REACH`` px along at
least this fraction of its image, and no edge found there, is said to be
hidden by saturation: a highlight on metal or an over-exposed face clips
the grey-level step the detector needs."""
SATURATION_REACH = 3
"""px: about the edge filter's reach either side of the edge (3 sigma)."""


def saturated_along(image, uv, top):
    """Fraction of an edge's image points with a pixel at ``top`` (saturated) within ``SATURATION_REACH`` px.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey image as recorded.
    uv : ndarray, shape (N, 2)
        The edge's projected points, distorted px; those outside the image
        do not count.
    top : float
        The grey level at which the sensor clips (:func:`saturation_level`).
    """
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        img = img.max(axis=2)
    h, w = img.shape
    uv = np.asarray(uv, float)
    ok = np.isfinite(uv).all(axis=1)
    cols, rows = np.rint(uv[ok, 0]).astype(int), np.rint(uv[ok, 1]).astype(int)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    if not inside.any():
        return 0.0
    k = 2 * SATURATION_REACH + 1
    near = cv2.dilate((img >= top).astype(np.uint8), np.ones((k, k), np.uint8))
    return float(np.mean(near[rows[inside], cols[inside]] > 0))


def saturation_level(image, bit_depth):
    """The grey level at which the sensor clips: 255 for 8 bits; for 16, the image's maximum if pixels pile up there.

    A 10-, 12- or 14-bit sensor's images are stored in 16 bits; clipped
    pixels then all read the sensor's top value, well below 65535.
    """
    if bit_depth <= 8:
        return 255.0
    img = np.asarray(image)
    top = img.max()
    return float(top) if np.count_nonzero(img == top) >= 1e-3 * img.size else 65535.0


def image_feature_reasons(stereo):
    """(side, image feature index) -> why it was not matched, in words."""
    from partinspect.vision.matching import REASONS

    out = {(u.side, u.feature): REASONS.get(u.reason, u.reason) + (f" ({u.detail})" if u.detail else "")
           for u in stereo.matching.unmatched}
    for m, why in stereo.failed:
        out[("left", m.left)] = out[("right", m.right)] = f"matched, but {why}"
    return out


def edge_points_along(measured, uv, lo, hi, reach=1.5):
    """Whether the detector's edge points run along at least COVERED_FRACTION of an edge's image.

    The edge was detected, but its points were left out of every line and
    arc: a short edge between two corners loses its ends to them
    (the segmentation keeps crowded points out of its fits) and what is left is too
    few points for a fit.
    """
    from scipy.spatial import cKDTree

    xy = measured.edges.xy
    box = np.all((xy >= lo) & (xy <= hi), axis=1)
    if len(uv) == 0 or box.sum() < 2:
        return False
    return bool(np.mean(cKDTree(xy[box]).query(uv)[0] < reach) >= COVERED_FRACTION)


def displaced_circle(feature, unassigned, reach=None):
    """An unassigned measured circle that is ``feature`` displaced, as a reason in words, or None.

    A measured circle is taken as the CAD circle moved when its radius
    agrees within the pose search's ``RADIUS_GATE``, its normal is parallel
    within ``ANGLE_GATE``, its centre lies in the nominal circle's plane
    (within ``MATCH_GATE``) and within the circle's radius of the nominal
    one (the measured rim still overlaps the nominal hole) but
    beyond ``MATCH_GATE``, the distance within which registration assigns a
    measured edge to a CAD edge.

    Parameters
    ----------
    feature : partinspect.cad.features.Feature
        The unmeasured CAD circle or arc (part frame).
    unassigned : sequence of PartFeature
        Measured circles no CAD edge was assigned to, part frame.
    reach : float, optional
        Farthest centre offset taken, mm; default the circle's radius.

    Returns
    -------
    str or None
    """
    from partinspect.cad.pose_search import ANGLE_GATE, MATCH_GATE, RADIUS_GATE

    if feature.kind == "line":
        return None
    reach = float(feature.radius) if reach is None else reach
    n = np.asarray(feature.normal, float)
    best = None
    for p in unassigned:
        c, m, r = np.asarray(p.params[:3], float), np.asarray(p.params[3:6], float), float(p.params[6])
        if abs(r - feature.radius) > RADIUS_GATE or abs(float(m @ n)) < np.cos(ANGLE_GATE):
            continue
        d = c - np.asarray(feature.center, float)
        offset = float(np.linalg.norm(d - (d @ n) * n))
        if abs(float(d @ n)) <= MATCH_GATE and MATCH_GATE < offset <= reach and (best is None or offset < best[0]):
            best = (offset, c, r)
    if best is None:
        return None
    offset, c, r = best
    where = ", ".join(f"{x:.3f}" for x in c)
    return (f"measured, but {offset:.2f} mm from its nominal place (a circle of radius {r:.3f} mm at [{where}]): "
            f"beyond the {MATCH_GATE:g} mm within which a measured edge is assigned to its CAD edge, so not matched "
            "to it; the feature is displaced (or the part is not the model)")


def unmeasured_reason(feature, vis, calib, pose, stereo, unmatched_reasons, owners=None, images=None):
    """Why a CAD feature has no measurement: out of view, or what became of its edge in the images.

    ``owners``: :func:`partinspect.vision.posed.image_owners`, to name the edge a longer image
    feature that also covers this one was measured as. ``images``: (left,
    right, bit depth), the grey images as recorded, to name saturation
    where no edge was found (:func:`saturated_along`).
    """
    # A feature measured and then taken out says why, though its visibility says little of it is in sight.
    withdrawn = dict(getattr(stereo, "withdrawn", ())).get(feature.id)
    if withdrawn:
        return f"measured, then taken out: {withdrawn}"
    if not vis.in_view:
        return "not visible: " + vis.reason()
    noise = max(float(stereo.left.noise), float(stereo.right.noise))
    if not vis.shows_edge(noise):
        clipped = [_saturation(images, side, uv) for side, uv in _projections(feature, calib, pose).items()]
        why = next((c for c in clipped if c), "its two faces look alike under this lighting")
        return (f"in view, but with too little grey-level step across it to be detected ({vis.contrast[0]:.0f} and "
                f"{vis.contrast[1]:.0f} grey levels in the left and right image; image noise {noise:.1f}): {why}")
    from scipy.spatial import cKDTree

    found, longer_sides = [], 0
    for side, uv in _projections(feature, calib, pose).items():
        tree = cKDTree(uv[np.isfinite(uv).all(axis=1)])
        feats = (stereo.left if side == "left" else stereo.right).features
        near = [i for i, f in enumerate(feats) if len(f.uv) and np.median(tree.query(f.uv)[0]) < 2.0]
        reasons = [unmatched_reasons[(side, i)] for i in near if (side, i) in unmatched_reasons]
        if not near:
            ok = np.isfinite(uv).all(axis=1)
            lo, hi = (uv[ok].min(axis=0) - 2.0, uv[ok].max(axis=0) + 2.0) if ok.any() else (np.inf, -np.inf)
            longer = [i for i, f in enumerate(feats) if len(f.uv) and np.all(f.uv.max(axis=0) >= lo)
                      and np.all(f.uv.min(axis=0) <= hi)
                      and np.mean(cKDTree(f.uv).query(uv[ok])[0] < 2.0) >= COVERED_FRACTION]
            if longer:
                i = longer[0]
                owner = (owners or {}).get((side, i))
                if owner:
                    fate = f"measured as {owner}"
                elif (side, i) in unmatched_reasons:
                    fate = f"not matched: {unmatched_reasons[(side, i)]}"
                else:
                    fate = "which matched no single CAD edge"
                found.append(f"{side} image: found as part of a longer edge that runs on past it, {fate}")
                longer_sides += 1
            elif edge_points_along(stereo.left if side == "left" else stereo.right, uv[ok], lo, hi):
                length = float(np.sum(np.linalg.norm(np.diff(uv[ok], axis=0), axis=1)))
                why = ("too few of them clear of the edges meeting it at its ends for a line fit"
                       if feature.kind == "line" else "the segmentation kept no arc of them")
                found.append(f"{side} image: edge points found along it, but {why} (its image is {length:.0f} px long)")
            else:
                clipped = _saturation(images, side, uv)
                found.append(f"no edge found along it in the {side} image" + (f": {clipped}" if clipped else ""))
        elif reasons:
            found.append(f"{side} image: {reasons[0]}")
    # Its own stretch of a longer image line found but not measured says more
    # than "found as part of a longer edge"; a reason the matching gave an
    # image feature of its own (along the epipolar lines, say) says more still.
    stretch = dict(getattr(stereo, "guided_failed", ())).get(feature.id)
    if stretch and longer_sides == len(found):
        return f"its own stretch of a longer straight edge was found in both images, but not measured: {stretch}"
    return "; ".join(found) if found else "seen in both images but not matched to the CAD model"


def _projections(feature, calib, pose):
    """{"left": uv, "right": uv}: the feature's sampled points in each image, distorted px."""
    from partinspect.cad.edge_sampling import feature_geometry, sample_edge
    from partinspect.vision.calibration import project_points

    pts, _ = sample_edge(feature.kind, feature_geometry(feature))
    X = pts @ pose[:3, :3].T + pose[:3, 3]
    return {"left": project_points(X, calib.K1, calib.D1, np.eye(3), np.zeros(3)),
            "right": project_points(X, calib.K2, calib.D2, calib.R, calib.T)}


def _saturation(images, side, uv):
    """The words to add where clipped pixels explain a missing edge; empty otherwise."""
    if images is None:
        return ""
    left, right, bit_depth = images
    image = left if side == "left" else right
    top = saturation_level(image, bit_depth)
    frac = saturated_along(image, uv, top)
    if frac < SATURATED_FRACTION:
        return ""
    return (f"the {side} image is saturated (grey level {top:g}) along {100 * frac:.0f} % of it: a highlight "
            "or an over-exposed face clips the step; lower the exposure or move the light")


def unmeasured_reasons(inv, stereo, registration, seen, calib, images=None):
    """CAD id -> why it has no measurement, for every feature registration did not assign.

    Parameters
    ----------
    inv : Inventory
    stereo : StereoResult
    registration : Registration
    seen : dict of str to FeatureVisibility
    calib : StereoCalibration
    images : (ndarray, ndarray, int), optional
        The left and right images as recorded and their bit depth, to name
        saturation (:func:`unmeasured_reason`).

    Returns
    -------
    dict of str to str
        :func:`unmeasured_reason` of each unmeasured feature.
    """
    parts = registration.features_in_part_frame()
    done = {p.cad_id for p in parts if p.cad_id is not None}
    unassigned = [p for p in parts if p.cad_id is None and p.kind == "circle"]
    reasons = image_feature_reasons(stereo)
    owners = image_owners(stereo, registration)
    return {f.id: displaced_circle(f, unassigned) or unmeasured_reason(
        f, seen[f.id], calib, registration.part_to_camera, stereo, reasons, owners, images)
            for f in inv.features if f.id not in done}


def edges_found(inv):
    """What a model without features has instead, e.g. "its edges: 1 seam (circle)"."""
    parts = [f"{n} {kind}" for kind, n in inv.skipped_edges.items()]
    parts += [f"{n} seam ({kind})" for kind, n in inv.seam_edges.items()]
    if inv.degenerated_edges:
        parts.append(f"{inv.degenerated_edges} degenerated")
    return "its edges: " + ", ".join(parts) if parts else "it has no edges"


def split_unseen(characteristics, seen, registration, measured=None):
    """The characteristics to judge, and those of edges out of view not inspected.

    General tolerances cover the whole part, but a stereo pair sees one
    side of it: a general-tolerance characteristic of an edge out of view
    that was not measured anyway is listed as not inspected, with the
    reason, rather than judged. A characteristic the spec names explicitly
    is always judged (inconclusive when unseen).

    ``measured``: the CAD ids measured, when not the registration's
    (several views: measured in any); ``seen`` then holds, per feature,
    whether any view had it in view.

    Returns
    -------
    judged : list of Characteristic
    not_inspected : list of dict
        report.json's "not_inspected" entries.
    """
    if measured is None:
        measured = set(registration.assignment["circle"].values()) | set(registration.assignment["line"].values())
    judged, not_inspected = [], []
    for c in characteristics:
        hidden = [fid for fid in c.features if not seen[fid].in_view]
        if hidden and c.source.endswith("(general tolerance)") and not any(fid in measured for fid in c.features):
            not_inspected.append({**c.to_dict(), "reason": "; ".join(f"{fid} {seen[fid].reason()}" for fid in hidden)})
        else:
            judged.append(c)
    return judged, not_inspected
