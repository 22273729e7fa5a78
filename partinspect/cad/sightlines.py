"""Per-point visibility of a CAD edge in one camera: in the image, in
sight, and with contrast.

For samples along an edge (:mod:`partinspect.cad.edge_sampling`):

- ``in_image``: the point projects inside the image (pixel centres' span,
  ``0 <= u <= W - 1``, ``0 <= v <= H - 1``);
- ``unoccluded``: a ray cast from the camera centre towards the point hits
  nothing more than ``OCCLUSION_TOLERANCE`` before it;
- ``contrast``: the noiseless shading differs by at least ``MIN_CONTRAST``
  grey levels between the two sides of the projected edge
  (``CONTRAST_OFFSET`` pixels along the image normal on either side), each
  side showing one face from 0.25 px out to that distance (or faces shaded
  alike: ``NEIGHBOUR_STEP_FRACTION``) and the face changing across the edge.
  An edge between two faces that meet tangentially shows none, nor does a
  stretch whose image runs within 1.5 px of another edge; judged in the
  image only.

Part frame (STEP), mm; ``part_to_camera`` maps it into the left camera
(rig) frame.

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., section 6.1 (projective camera).
"""

import numpy as np

from partinspect.cad.raycast import DEFAULT_SHADING, camera_in_part, cast, pixel_rays, shade
from partinspect.vision.calibration import project_points

__all__ = ["MIN_CONTRAST", "CONTRAST_OFFSET", "NEIGHBOUR_STEP_FRACTION", "OCCLUSION_TOLERANCE", "in_view", "in_sight",
           "edge_visibility"]

MIN_CONTRAST = 20.0
"""Grey levels across an edge for it to count as showing."""
CONTRAST_OFFSET = 1.5
"""Pixels from the edge, on each side, where the contrast is taken."""
NEIGHBOUR_STEP_FRACTION = 0.1
"""A face boundary within ``CONTRAST_OFFSET`` of an edge, on one side, counts
as a second edge when its grey step is at least this fraction of the edge's
contrast. Faces shaded alike (a hole's wall and the face seen past it,
where the 2D chain still finds the edge) step by far less, true second
edges by far more."""
OCCLUSION_TOLERANCE = 0.05
"""mm: a surface this little in front of an edge point does not hide it
(the tessellation's chord error, seen at grazing incidence, is below it)."""


def in_view(uv, image_size):
    """Mask of the pixel positions ``uv`` (N, 2) within the pixel centres' span of an image of ``image_size`` (w, h)."""
    w, h = image_size
    return np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)


def in_sight(rs, origin, points):
    """Mask of the ``points`` (N, 3, part frame) that a ray cast from ``origin`` reaches with nothing more than
    ``OCCLUSION_TOLERANCE`` before them."""
    ray = points - origin
    dist = np.linalg.norm(ray, axis=1)
    return cast(rs, origin, ray / dist[:, None]).distance >= dist - OCCLUSION_TOLERANCE


def edge_visibility(rs, calib, index, part_to_camera, points, tangents, shading=DEFAULT_SHADING):
    """Per-point visibility of edge samples in one camera.

    Parameters
    ----------
    rs : partinspect.cad.raycast.RaycastScene
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
    uv = project_points(points, K, D, R, t)
    # Image direction of the edge by a central difference along its tangent.
    step = 1e-3
    du = project_points(points + step * tangents, K, D, R, t) - project_points(points - step * tangents, K, D, R, t)
    du /= np.maximum(np.linalg.norm(du, axis=1), 1e-300)[:, None]
    normal = np.stack([-du[:, 1], du[:, 0]], axis=1)
    in_image = in_view(uv, calib.image_size)
    unoccluded = in_sight(rs, -R.T @ t, points)

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
