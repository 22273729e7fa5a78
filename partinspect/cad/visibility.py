"""Which CAD edges the cameras can see with the part at a given pose.

A feature that was not measured is either out of view (outside an image,
or hidden behind the part itself) or seen but not measurable (too short,
unmatched, degenerate). The report must say which: the first is a matter of
fixturing, the second of the measurement. Visibility here is geometric:
CAD edges sampled densely, projected with the lens model, and a ray cast
from each camera centre towards every sample through the tessellated part.

Frames: part frame (STEP), mm; ``part_to_camera`` maps it into the left
camera (rig) frame.

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., section 6.1 (projective camera).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FeatureVisibility", "SEEN_FRACTION", "visibility", "visibility_mesh"]

SEEN_FRACTION = 0.5
"""A feature with less than this fraction of its length in view in either
image counts as out of view."""

MIN_CONTRAST_SNR = 3.0
"""An edge whose grey step is below this many noise standard deviations
cannot be expected to be detected, with any of the parameters the adaptive
processing tries (:mod:`partinspect.adaptive`): at 3 the widest edge filter
a re-run uses (1.5 px) still finds nearly every point of a blurred step, so
an edge above it that is missing is worth a re-run and worth reporting."""
CONTRAST_OFFSET = 2.5
"""px either side of the projected edge where its grey step is read."""

MESH_TOLERANCE = 0.05
"""Chord error of the mesh the sight lines are cast through, mm (about a
pixel's footprint on the part for the rigs the project targets)."""


@dataclass(frozen=True)
class FeatureVisibility:
    """How much of one CAD edge each camera sees.

    Attributes
    ----------
    contrast : tuple of float
        Median grey-level step across the edge where it is seen, left and
        right image (NaN when no images were given or nothing is seen).
    in_image : tuple of float
        Fraction of the edge projecting inside the left and right image.
    unoccluded : tuple of float
        Fraction whose line of sight from the left / right camera is free.
    seen : tuple of float
        Fraction both inside the image and unoccluded, per camera.
    """

    in_image: tuple
    unoccluded: tuple
    seen: tuple
    contrast: tuple = (float("nan"), float("nan"))

    def shows_edge(self, noise):
        """True when the edge is in view and its grey step is at least ``MIN_CONTRAST_SNR`` x ``noise`` in both images."""
        return self.in_view and all(not (c < MIN_CONTRAST_SNR * noise) for c in self.contrast)

    @property
    def in_view(self):
        """True when both cameras see at least ``SEEN_FRACTION`` of the edge."""
        return min(self.seen) >= SEEN_FRACTION

    def reason(self):
        """Why the edge is out of view, in words ("" when it is in view)."""
        if self.in_view:
            return ""
        names = ("left", "right")
        out = []
        for i, name in enumerate(names):
            if self.seen[i] >= SEEN_FRACTION:
                continue
            if self.in_image[i] < SEEN_FRACTION:
                out.append(f"outside the {name} image ({100 * self.in_image[i]:.0f} % inside)")
            else:
                out.append(f"hidden by the part in the {name} image ({100 * self.unoccluded[i]:.0f} % in sight)")
        return "; ".join(out)


def _step(image, uv, normal):
    """Grey-level difference across an edge at each point, bilinear samples CONTRAST_OFFSET px either side."""
    import cv2

    img = np.asarray(image, np.float32)
    a = uv + CONTRAST_OFFSET * normal
    b = uv - CONTRAST_OFFSET * normal
    ga = cv2.remap(img, a[:, 0:1].astype(np.float32), a[:, 1:2].astype(np.float32), cv2.INTER_LINEAR)
    gb = cv2.remap(img, b[:, 0:1].astype(np.float32), b[:, 1:2].astype(np.float32), cv2.INTER_LINEAR)
    return np.abs(ga - gb).ravel()


def visibility_mesh(shape, inventory=None):
    """The coarse tessellation the visibility test casts rays at.

    Occlusion need only be decided to a pixel or so, and the renderer's fine
    mesh would be slow on a large part.

    Returns
    -------
    trimesh.Trimesh
        Part frame, mm, with ``face_attributes["cad_face"]``
        (`partinspect.cad.mesh.tessellate`).
    """
    from partinspect.cad.mesh import tessellate

    return tessellate(shape, tolerance=MESH_TOLERANCE, angular_tolerance=0.2, inventory=inventory)


def visibility(shape, inventory, calib, part_to_camera, *, mesh=None, images=None, scene=None):
    """Visibility of every feature of an inventory in both cameras.

    Parameters
    ----------
    shape : cadquery.Shape
        The part, for tessellation (ignored when ``mesh`` is given).
    inventory : partinspect.cad.features.Inventory
    calib : partinspect.vision.calibration.StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
        ``x_rig = R @ X_part + t``, mm.
    mesh : trimesh.Trimesh, optional
        A tessellation of ``shape`` with ``face_attributes["cad_face"]``.
    images : (ndarray, ndarray), optional
        The left and right images (grey, as recorded): each edge's grey
        step across it is then read where it is seen.
    scene : RaycastScene, optional
        ``build_scene(mesh)``, if the caller has it (``mesh`` and ``shape``
        are then not read).

    Returns
    -------
    dict of str to FeatureVisibility
        Keyed by feature id.
    """
    from partinspect.cad.raycast import build_scene
    from partinspect.cad.sightlines import edge_visibility
    from partinspect.cad.edge_sampling import feature_geometry, sample_edge

    rs = scene
    if rs is None:
        rs = build_scene(visibility_mesh(shape, inventory) if mesh is None else mesh)
    out = {}
    for f in inventory.features:
        pts, tan = sample_edge(f.kind, feature_geometry(f))
        fr = {"in_image": [], "unoccluded": [], "seen": [], "contrast": []}
        for index in (0, 1):
            v = edge_visibility(rs, calib, index, part_to_camera, pts, tan)
            seen = v["in_image"] & v["unoccluded"]
            fr["in_image"].append(float(np.mean(v["in_image"])))
            fr["unoccluded"].append(float(np.mean(v["unoccluded"])))
            fr["seen"].append(float(np.mean(seen)))
            c = float("nan")
            if images is not None and seen.any():
                c = float(np.median(_step(images[index], v["uv"][seen], v["normal_uv"][seen])))
            fr["contrast"].append(c)
        out[f.id] = FeatureVisibility(*(tuple(fr[k]) for k in ("in_image", "unoccluded", "seen", "contrast")))
    return out
