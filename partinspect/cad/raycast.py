"""A part's mesh in a ray caster: what a camera's pixel sees of it.

A pixel position ``(u, v)`` in *distorted* pixel coordinates is mapped to
its viewing ray by the calibration's exact undistortion, so lens distortion
enters through the camera model itself. Rays are cast in the part frame
(coordinates of tens of mm, where float32 resolves 1e-5 mm) and start at
the part's bounding sphere rather than at the camera, so the float32 ray
caster loses nothing measurable at working distances of hundreds of mm.

Shading is Lambertian and view-independent: ``ambient + albedo * max(0,
n . l)`` for a directional light fixed in the rig frame and a uniform dark
background where rays miss, so a surface point has the same grey in both
images. Visibility and contrast predictions (:mod:`partinspect.cad.visibility`),
the planner and the renderer of :mod:`partinspect.simulate` share it.

References
----------
.. [1] Wald, I. et al. (2014). Embree: a kernel framework for efficient CPU
       ray tracing. ACM Trans. Graph. 33(4), 143 (the ray caster, through
       the embreex binding that trimesh uses: the same Embree as Open3D's
       RaycastingScene at a small part of its import time).
"""

from dataclasses import dataclass

import numpy as np

from partinspect.vision.calibration import undistort_points

__all__ = [
    "MISS",
    "RAY_CHUNK",
    "RENDER_TOLERANCE",
    "RENDER_ANGULAR_TOLERANCE",
    "Shading",
    "DEFAULT_SHADING",
    "RaycastScene",
    "Hits",
    "build_scene",
    "camera_in_part",
    "pixel_rays",
    "cast",
    "shade",
    "surface_normals",
]

MISS = -1
"""Label of a ray that hits nothing."""
RAY_CHUNK = 1 << 20
"""Rays per ray-caster call: about 100 MB of temporaries."""
RENDER_TOLERANCE = 0.005
"""Chord error of the render mesh, mm (a tenth of a pixel's footprint)."""
RENDER_ANGULAR_TOLERANCE = 0.01
"""Angle between neighbouring facets of a curved face, radians. Finer than
the mesh module's default: a circle drawn as a polygon has a mean radius
short by a part of r that grows with the square of this angle, which at
0.05 rad would bias rendered diameters by micrometres, what the
measurement claims to resolve."""


@dataclass(frozen=True)
class Shading:
    """Lambertian lighting of the simulated scene.

    Attributes
    ----------
    light : tuple of float, shape (3,)
        Direction *towards* the light in the rig (left camera) frame; need
        not be unit length.
    ambient : float
        Grey of a surface facing away from the light, grey levels.
    albedo : float
        Grey added for a surface facing the light head-on, grey levels.
    background : float
        Grey where a ray hits nothing, grey levels.

    Notes
    -----
    The default light sits near the cameras, a little to the right of and
    above the optical axis, like a ring or bar light on the rig, so that the
    faces the cameras see differ by tens of grey levels and faces turned away
    (``ambient``) stay well above the background: every silhouette shows.
    """

    light: tuple = (0.351, -0.084, -0.933)
    ambient: float = 65.0
    albedo: float = 185.0
    background: float = 25.0

    def direction(self):
        l = np.asarray(self.light, dtype=float)
        return l / np.linalg.norm(l)


DEFAULT_SHADING = Shading()


@dataclass(frozen=True, eq=False)
class RaycastScene:
    """A triangle mesh loaded into the Embree ray caster, with what shading needs.

    Attributes
    ----------
    scene : embreex.rtcore_scene.EmbreeScene
    vertices : ndarray, shape (V, 3)
        Part frame, mm.
    triangles : ndarray, shape (F, 3)
        Vertex indices.
    labels : ndarray, shape (F,)
        CAD face index of every triangle.
    flat_normals : ndarray, shape (F, 3)
        Unit normal of every triangle (winding order).
    corner_normals : ndarray, shape (F, 3, 3)
        Unit normal at each triangle corner, averaged over the triangles of
        the same CAD face around that vertex: the smooth surface normal of a
        curved face, the exact normal of a planar one.
    center : ndarray, shape (3,)
    radius : float
        Bounding sphere of the mesh, part frame, mm.
    """

    scene: object
    vertices: np.ndarray
    triangles: np.ndarray
    labels: np.ndarray
    flat_normals: np.ndarray
    corner_normals: np.ndarray
    center: np.ndarray
    radius: float


def _corner_normals(vertices, triangles, labels):
    cross = np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]], vertices[triangles[:, 2]] - vertices[triangles[:, 0]])
    area2 = np.linalg.norm(cross, axis=1)
    flat = cross / np.where(area2 > 0, area2, 1.0)[:, None]
    # Group corners by (vertex, CAD face): normals are smoothed within a face,
    # never across the sharp edge between two faces.
    key = triangles.astype(np.int64) * (int(labels.max()) + 1) + labels[:, None]
    _, group = np.unique(key.ravel(), return_inverse=True)
    acc = np.zeros((group.max() + 1, 3))
    # area-weighted: sum of the unnormalised cross products
    np.add.at(acc, group, np.repeat(cross, 3, axis=0))
    acc /= np.maximum(np.linalg.norm(acc, axis=1), 1e-300)[:, None]
    return flat, acc[group].reshape(-1, 3, 3)


def build_scene(mesh):
    """Load a mesh into a ray-casting scene.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Part frame, mm, with ``mesh.face_attributes["cad_face"]`` giving the
        CAD face of every triangle (as made by
        :func:`partinspect.cad.mesh.tessellate`); without it every triangle
        is its own face.

    Returns
    -------
    RaycastScene
    """
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    vertices = np.asarray(mesh.vertices, dtype=float)
    triangles = np.asarray(mesh.faces, dtype=np.int64)
    attrs = getattr(mesh, "face_attributes", None) or {}
    labels = np.asarray(attrs.get("cad_face", np.arange(len(triangles))), dtype=np.int64).ravel()
    if labels.shape != (len(triangles),):
        raise ValueError(f"cad_face has {labels.size} entries for {len(triangles)} triangles")
    flat, corner = _corner_normals(vertices, triangles, labels)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(vertices - center, axis=1).max())
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, vertices.astype(np.float32), triangles.astype(np.int32))
    return RaycastScene(scene, vertices, triangles, labels, flat, corner, center, radius)


def camera_in_part(calib, index, part_to_camera):
    """Pose of camera ``index`` relative to the part.

    Parameters
    ----------
    calib : StereoCalibration
    index : int
        0 left, 1 right.
    part_to_camera : ndarray, shape (4, 4)
        Part frame to left camera (rig) frame.

    Returns
    -------
    K : ndarray, shape (3, 3)
    D : ndarray
    R : ndarray, shape (3, 3)
    t : ndarray, shape (3,)
        ``x_cam = R @ X_part + t``, mm.
    """
    K, D, Rc, tc = calib.camera(index)
    P = np.asarray(part_to_camera, dtype=float)
    return K, D, Rc @ P[:3, :3], Rc @ P[:3, 3] + tc


def pixel_rays(uv, K, D, R, t):
    """Viewing rays of distorted pixel positions, in the part frame.

    Parameters
    ----------
    uv : ndarray, shape (N, 2)
        Distorted pixel coordinates (OpenCV: centre of the top-left pixel at
        (0, 0)).
    K, D : camera matrix and distortion vector.
    R, t : part-to-camera pose, ``x_cam = R @ X + t``.

    Returns
    -------
    origin : ndarray, shape (3,)
        Camera centre in the part frame, mm.
    directions : ndarray, shape (N, 3)
        Unit ray directions in the part frame.
    """
    xn = undistort_points(uv, K, D)
    d = np.empty((len(xn), 3))
    d[:, :2] = xn
    d[:, 2] = 1.0
    d /= np.linalg.norm(d, axis=1)[:, None]
    return -R.T @ t, d @ R


@dataclass(frozen=True)
class Hits:
    """What a batch of rays hit.

    Attributes
    ----------
    label : ndarray of int64, shape (N,)
        CAD face, or ``MISS`` (-1).
    triangle : ndarray of int64, shape (N,)
        Triangle index (meaningless where missed).
    bary : ndarray of float32, shape (N, 2)
        Barycentric ``(u, v)``: point = (1-u-v) p0 + u p1 + v p2.
    distance : ndarray of float64, shape (N,)
        Distance from the ray's origin, mm; inf where missed.
    """

    label: np.ndarray
    triangle: np.ndarray
    bary: np.ndarray
    distance: np.ndarray


def cast(rs, origin, directions):
    """Cast rays from one origin and return what they hit.

    Parameters
    ----------
    rs : RaycastScene
    origin : ndarray, shape (3,)
        Part frame, mm.
    directions : ndarray, shape (N, 3)
        Unit vectors, part frame.

    Returns
    -------
    Hits
    """
    origin = np.asarray(origin, dtype=float)
    # Start the rays where they enter the bounding sphere (less a margin),
    # computed in float64, so float32 ray origins stay near the part.
    skip = max(0.0, float(np.linalg.norm(origin - rs.center)) - rs.radius - 1.0)
    n = len(directions)
    label = np.empty(n, np.int64)
    tri = np.empty(n, np.int64)
    bary = np.empty((n, 2), np.float32)
    dist = np.empty(n, np.float64)
    for a in range(0, n, RAY_CHUNK):
        d = directions[a : a + RAY_CHUNK]
        o = np.ascontiguousarray(origin + skip * d, dtype=np.float32)
        out = rs.scene.run(o, np.ascontiguousarray(d, dtype=np.float32), output=1)
        prim = np.asarray(out["primID"], dtype=np.int64)
        hit = prim >= 0
        prim[~hit] = 0
        tri[a : a + len(d)] = prim
        label[a : a + len(d)] = np.where(hit, rs.labels[prim], MISS)
        bary[a : a + len(d), 0] = out["u"]
        bary[a : a + len(d), 1] = out["v"]
        dist[a : a + len(d)] = np.where(hit, skip + np.asarray(out["tfar"], dtype=np.float64), np.inf)
    return Hits(label, tri, bary, dist)


def shade(rs, hits, directions, light, shading=DEFAULT_SHADING):
    """Lambertian grey of every ray.

    Parameters
    ----------
    rs : RaycastScene
    hits : Hits
    directions : ndarray, shape (N, 3)
        The rays' directions, part frame (to orient normals towards the
        viewer).
    light : ndarray, shape (3,)
        Unit direction towards the light, part frame.
    shading : Shading

    Returns
    -------
    grey : ndarray of float32, shape (N,)
    """
    hit = hits.label != MISS
    grey = np.full(len(hits.label), shading.background, np.float32)
    if not hit.any():
        return grey
    n = surface_normals(rs, hits, directions)
    grey[hit] = shading.ambient + shading.albedo * np.maximum(0.0, n @ light)
    return grey


def surface_normals(rs, hits, directions):
    """Smooth unit surface normal at every ray's hit, turned towards the viewer.

    Parameters
    ----------
    rs : RaycastScene
    hits : Hits
    directions : ndarray, shape (N, 3)
        The rays' directions, part frame.

    Returns
    -------
    ndarray, shape (M, 3)
        For the M rays that hit (``hits.label != MISS``, in order): the
        corner normals interpolated barycentrically, part frame.
    """
    hit = hits.label != MISS
    tri = hits.triangle[hit]
    u = hits.bary[hit, 0:1].astype(float)
    v = hits.bary[hit, 1:2].astype(float)
    cn = rs.corner_normals[tri]
    n = (1.0 - u - v) * cn[:, 0] + u * cn[:, 1] + v * cn[:, 2]
    # A closed solid is seen from outside; flip by the geometric normal only,
    # so a smooth normal near a silhouette keeps its side.
    facing = np.einsum("ij,ij->i", rs.flat_normals[tri], directions[hit])
    n *= np.where(facing > 0, -1.0, 1.0)[:, None] / np.linalg.norm(n, axis=1)[:, None]
    return n
