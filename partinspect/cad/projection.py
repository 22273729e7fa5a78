"""The images of CAD edges in both cameras under a pose.

Once the part's pose is registered, every CAD edge's image is known, faint
and hidden ones too; the pose-guided measurement
(:mod:`partinspect.vision.posed`) and the diagnosis of unmeasured edges read
them. Edges are projected through the full lens model (distorted pixels,
OpenCV convention), sampled about half a pixel apart so a nearest-point
query is as fine as the edge points themselves.

Frames: part frame (STEP), mm; ``part_to_camera`` maps it into the left
camera (rig) frame.

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., section 6.1 (projective camera).
"""

import numpy as np

__all__ = ["edge_images", "curve_images", "edge_polylines"]


def edge_images(feature, part_to_camera, calib):
    """A CAD line's image in the left and the right camera under a pose.

    Returns
    -------
    tuple of two ndarray, shape (M, 2)
        Distorted pixels, sampled from ``feature.start`` to ``feature.end``
        about half a pixel apart (NaN where a point is behind a camera).
    """
    from partinspect.vision.calibration import project_points

    R, t = part_to_camera[:3, :3], part_to_camera[:3, 3]
    ends = np.array([feature.start, feature.end], float) @ R.T + t
    out = []
    for K, D, Rc, tc in ((calib.K1, calib.D1, np.eye(3), np.zeros(3)), (calib.K2, calib.D2, calib.R, calib.T)):
        uv = project_points(ends, K, D, Rc, tc)
        length = float(np.hypot(*(uv[1] - uv[0]))) if np.isfinite(uv).all() else 0.0
        s = np.linspace(0.0, 1.0, int(min(2 * length, 20000)) + 2)
        out.append(project_points(ends[0] + s[:, None] * (ends[1] - ends[0]), K, D, Rc, tc))
    return tuple(out)


def curve_images(feature, part_to_camera, calib):
    """A CAD edge's image (line, circle or arc) in the left and the right camera under a pose.

    Returns
    -------
    tuple of two ndarray, shape (M, 2)
        Distorted pixels, about half a pixel apart (NaN where a point is
        behind a camera).
    """
    if feature.kind == "line":
        return edge_images(feature, part_to_camera, calib)
    from partinspect.cad.edge_sampling import feature_geometry, sample_edge
    from partinspect.vision.calibration import project_points

    R, t = part_to_camera[:3, :3], part_to_camera[:3, 3]
    g = feature_geometry(feature)
    out = []
    for K, D, Rc, tc in ((calib.K1, calib.D1, np.eye(3), np.zeros(3)), (calib.K2, calib.D2, calib.R, calib.T)):
        coarse = project_points(sample_edge(feature.kind, g, 64)[0] @ R.T + t, K, D, Rc, tc)
        ok = np.isfinite(coarse).all(axis=1)
        length = float(np.sum(np.hypot(*np.diff(coarse[ok], axis=0).T))) if ok.sum() > 1 else 0.0
        n = int(min(2 * length * 64 / 63, 20000)) + 2
        out.append(project_points(sample_edge(feature.kind, g, n)[0] @ R.T + t, K, D, Rc, tc))
    return tuple(out)


def edge_polylines(inv, part_to_camera, calib):
    """Every CAD edge's image in both cameras under a pose: id -> :func:`curve_images`."""
    return {f.id: curve_images(f, part_to_camera, calib) for f in inv.features}
