"""Renders of the sample parts and their truth in the rig frame, for the stereo tests.

Renders are 1224 x 1024 (the default rig's field of view at half its
resolution) and cached for the session in this module, so each (part,
noise, seed) pair is ray-cast once however many test modules use it.
"""

import numpy as np

from tests.simulate.scenes import Part

SIZE = (1224, 1024)
_PARTS = {}
_TRUTH = {}


def part(name):
    if name not in _PARTS:
        _PARTS[name] = Part(name)
    return _PARTS[name]


def render(name, noise=2.0, seed=0, distortion=False, size=SIZE):
    """(rig, part_to_camera, left, right) of a sample part in its default pose."""
    rig, pose, (left, right) = part(name).render(distortion=distortion, noise=noise, seed=seed, size=size)
    return rig, pose, left, right


def truth_in_rig(name, distortion=False, size=SIZE):
    """Every feature of the part, geometry in the rig frame (mm).

    Returns
    -------
    list of dict
        ``id``, ``kind``, ``visible_both`` and, for lines, ``start``, ``end``; for circles and
        arcs ``center``, ``normal``, ``radius``; plus ``samples`` (M, 3),
        points along the edge.
    """
    key = (name, distortion, size)
    if key in _TRUTH:
        return _TRUTH[key]
    from partinspect.simulate.truth import feature_visibility
    from partinspect.cad.edge_sampling import feature_geometry, sample_edge

    p = part(name)
    rig = p.rig(distortion, size)
    pose = p.pose(rig)
    Rp, tp = pose[:3, :3], pose[:3, 3]
    out = []
    for f in p.inv.features:
        g = feature_geometry(f)
        vis = feature_visibility(p.scene, rig, pose, f.kind, g)
        pts, _ = sample_edge(f.kind, g, n=2000)
        t = {"id": f.id, "kind": f.kind, "samples": pts @ Rp.T + tp, "visible_both": vis["visible_both"]}
        if f.kind == "line":
            t["start"], t["end"] = Rp @ g["start"] + tp, Rp @ g["end"] + tp
        else:
            t["center"], t["normal"], t["radius"] = Rp @ g["center"] + tp, Rp @ g["normal"], g["radius"]
        out.append(t)
    _TRUTH[key] = out
    return out


def project(P, X):
    x = np.c_[X, np.ones(len(X))] @ P.T
    return x[:, :2] / x[:, 2:]


def label_image_feature(xy_ideal, truths, P, max_mean_distance=1.0):
    """Id of the true edge whose image the ideal points lie on (or None)."""
    from scipy.spatial import cKDTree

    best, best_d = None, max_mean_distance
    for t in truths:
        d, _ = cKDTree(project(P, t["samples"])).query(xy_ideal)
        if np.mean(d) < best_d:
            best, best_d = t["id"], float(np.mean(d))
    return best


def line_point_error(point, direction, truth):
    """Error (mm) of a measured line's ``point``: from the true line to it, as
    a 3-vector perpendicular to the measured direction.

    At ``point`` (near the centroid of the measured edge points), where the
    line's covariance (``Feature3D.covariance``) is stated: a line measured
    on a piece of its edge is not to be judged at the edge's middle, which
    its direction's error would move by the lever arm.
    """
    a = truth["start"]
    d = truth["end"] - a
    d = d / np.linalg.norm(d)
    v = point - a
    v = v - (v @ d) * d
    return v - (v @ direction) * direction
