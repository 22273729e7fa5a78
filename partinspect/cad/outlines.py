"""The outlines of curved faces: where a camera's sight line grazes a convex surface.

A sharp CAD edge shows in the image where it is. A curved face (a
cylinder's side, a corner round, a fillet) shows one more grey step that
is no CAD edge: its occluding contour, the line on the surface where the
sight lines graze it, beyond which the camera sees past the part. It
starts on a CAD edge (a boss's or a round corner's top rim, at the point
where the rim's image turns round), and beside that point the face seen
between the two is a wedge narrower than the edge filter: the rim's
points there are pulled towards the outline, all to one side. The
pose-guided measurement leaves out the points of a registered edge that
lie near another edge's image (:func:`partinspect.vision.guided.clear_arc_ends`);
the outlines are such images too.

On the part's mesh, the occluding contour of a smooth surface is where
``(p - eye) . n`` changes sign, ``n`` the surface's smooth normal,
interpolated across each triangle [2]_, on the faces that are convex. A
concave face's contour (a bore's wall) lies behind the face itself and is
not seen; the convex faces' contours are cast against the mesh and kept
only where nothing hides them.

Frames: part frame (STEP), mm; ``part_to_camera`` maps it into the left
camera (rig) frame.

References
----------
.. [1] Koenderink, J. J. (1984). What does the occluding contour tell us
       about solid shape? Perception 13(3), 321-330.
.. [2] Hertzmann, A., Zorin, D. (2000). Illustrating smooth surfaces.
       SIGGRAPH 2000, 517-526 (section 3: the smooth contour of a mesh,
       from the sign of ``(p - eye) . n`` at the vertices, interpolated
       along the triangles' edges).
"""

import numpy as np

__all__ = ["FLAT_FOLD", "outline_images"]

FLAT_FOLD = 1e-3
"""rad: a fold between two triangles of a face turning by less than this is
flat, neither convex nor concave (the inventory's own threshold for faces
meeting without a crease, ``partinspect.cad.features.SMOOTH_ANGLE``)."""


def _outward_faces(rs):
    """Per CAD face label, whether the face is convex: its mesh folds outwards more often than inwards.

    Counting, not a single fold's sign: a concave cone's facets, twisted
    between rings of vertices at different angles, fold outwards here and
    there.
    """
    tri, v, n = rs.triangles, rs.vertices, rs.flat_normals
    edges = np.sort(tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(len(tri)), 3)
    opposite = tri[:, [2, 0, 1]].ravel()
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    pair = np.flatnonzero((edges[order][1:] == edges[order][:-1]).all(axis=1))
    i, j = order[pair], order[pair + 1]
    a, b = owner[i], owner[j]
    same = rs.labels[a] == rs.labels[b]
    i, j, a = i[same], j[same], a[same]
    # How far the far corner of one triangle lies in front of the other's plane.
    far = v[opposite[j]] - v[edges[i, 0]]
    fold = np.einsum("ij,ij->i", far, n[a]) / np.maximum(np.linalg.norm(far, axis=1), 1e-300)
    size = int(rs.labels.max()) + 1
    return np.bincount(rs.labels[a], fold < -FLAT_FOLD, size) > np.bincount(rs.labels[a], fold > FLAT_FOLD, size)


def _contour_segments(rs, eye):
    """The occluding contour of the convex faces seen from ``eye``, one segment per triangle it crosses.

    The smooth surface's contour, not the facets' own: where ``(p - eye) . n``
    changes sign along a triangle's edges, with ``n`` the face's smooth
    normal at each corner (``RaycastScene.corner_normals``), interpolated
    linearly [2]_. The facets' contour runs along mesh edges, up to half a
    facet's angle round the surface from the true one.

    Returns
    -------
    points : ndarray, shape (S, 2, 3)
        Each segment's ends, part frame, mm.
    normals : ndarray, shape (S, 2, 3)
        The smooth normals there.
    face : ndarray, shape (S,)
        The CAD face label of each.
    """
    tri, v = rs.triangles, rs.vertices
    keep = np.flatnonzero(_outward_faces(rs)[rs.labels])
    p, nrm = v[tri[keep]], rs.corner_normals[keep]
    g = np.einsum("tkj,tkj->tk", p - eye, nrm)
    front = g < 0.0
    cross = front.any(axis=1) & ~front.all(axis=1)
    p, nrm, g, front, keep = p[cross], nrm[cross], g[cross], front[cross], keep[cross]
    ends, normals = [], []
    for k in range(3):
        m = (k + 1) % 3
        s = g[:, k] / np.where(front[:, k] != front[:, m], g[:, k] - g[:, m], 1.0)
        ends.append(p[:, k] + s[:, None] * (p[:, m] - p[:, k]))
        normals.append(nrm[:, k] + s[:, None] * (nrm[:, m] - nrm[:, k]))
    # Two of a crossed triangle's three edges change sign.
    on = np.stack([front[:, k] != front[:, (k + 1) % 3] for k in range(3)], axis=1)
    pick = np.argsort(~on, axis=1, kind="stable")[:, :2]
    rows = np.arange(len(p))[:, None]
    points = np.stack(ends, axis=1)[rows, pick]
    normals = np.stack(normals, axis=1)[rows, pick]
    return points, normals, rs.labels[keep]


def outline_images(rs, calib, part_to_camera, spacing=0.5):
    """The images of the curved faces' occluding contours in both cameras, where they are in sight.

    Parameters
    ----------
    rs : RaycastScene
        The part's mesh (:func:`partinspect.cad.raycast.build_scene` of a
        :func:`partinspect.cad.mesh.tessellate`), part frame, mm.
    calib : StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
        ``x_rig = R @ X_part + t``, mm.
    spacing : float
        px between samples along the contour's image.

    Returns
    -------
    dict of str to (ndarray (M, 2), ndarray (K, 2))
        ``"face-N outline"`` -> the samples of that face's contour seen in
        the left and the right image (distorted px; a camera that sees none
        of it has an empty array); faces without a contour in sight in
        either image are left out. Samples, not one ordered polyline: a
        contour may run in several pieces.
    """
    from partinspect.cad.raycast import camera_in_part
    from partinspect.cad.sightlines import OCCLUSION_TOLERANCE, in_sight, in_view
    from partinspect.vision.calibration import project_points

    found = {}
    for index in (0, 1):
        K, D, R, t = camera_in_part(calib, index, part_to_camera)
        eye = -R.T @ t
        ends, normals, face = _contour_segments(rs, eye)
        if not len(ends):
            continue
        uv = project_points(ends[:, 0], K, D, R, t), project_points(ends[:, 1], K, D, R, t)
        length = np.hypot(*(uv[1] - uv[0]).T)
        n = np.where(np.isfinite(length), np.ceil(np.nan_to_num(length) / spacing), 0).astype(int) + 1
        s = np.concatenate([np.linspace(0.0, 1.0, k + 1) for k in n])[:, None]
        which = np.repeat(np.arange(len(ends)), n + 1)
        pts = ends[which, 0] + s * (ends[which, 1] - ends[which, 0])
        # The smooth contour lies up to the mesh's chord error off its
        # facets: sighted from just outside the surface, so that a grazing
        # sight line does not clip the facet beside it.
        out = normals[which, 0] + s * (normals[which, 1] - normals[which, 0])
        aim = pts + OCCLUSION_TOLERANCE * out / np.linalg.norm(out, axis=1)[:, None]
        q = project_points(pts, K, D, R, t)
        seen = in_view(q, calib.image_size) & in_sight(rs, eye, aim)
        for label in np.unique(face[which[seen]]):
            key = f"face-{label + 1} outline"
            pair = found.setdefault(key, [np.zeros((0, 2)), np.zeros((0, 2))])
            pair[index] = q[seen & (face[which] == label)]
    return {k: tuple(v) for k, v in found.items()}
