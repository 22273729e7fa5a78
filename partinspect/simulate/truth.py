"""Ground truth of a synthetic render: pose, settings, and every feature.

For every feature of the part's inventory the truth gives its nominal
geometry (the STEP model), its as-rendered geometry (after the requested
deviations) and how well each camera sees it:

- ``in_image``: fraction of points along the edge that project inside the
  image (pixel centres' span, ``0 <= u <= W - 1``, ``0 <= v <= H - 1``);
- ``unoccluded``: fraction whose line of sight is free: a ray cast from the
  camera centre towards the point hits nothing more than
  ``OCCLUSION_TOLERANCE`` before it;
- ``contrast``: fraction where the noiseless shading differs by at least
  ``MIN_CONTRAST`` grey levels between the two sides of the projected edge
  (``CONTRAST_OFFSET`` pixels along the image normal on either side), each
  side showing one face from 0.25 px out to that distance (or faces
  shaded alike: ``NEIGHBOUR_STEP_FRACTION``) and the face
  changing across the edge: an edge between two faces that meet
  tangentially shows none, nor does a stretch of edge whose image runs
  within 1.5 px of another edge (as where a hole's bottom rim passes
  behind its top rim); judged in the image only (a sample outside it
  counts as without contrast);
- ``visible``: fraction passing all three at once.

``visible_both`` is true when ``visible`` is at least ``VISIBLE_FRACTION``
in both images.

All geometry is in the part frame (the STEP frame), mm; the JSON rounds
floats to 1e-9 mm so the file is the same bytes on every run.
"""

import json
import math
import re

import numpy as np

from partinspect.simulate.render import DEFAULT_SHADING, camera_in_part, cast, pixel_rays, shade
from partinspect.vision.calibration import project_points

__all__ = [
    "SCHEMA",
    "MIN_CONTRAST",
    "CONTRAST_OFFSET",
    "NEIGHBOUR_STEP_FRACTION",
    "OCCLUSION_TOLERANCE",
    "VISIBLE_FRACTION",
    "feature_geometry",
    "sample_edge",
    "edge_visibility",
    "feature_visibility",
    "deviated_geometry",
    "make_truth",
    "to_json",
]

SCHEMA = "truth/1"
MIN_CONTRAST = 20.0
"""Grey levels across an edge for it to count as showing."""
CONTRAST_OFFSET = 1.5
"""Pixels from the edge, on each side, where the contrast is taken."""
NEIGHBOUR_STEP_FRACTION = 0.1
"""A face boundary within ``CONTRAST_OFFSET`` of an edge, on one side, counts
as a second edge when its grey step is at least this fraction of the edge's
contrast. On the sample parts (default pose and light) such boundaries step
by under 0.05 of the edge's contrast (a hole's wall and the face seen past
it, shaded alike; the 2D chain finds the edge there) or by 0.27 and more."""
OCCLUSION_TOLERANCE = 0.05
"""mm: a surface this little in front of an edge point does not hide it
(the tessellation's chord error, seen at grazing incidence, is below it)."""
VISIBLE_FRACTION = 0.5
"""Fraction of an edge that must be visible in an image for ``visible_both``."""
_SAMPLE_SPACING = 0.25  # mm between edge samples
_MIN_SAMPLES, _MAX_SAMPLES = 24, 400


def feature_geometry(feature):
    """The geometry of an inventory feature as a dict of arrays.

    Parameters
    ----------
    feature : partinspect.cad.features.Feature

    Returns
    -------
    dict
        Lines: ``start``, ``end``. Circles: ``center``, ``normal``,
        ``radius``. Arcs: those of a circle plus ``start``, ``end``,
        ``angle_start``, ``angle_end`` (radians, counter-clockwise about
        ``normal`` from ``reference_direction(normal)``). Part frame, mm.
    """
    if feature.kind == "line":
        return {"start": np.array(feature.start, float), "end": np.array(feature.end, float)}
    g = {"center": np.array(feature.center, float), "normal": np.array(feature.normal, float), "radius": float(feature.radius)}
    if feature.kind == "arc":
        g.update(
            start=np.array(feature.start, float),
            end=np.array(feature.end, float),
            angle_start=float(feature.angle_start),
            angle_end=float(feature.angle_end),
        )
    return g


def _circle_axes(normal):
    from partinspect.frames import orthonormal_frame

    return tuple(orthonormal_frame(normal)[:2])


def sample_edge(kind, geometry, n=None):
    """Points and unit tangents along an edge, away from its ends.

    Parameters
    ----------
    kind : {"line", "circle", "arc"}
    geometry : dict
        As :func:`feature_geometry` returns.
    n : int, optional
        Number of samples; default one per 0.25 mm, between 24 and 400.
        They sit at the middles of ``n`` equal pieces, so no sample falls on
        an end point (a corner).

    Returns
    -------
    points, tangents : ndarray, shape (n, 3)
        Part frame, mm; unit tangents.
    """
    if kind == "line":
        a, b = geometry["start"], geometry["end"]
        extent = float(np.linalg.norm(b - a))
    else:
        c, r = geometry["center"], geometry["radius"]
        t0, t1 = (0.0, 2 * math.pi) if kind == "circle" else (geometry["angle_start"], geometry["angle_end"])
        extent = r * (t1 - t0)
    if n is None:
        n = int(np.clip(math.ceil(extent / _SAMPLE_SPACING), _MIN_SAMPLES, _MAX_SAMPLES))
    s = (np.arange(n) + 0.5) / n
    if kind == "line":
        return a + s[:, None] * (b - a), np.repeat(((b - a) / extent)[None], n, axis=0)
    x, y = _circle_axes(geometry["normal"])
    t = t0 + s * (t1 - t0)
    cos, sin = np.cos(t)[:, None], np.sin(t)[:, None]
    return c + r * (cos * x + sin * y), -sin * x + cos * y


def edge_visibility(rs, calib, index, part_to_camera, points, tangents, shading=DEFAULT_SHADING):
    """Per-point visibility of edge samples in one camera.

    Parameters
    ----------
    rs : partinspect.simulate.render.RaycastScene
        The part as rendered (deviations applied).
    calib : StereoCalibration
    index : int
        0 left, 1 right.
    part_to_camera : ndarray, shape (4, 4)
        Part frame to left camera frame.
    points, tangents : ndarray, shape (N, 3)
        Edge samples and unit tangents, part frame.
    shading : Shading

    Returns
    -------
    dict of ndarray of bool, shape (N,)
        ``in_image``, ``unoccluded``, ``contrast`` (see the module notes),
        and ``uv`` (N, 2): the samples' distorted pixel positions,
        ``normal_uv`` (N, 2): unit normals of the projected edge, and
        ``side_label`` (N, 2) int, ``side_grey`` (N, 2): the face seen and
        its noiseless grey level ``CONTRAST_OFFSET`` px either side
        (against, along the normal), -1 for the background, -2 and NaN for
        samples outside the image.
    """
    K, D, R, t = camera_in_part(calib, index, part_to_camera)
    w, h = calib.image_size
    uv = project_points(points, K, D, R, t)
    # Image direction of the edge by a central difference along its tangent.
    step = 1e-3
    du = project_points(points + step * tangents, K, D, R, t) - project_points(points - step * tangents, K, D, R, t)
    du /= np.maximum(np.linalg.norm(du, axis=1), 1e-300)[:, None]
    normal = np.stack([-du[:, 1], du[:, 0]], axis=1)
    in_image = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)

    origin = -R.T @ t
    ray = points - origin
    dist = np.linalg.norm(ray, axis=1)
    hits = cast(rs, origin, ray / dist[:, None])
    unoccluded = hits.distance >= dist - OCCLUSION_TOLERANCE

    # Contrast: the shading CONTRAST_OFFSET px either side differs enough, and
    # each side is one face out to that distance (no other edge within it),
    # with a change of face across the edge itself.
    light = np.asarray(part_to_camera, float)[:3, :3].T @ shading.direction()
    contrast = np.zeros(len(points), bool)
    side_label = np.full((len(points), 2), -2)
    side_grey = np.full((len(points), 2), np.nan)
    # Only samples in the image: far outside it a strong distortion model can
    # fold over, and its pixels cannot be mapped back to rays.
    ok = in_image
    if ok.any():
        offsets = np.array([-CONTRAST_OFFSET, -0.25, 0.25, CONTRAST_OFFSET])
        q = uv[ok, None, :] + offsets[None, :, None] * normal[ok, None, :]
        o, d = pixel_rays(q.reshape(-1, 2), K, D, R, t)
        hits = cast(rs, o, d)
        g = shade(rs, hits, d, light, shading).astype(float).reshape(-1, 4)
        lab = hits.label.reshape(-1, 4)
        step = np.abs(g[:, 3] - g[:, 0])
        # A face boundary on one side whose grey step is a small fraction
        # of the edge's own shows no second edge (two faces shaded alike,
        # as a hole's wall and the floor seen past it): it neither hides
        # the edge nor disturbs its points.
        quiet = NEIGHBOUR_STEP_FRACTION * step
        one_face = [(lab[:, i] == lab[:, j]) | (np.abs(g[:, i] - g[:, j]) < quiet) for i, j in ((0, 1), (2, 3))]
        clean = one_face[0] & one_face[1] & (lab[:, 1] != lab[:, 2])
        contrast[ok] = clean & (step >= MIN_CONTRAST)
        side_label[ok] = lab[:, [0, 3]]
        side_grey[ok] = g[:, [0, 3]]
    return {"in_image": in_image, "unoccluded": unoccluded, "contrast": contrast, "uv": uv, "normal_uv": normal,
            "side_label": side_label, "side_grey": side_grey}


def feature_visibility(rs, calib, part_to_camera, kind, geometry, shading=DEFAULT_SHADING):
    """Visibility fractions of one edge in both cameras.

    Returns
    -------
    dict
        ``{"left": {...}, "right": {...}, "visible_both": bool}`` where each
        camera's dict has the fractions ``in_image``, ``unoccluded``,
        ``contrast`` and ``visible`` (see the module notes).
    """
    pts, tan = sample_edge(kind, geometry)
    out = {}
    for index, name in enumerate(("left", "right")):
        v = edge_visibility(rs, calib, index, part_to_camera, pts, tan, shading)
        every = v["in_image"] & v["unoccluded"] & v["contrast"]
        out[name] = {k: float(np.mean(v[k])) for k in ("in_image", "unoccluded", "contrast")}
        out[name]["visible"] = float(np.mean(every))
    out["visible_both"] = bool(min(out["left"]["visible"], out["right"]["visible"]) >= VISIBLE_FRACTION)
    return out


def _rounded(value, digits=9):
    """JSON-ready copy with floats rounded to ``digits`` decimals, no -0.0."""
    if isinstance(value, dict):
        return {k: _rounded(v, digits) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_rounded(v, digits) for v in value]
    if isinstance(value, np.ndarray):
        return _rounded(value.tolist(), digits)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return round(float(value), digits) + 0.0
    return value


_NUMBER_LIST = re.compile(r"\[[-+0-9.eE,\s]*\]")


def to_json(truth):
    """Serialise a truth dict deterministically (floats rounded to 1e-9).

    Indented, with every innermost list of numbers (a point, a matrix row)
    kept on one line.
    """
    text = json.dumps(_rounded(truth), indent=1)
    return _NUMBER_LIST.sub(lambda m: "[" + ", ".join(m.group(0)[1:-1].split()).replace(",,", ",") + "]", text) + "\n"


def _shift_circle(g, center_delta=None, radius_delta=0.0):
    g = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in g.items()}
    if center_delta is not None:
        g["center"] = g["center"] + center_delta
    g["radius"] = g["radius"] + radius_delta
    if "angle_start" in g:
        x, y = _circle_axes(g["normal"])
        for key, angle in (("start", g["angle_start"]), ("end", g["angle_end"])):
            g[key] = g["center"] + g["radius"] * (math.cos(angle) * x + math.sin(angle) * y)
    return g


_AXES = {"x": 0, "y": 1, "z": 2}


def _same_axis_and_radius(f, g, tol=1e-6):
    """Do two circles or arcs lie on one cylinder (same axis and radius)?"""
    if abs(f.radius - g.radius) > tol * max(1.0, f.radius):
        return False
    if np.linalg.norm(np.cross(f.normal, g.normal)) > tol:
        return False
    v = np.asarray(g.center) - np.asarray(f.center)
    return np.linalg.norm(v - (v @ f.normal) * f.normal) <= tol * max(1.0, f.radius)


def deviated_geometry(inv, deviations):
    """As-rendered geometry of every feature, from the nominal one and the deltas.

    Parameters
    ----------
    inv : Inventory
        Of the nominal part.
    deviations : sequence of (feature_id, param, delta)
        ``param`` is ``radius`` or ``diameter`` (delta in mm), ``center``
        (delta a 3-vector, mm) or ``x``, ``y``, ``z`` (the centre moved along
        that part axis, mm).

    Returns
    -------
    dict of str to dict
        Feature id to geometry (as :func:`feature_geometry`).

    Notes
    -----
    A deviation changes the whole cylindrical wall a circle or arc bounds,
    so it applies to every circle and arc of that same cylinder (both rims
    of a through hole), as :func:`partinspect.cad.deviate.deviate` changes
    the solid. Deviate validates what it accepts (complete cylinders,
    shifts perpendicular to the axis); this function assumes that.
    """
    geometry = {f.id: feature_geometry(f) for f in inv.features}
    for fid, param, delta in deviations:
        f = inv[fid]
        if f.kind not in ("circle", "arc"):
            raise ValueError(f"{fid}: only circles and arcs can be deviated, not a {f.kind}")
        group = [g for g in inv.features if g.kind != "line" and _same_axis_and_radius(f, g)]
        if param in ("radius", "diameter"):
            change = {"radius_delta": float(delta) / (2.0 if param == "diameter" else 1.0)}
        elif param == "center":
            change = {"center_delta": np.asarray(delta, float).reshape(3)}
        elif param in _AXES:
            v = np.zeros(3)
            v[_AXES[param]] = float(delta)
            change = {"center_delta": v}
        else:
            raise ValueError(f"{fid}: unknown deviation parameter {param!r}")
        for g in group:
            geometry[g.id] = _shift_circle(geometry[g.id], **change)
    return geometry


def _delta_json(delta):
    d = np.asarray(delta, float)
    return float(d) if d.ndim == 0 else d.tolist()


def make_truth(inv, deviations, rs, calib, part_to_camera, settings, shading=DEFAULT_SHADING):
    """The truth of a render as a JSON-ready dict (schema ``truth/1``).

    Parameters
    ----------
    inv : Inventory
        Of the nominal part.
    deviations : sequence of (feature_id, param, delta)
    rs : RaycastScene
        The part as rendered.
    calib : StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
    settings : dict
        Render settings (image size, noise, seed, ...), copied in.
    shading : Shading

    Returns
    -------
    dict
        ``schema``, ``units``, the settings, ``part_to_camera``,
        ``deviations`` and ``features``: per feature its ``id``, ``kind``,
        ``faces``, ``smooth``, ``nominal`` and ``rendered`` geometry,
        ``deviated`` (whether they differ), ``visibility`` (``left`` and
        ``right`` fractions) and ``visible_both``.
    """
    rendered = deviated_geometry(inv, deviations)
    features = []
    for f in inv.features:
        nominal, actual = feature_geometry(f), rendered[f.id]
        changed = any(not np.allclose(nominal[k], actual[k], rtol=0, atol=1e-12) for k in nominal)
        vis = feature_visibility(rs, calib, part_to_camera, f.kind, actual, shading)
        features.append(
            {
                "id": f.id,
                "kind": f.kind,
                "faces": list(f.faces),
                "smooth": bool(f.smooth),
                "nominal": nominal,
                "rendered": actual,
                "deviated": bool(changed),
                "visibility": {"left": vis["left"], "right": vis["right"]},
                "visible_both": vis["visible_both"],
            }
        )
    truth = {"schema": SCHEMA, "units": "mm"}
    truth.update(settings)
    truth["part_to_camera"] = np.asarray(part_to_camera, float).tolist()
    truth["visibility_rules"] = {
        "min_contrast": MIN_CONTRAST,
        "contrast_offset_px": CONTRAST_OFFSET,
        "occlusion_tolerance": OCCLUSION_TOLERANCE,
        "visible_fraction": VISIBLE_FRACTION,
    }
    truth["deviations"] = [{"feature": fid, "param": p, "delta": _delta_json(d)} for fid, p, d in deviations]
    truth["features"] = features
    return truth
