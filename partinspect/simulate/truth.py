"""Ground truth of a synthetic render: pose, settings, and every feature.

For every feature of the part's inventory the truth gives its nominal
geometry (the STEP model), its as-rendered geometry (after the requested
deviations) and how well each camera sees it:

- ``in_image``: fraction of points along the edge that project inside the
  image (pixel centres' span, ``0 <= u <= W - 1``, ``0 <= v <= H - 1``);
- ``unoccluded``: fraction whose line of sight is free;
- ``contrast``: fraction whose image shows a clean grey step;

(each as :func:`partinspect.cad.sightlines.edge_visibility` decides it);
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

from partinspect.cad.edge_sampling import feature_geometry, sample_edge
from partinspect.cad.raycast import DEFAULT_SHADING
from partinspect.cad.sightlines import CONTRAST_OFFSET, MIN_CONTRAST, OCCLUSION_TOLERANCE, edge_visibility
from partinspect.frames import orthonormal_frame

__all__ = [
    "SCHEMA",
    "VISIBLE_FRACTION",
    "feature_visibility",
    "deviated_geometry",
    "drawn_radius",
    "make_truth",
    "to_json",
]

SCHEMA = "truth/1"
VISIBLE_FRACTION = 0.5
"""Fraction of an edge that must be visible in an image for ``visible_both``."""


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
        x, y = orthonormal_frame(g["normal"])[:2]
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


def drawn_radius(vertices, geometry, tol=1e-5):
    """The mean radius of a circle or arc as the render's mesh draws it, mm.

    The mesh draws a circle as a polygon through vertices on it; each side
    lies inside the circle by up to ``r (1 - cos(a))`` (``2 a`` the angle it
    spans). An edge fit to its image, through points about evenly spaced
    along it, reads the polygon's mean distance from the centre along its
    sides, short of ``r`` by about ``r a^2 / 3``: the truth states that.

    Parameters
    ----------
    vertices : ndarray, shape (V, 3)
        The render mesh's vertices, part frame, mm.
    geometry : dict
        The circle or arc as rendered (:func:`deviated_geometry`).
    tol : float
        mm: how near the circle's plane and radius a vertex lies on it.

    Returns
    -------
    float
        ``geometry["radius"]`` where fewer than 3 vertices lie on the circle.
    """
    c, r = np.asarray(geometry["center"], float), float(geometry["radius"])
    x, y, n = orthonormal_frame(np.asarray(geometry["normal"], float))
    d = np.asarray(vertices, float) - c
    on = (np.abs(d @ n) < tol) & (np.abs(np.hypot(d @ x, d @ y) - r) < tol)
    theta = np.unique(np.arctan2(d[on] @ y, d[on] @ x))
    if len(theta) < 3:
        return r
    if "angle_start" in geometry:
        span = (geometry["angle_end"] - geometry["angle_start"]) % (2.0 * np.pi) or 2.0 * np.pi
        t = np.sort((theta - geometry["angle_start"]) % (2.0 * np.pi))
        gaps = np.diff(t[t <= span + 1e-9])
    else:
        gaps = np.diff(np.append(theta, theta[0] + 2.0 * np.pi))
    a = 0.5 * gaps[gaps > 0]
    if not len(a):
        return r
    # Per side: the integral of the distance along it, h r + d^2 asinh(h / d),
    # with d = r cos(a) its distance and 2 h = 2 r sin(a) its length.
    h, d = r * np.sin(a), r * np.cos(a)
    return float(np.sum(h * r + d * d * np.arcsinh(np.tan(a))) / np.sum(2.0 * h))


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
        if f.kind != "line":
            actual = dict(actual, radius=drawn_radius(rs.vertices, actual))
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
