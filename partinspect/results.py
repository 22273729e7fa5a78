"""A run's measurement objects as report data: features, registration, figures.

Turns what the chain produced (the stereo result, the registration, the
decisions) into the plain entries report.json and the HTML report's
figures are written from. Every geometry in report.json is in the part
frame; the figures' overlays are in distorted pixels, each measured
feature drawn as its 3D fit projected back through the lens model, so the
overlay shows the reconstruction, not just the detected edge.
"""

import numpy as np

from partinspect.cad.registration import feature_order
from partinspect.reports.assemble import mat, vec

__all__ = ["nominal_geometry", "characteristic_entry", "registration_entry", "ambiguity_entry", "feature_entries",
           "edge_break_entries", "curve_3d", "figure_data", "fused_feature_entries", "view_entry"]

# The words report.json writes, in one place: the statuses and edge-break
# readings a reader (and reports/html.py) matches on, and each reason
# sentence, so that one wording serves every entry that gives it.
MEASURED = "measured"
NOT_MEASURED = "not measured"
UNMATCHED = "unmatched"
AT_APPARENT_EDGE = "apparent edge"
AT_BAND_PLACE = "predicted band place"
DECIDES_POSE = "; it would tell which of the poses that fit is right, were it measured (see the registration)"
ON_ITS_STRETCH = ("measured on its own stretch of a longer straight edge in the images (edges in line with it merge "
                  "into one there), the stretch its CAD edge's image covers")
UNPREDICTED = ("its place across the band is not predicted: the chain predicts it on a toleranced rim seen from its "
               "face and on a straight edge between two planar faces")
NOT_PREDICTABLE = "its place across the band could not be predicted (too little of it or of its faces seen)"
NO_BETTER_THAN_UNIFORM = "its place is predicted no better than uniform across the band"


def nominal_geometry(feature):
    """The CAD geometry of a feature as report.json writes it (part frame, mm)."""

    def vec(v):
        return [round(float(x), 9) for x in v]

    if feature.kind == "line":
        return {"start": vec(feature.start), "end": vec(feature.end)}
    g = {"center": vec(feature.center), "normal": vec(feature.normal), "radius": round(float(feature.radius), 9)}
    if feature.kind == "arc":
        g.update(start=vec(feature.start), end=vec(feature.end))
    return g


def characteristic_entry(decision):
    """report.json's entry of one decided characteristic, with one reason a reader can act on."""
    d = decision.to_dict()
    # One "reason" a reader can act on: why it is not measured, else why it was decided so.
    d["reason"] = d.get("reason") or decision.reason
    return d


def registration_entry(reg, datum_reference=None):
    """report.json's "registration": the pose, its uncertainty and fit statistics.

    ``datum_reference``, where the datums come from
    (`partinspect.tolerances.from_pmi.datum_entry`), is added when given.
    """
    std = reg.pose_std
    return {
        "part_to_camera": mat(reg.part_to_camera, 12),
        "rms": round(float(reg.rms), 9),
        "weighted_rms": round(float(reg.weighted_rms), 6),
        "chi2": round(float(reg.chi2), 6),
        "dof": int(reg.dof),
        "datums": list(reg.datums),
        "outliers": [{"feature": fid, "chi2": round(float(c2), 3), "residuals": int(n)}
                     for fid, (c2, n) in sorted(reg.outliers.items())],
        "pose_covariance": mat(reg.pose_cov),
        "pose_covariance_scale": round(float(reg.pose_cov_scale), 6),
        "rotation_std_deg": vec(np.degrees(std[:3]), 9),
        "translation_std": vec(std[3:], 9),
        "frame": "pose error xi = (rotation vector [rad], translation [mm]) in the part frame",
        **({"symmetry": reg.symmetry} if reg.symmetry else {}),
        **({"ambiguity": ambiguity_entry(reg)} if reg.competing else {}),
        **({"datum_reference": datum_reference} if datum_reference else {}),
    }


def ambiguity_entry(reg):
    """report.json's "registration.ambiguity": the poses that explain the features as well as the chosen one."""
    return {
        "summary": reg.ambiguity,
        "deciding_features": sorted({fid for c in reg.competing for fid in c.deciding}, key=feature_order),
        "competing": [{
            "part_to_camera": mat(c.registration.part_to_camera, 12),
            "angle_deg": round(c.angle, 6),
            "shift": round(c.shift, 6),
            "chi2": round(float(c.registration.chi2), 6),
            "dof": int(c.registration.dof),
            "weighted_rms": round(float(c.registration.weighted_rms), 6),
            "deciding_features": list(c.deciding),
            "assignment_differs": _assignment_differs(reg, c.registration),
        } for c in reg.competing],
    }


def _assignment_differs(reg, other):
    """CAD ids that the two registrations assign different measured features to (sorted)."""
    def table(r):
        out = {}
        for kind, pairs in r.assignment.items():
            for i, fid in pairs.items():
                out.setdefault(fid, set()).add((kind, i))
        return out

    a, b = table(reg), table(other)
    return sorted((fid for fid in set(a) | set(b) if a.get(fid) != b.get(fid)), key=feature_order)


def feature_entries(inv, stereo, registration, seen, decisions, reasons, edge_break=None):
    """report.json's "features": nominal and measured geometry (part frame) with covariances.

    ``reasons``: CAD id -> why it was not measured
    (:func:`partinspect.diagnosis.unmeasured_reasons`), for every feature
    the registration did not assign. ``edge_break``: CAD id -> where a
    measured feature's edge was taken on its broken edge
    (:func:`edge_break_entries`), its entry's ``"edge_break"``.
    """
    parts = {p.cad_id: p for p in registration.features_in_part_frame() if p.cad_id is not None}
    index = {"circle": [f for f in stereo.features if f.kind != "line"], "line": [f for f in stereo.features if f.kind == "line"]}
    worst = _worst_decisions(decisions)
    deciding = {fid for c in getattr(registration, "competing", ()) for fid in c.deciding}
    out = []
    for f in inv.features:
        entry = _entry_of(f, seen)
        p = parts.get(f.id)
        if p is None:
            entry.update(measured=None, status=NOT_MEASURED, reason=reasons[f.id])
            if f.id in deciding:
                entry["reason"] += DECIDES_POSE
        else:
            f3 = index[p.kind][p.index]
            m = _measured_geometry(p)
            m.update(n_points=int(len(f3.correspondences)), datum=bool(p.datum), measured_as=f3.kind)
            entry.update(measured=m, status=worst.get(f.id, MEASURED))
            if f3.guided is not None:
                entry["reason"] = ON_ITS_STRETCH
            if edge_break and f.id in edge_break:
                entry["edge_break"] = edge_break[f.id]
        out.append(entry)
    return out


def edge_break_entries(stereo, registration, calib, rims, lines):
    """Where each measured feature's edge was taken on its broken edge: report.json's features' ``"edge_break"``.

    Under a stated edge break every edge carries the whole band as a Type B
    (:func:`partinspect.vision.band_modes.edge_band`) unless its feature
    was moved onto the sharp edge's image by its predicted place
    (:func:`partinspect.vision.band_place.rims_at_sharp_edge`,
    :func:`partinspect.vision.line_band.lines_at_sharp_edge`): the entry
    says which, how far the apparent edge lay from the sharp edge's image
    (towards the face, as the points were moved back by it), and the Type
    B each point carries, so a reader sees what was corrected and what
    carried.

    Parameters
    ----------
    stereo : StereoResult
        ``edge_break``: the uniform band's Type B, mm (None: no break stated).
    registration : Registration
        The final one (its pose converts a line's offsets to mm).
    calib : StereoCalibration
    rims : dict of str to (BandPlace or None, float, bool)
        CAD id of a broken rim whose place the chain predicts -> its place
        (:class:`~partinspect.vision.band_place.BandPlace`, None where not
        predicted), the break's expected size (mm) and whether its points
        were moved.
    lines : dict of str to (LinePlace or None, BrokenLine, bool)
        Likewise for the broken straight edges
        (:mod:`partinspect.vision.line_band`), with the edge.

    Returns
    -------
    dict of str to dict
        CAD id -> entry, every measured feature; empty where no break is stated.
    """
    from partinspect.vision.band_place import UNIFORM_STD, pixel_size

    if stereo.edge_break is None:
        return {}
    band = float(stereo.edge_break)
    kept = {"measured_at": AT_APPARENT_EDGE, "standard_uncertainty": round(band, 6), "reason": UNPREDICTED}
    out = {}
    for p in registration.features_in_part_frame():
        if p.cad_id is None:
            continue
        place, edge, moved = (rims if p.kind == "circle" else lines).get(p.cad_id, (None, None, False))
        entry = dict(kept)
        if place is None and edge is not None:
            entry["reason"] = NOT_PREDICTABLE
        elif place is not None and p.kind == "circle":
            entry = _rim_entry(place, edge, moved, band, UNIFORM_STD)
        elif place is not None:
            mid = p.point if p.start is None else 0.5 * (p.start + p.end)
            entry = _line_entry(place, edge, moved, band, pixel_size(calib, registration.part_to_camera, mid))
        out[p.cad_id] = entry
    return out


def _offset_ranges(offsets):
    """Per image, [least, largest] of a place's offsets, px (None where none is finite)."""
    out = []
    for o in offsets:
        o = np.asarray(o, float)
        o = o[np.isfinite(o)]
        out.append(vec([o.min(), o.max()], 4) if o.size else None)
    return out


def _rim_entry(place, size, moved, band, uniform):
    """A broken rim's ``"edge_break"``: its band place ``s`` (share of the break from the wall), offset, Type B."""
    entry = {"break_size": round(size, 6), "band_place": round(place.s, 4),
             "band_place_standard_uncertainty": round(place.u, 4),
             "offset": round(place.s * size, 6), "offset_px": _offset_ranges(place.offsets)}
    if moved:
        return {"measured_at": AT_BAND_PLACE, **entry,
                "standard_uncertainty": round(place.u_point * size, 6), "band_standard_uncertainty": round(band, 6)}
    why = (NO_BETTER_THAN_UNIFORM if max(place.u, place.u_point) >= uniform
           else "its fit at the predicted place failed")
    return {"measured_at": AT_APPARENT_EDGE, **entry, "standard_uncertainty": round(band, 6),
            "reason": f"{why}: its size is corrected by the place, its points keep the band"}


def _line_entry(place, line, moved, band, pixel):
    """A broken straight edge's ``"edge_break"``: its offset (mm, px per image, towards its first face) and Type B."""
    medians = [float(np.nanmedian(o)) * px for o, px in zip(place.offsets, pixel) if np.isfinite(o).any()]
    entry = {"break_size": round(line.size, 6), "offset": round(float(np.mean(medians)), 6),
             "offset_px": _offset_ranges(place.offsets), "towards_face": line.faces[0]}
    if moved:
        return {"measured_at": AT_BAND_PLACE, **entry, "standard_uncertainty": round(place.u, 6),
                "standard_uncertainty_px": vec(place.u_px, 4), "band_standard_uncertainty": round(band, 6)}
    why = (NO_BETTER_THAN_UNIFORM if place.u >= band
           else "its fit at the predicted place, or the pose registered on it, failed")
    return {"measured_at": AT_APPARENT_EDGE, **entry, "standard_uncertainty": round(band, 6), "reason": why}


def _entry_of(f, seen):
    """A feature's report entry before its measurement: id, kind, nominal geometry, visibility."""
    return {"id": f.id, "kind": f.kind, "nominal": nominal_geometry(f), "visibility": {
        "left": round(seen[f.id].seen[0], 3), "right": round(seen[f.id].seen[1], 3)}}


def _measured_geometry(p):
    """A part-frame feature's measured geometry and covariance (a line's extent where it has one)."""
    if p.kind == "circle":
        return {"center": vec(p.center), "normal": vec(p.normal), "radius": round(p.radius, 9),
                "covariance": mat(p.covariance), "radius_std": float(f"{p.radius_std:.6g}")}
    return {"point": vec(p.point), "direction": vec(p.direction),
            **({"start": vec(p.start), "end": vec(p.end)} if p.start is not None else {}),
            "covariance": mat(p.covariance)}


def _worst_decisions(decisions):
    worst = {}
    rank = {"pass": 0, "inconclusive": 1, "fail": 2}
    for d in decisions:
        for fid in d.evaluation.characteristic.features:
            if rank[d.decision] >= rank.get(worst.get(fid), -1):
                worst[fid] = d.decision
    return worst


def fused_feature_entries(inv, fused, measured, names, seen, decisions, reasons):
    """report.json's "features" of a multi-view run: each measured feature combined over its views.

    Parameters
    ----------
    inv : Inventory
    fused : dict
        CAD id -> :class:`~partinspect.tolerances.fusion.FusedFeature`.
    measured : list
        Per view, its measurement (``stereo``, ``registration``).
    names : list of str
        The views' names, same order.
    seen : dict
        CAD id -> visibility over the views (``seen``: the best view's
        fractions, left and right).
    decisions : list of Decision
    reasons : dict
        CAD id -> why no view measured it.
    """
    worst = _worst_decisions(decisions)
    out = []
    for f in inv.features:
        entry = _entry_of(f, seen)
        p = fused.get(f.id)
        if p is None:
            entry.update(measured=None, status=NOT_MEASURED, reason=reasons[f.id])
            out.append(entry)
            continue
        m = _measured_geometry(p)
        n_points, datum, kinds = 0, False, set()
        for v, part, _, _ in p.contributions:
            stereo = measured[v].stereo
            f3 = [g for g in stereo.features if (g.kind == "line") == (part.kind == "line")][part.index]
            n_points += len(f3.correspondences)
            datum |= bool(part.datum)
            kinds.add(f3.kind)
        m.update(n_points=int(n_points), datum=datum, measured_as="/".join(sorted(kinds)),
                 views=[names[v] for v in p.views])
        if p.rejected:
            m["left_out"] = [{"view": names[r["view"]], "reason": r["reason"]} for r in p.rejected]
        entry.update(measured=m, status=worst.get(f.id, MEASURED))
        out.append(entry)
    return out


def view_entry(name, folder, registration, fused, index, problem=None):
    """report.json's entry of one view: its folder, pose and fit, the features it gave, or why it was left out."""
    entry = {"name": name, "folder": str(folder)}
    if registration is None:
        entry.update(used=False, reason=problem)
        return entry
    ids = sorted(p.cad_id for p in registration.features_in_part_frame() if p.cad_id is not None)
    entry.update(
        used=True,
        part_to_camera=mat(registration.part_to_camera, 12),
        rotation_std_deg=vec(np.degrees(registration.pose_std[:3]), 9),
        translation_std=vec(registration.pose_std[3:], 9),
        rms=round(float(registration.rms), 9),
        weighted_rms=round(float(registration.weighted_rms), 6),
        pose_covariance_scale=round(float(registration.pose_cov_scale), 6),
        features_measured=len(set(ids)),
        features=sorted(set(ids)),
        features_combined=sorted(fid for fid, f in fused.items() if index in f.views),
        features_left_out=sorted(fid for fid, f in fused.items() if any(r["view"] == index for r in f.rejected)),
    )
    return entry


def curve_3d(f, n=96):
    """Points along a measured Feature3D (rig frame, mm) for drawing."""
    if f.kind == "line":
        return f.start + np.linspace(0.0, 1.0, n)[:, None] * (f.end - f.start)
    from partinspect.frames import orthonormal_frame

    e1, e2, _ = orthonormal_frame(f.normal)
    a = np.linspace(f.angle_start, f.angle_end, n)
    return f.center + f.radius * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)


def view_figure(name, inputs, measured, features):
    """One view's entry of the report's view strip: its left image and the curves it measured there.

    ``features``: the fused report entries, whose status the curves take.
    """
    overlays = feature_overlays(inputs.calib, measured.stereo, measured.registration, features, sides=("left",))
    return {"name": name, "image": inputs.left, "overlays": overlays}


def _cad_labels(stereo, registration):
    """CAD id of each registered measured feature, keyed by ``id(feature)``."""
    cad_of = {}
    for kind, key in (("circle", lambda f: f.kind != "line"), ("line", lambda f: f.kind == "line")):
        measured = [f for f in stereo.features if key(f)]
        for i, cid in registration.assignment[kind].items():
            cad_of[id(measured[i])] = cid
    return cad_of


def feature_overlays(calib, stereo, registration, features, sides=("left", "right")):
    """The curves to draw over the images: each measured feature's 3D fit projected back, then the unmatched.

    Distorted pixels; each curve's status is its feature's in ``features``
    (report entries), "unmatched" where it found no CAD edge.
    """
    from partinspect.vision.calibration import project_points

    status = {e["id"]: e["status"] for e in features}
    cad_of = _cad_labels(stereo, registration)
    cams = {"left": (calib.K1, calib.D1, np.eye(3), np.zeros(3)), "right": (calib.K2, calib.D2, calib.R, calib.T)}
    overlays, used = [], {"left": set(), "right": set()}
    for f in stereo.features:
        label = cad_of.get(id(f), "")
        X = curve_3d(f)
        for side, index in (("left", f.left), ("right", f.right)):
            if side not in sides:
                continue
            used[side].add(index)
            K, D, R, t = cams[side]
            overlays.append({"image": side, "xy": project_points(X, K, D, R, t), "kind": f.kind, "label": label,
                             "status": status.get(label, MEASURED) if label else UNMATCHED})
    for side in sides:
        for i, imf in enumerate((stereo.left if side == "left" else stereo.right).features):
            if i not in used[side]:
                overlays.append({"image": side, "xy": imf.uv, "kind": imf.kind, "label": "", "status": UNMATCHED})
    return overlays


def figure_data(left, right, calib, inv, stereo, registration, features):
    """The data behind the report's figures (:mod:`partinspect.reports.figures`).

    Images as recorded; overlays in distorted pixels (each measured feature
    is its 3D fit projected back through the lens model, so the overlay
    shows the reconstruction, not just the detected edge); 3D data in the
    part frame.
    """
    from partinspect.cad.edge_sampling import feature_geometry, sample_edge

    status = {e["id"]: e["status"] for e in features}
    cad_of = _cad_labels(stereo, registration)
    residuals = []
    for f in stereo.features:
        label = cad_of.get(id(f), "")
        for side, index in (("left", f.left), ("right", f.right)):
            fit = (stereo.left if side == "left" else stereo.right).features[index].fit
            residuals.append({"label": label or f"unregistered {f.kind}", "image": side, "residuals": np.asarray(fit.residuals),
                              "sigma": float(np.median(fit.point_std))})
    overlays = feature_overlays(calib, stereo, registration, features)
    points3d = [{"label": p.cad_id, "points": p.points, "covs": p.point_covs, "status": status.get(p.cad_id, MEASURED)}
                for p in registration.features_in_part_frame() if p.cad_id is not None and p.points is not None]
    cad_edges = [{"label": f.id, "polyline": sample_edge(f.kind, feature_geometry(f), n=120)[0]} for f in inv.features]
    return {"left": left, "right": right, "overlays": overlays, "residuals": residuals, "points3d": points3d, "cad_edges": cad_edges}
