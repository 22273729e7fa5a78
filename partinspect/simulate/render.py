"""Ray-cast rendering of a tessellated part through calibrated cameras.

Every sample of the image is a ray: a position ``(u, v)`` in *distorted*
pixel coordinates is mapped to its viewing direction by the calibration's
exact undistortion, so lens distortion is rendered through the model itself
rather than by warping an image. The image forms as in a camera: the optics
blur the radiance with a Gaussian point-spread function (PSF), each pixel
integrates the blurred irradiance over its square, and the sensor adds noise
and quantises to 8 bits. (Blurring the pixels' area means instead, as a
digital filter would, gives a profile the sub-pixel edge estimator reads
with a different bias from a camera's: up to 0.029 px RMS near the image
axes for the log-parabola, against 0.0022 px for the optical order at a
PSF of 0.6 px; ``benchmarks/bench_subpixel.py``.)

Area integration is adaptive: a coarse pass casts one ray at every pixel
corner and one at every pixel centre; a pixel whose five samples all hit the
same CAD face (or all miss) is *uniform* and takes its centre ray's grey,
unless the five greys spread by more than a grey level (a strongly curved
face); the rest, with their eight neighbours (which catches the tip of a
face that pokes into a pixel between its samples), are supersampled with ``n x n`` rays on a rotated lattice
whose ``n**2`` x offsets and ``n**2`` y offsets are all distinct, so the
coverage of an edge parallel to either pixel axis is resolved to
``1 / n**2`` of a pixel, not ``1 / n``. Each ray of a supersampled pixel is
spread over the pixels around it with the PSF integrated over their squares;
a uniform pixel's grey is spread with that weight averaged over its own
square (:func:`optics`).

Shading is Lambertian and view-independent: ``ambient + albedo * max(0,
n . l)`` for a directional light fixed in the rig frame, a uniform dark
background where rays miss. The same light shines for both cameras, so a
surface point has the same grey in the left and the right image.

The mesh is ray-cast in the part frame (coordinates of tens of mm, where
float32 resolves 1e-5 mm) and every ray starts at the part's bounding
sphere rather than at the camera, so the float32 ray caster loses nothing
measurable: 1/64 px is about 1e-3 mm on the part at 400 mm.

References
----------
.. [1] Pharr, M., Jakob, W., Humphreys, G. *Physically Based Rendering*,
       3rd ed., ch. 7 (sampling and reconstruction; stratified and
       n-rooks patterns). Morgan Kaufmann, 2016.
.. [2] Wald, I. et al. (2014). Embree: a kernel framework for efficient CPU
       ray tracing. ACM Trans. Graph. 33(4), 143 (the ray caster behind
       Open3D's RaycastingScene).
"""

from dataclasses import dataclass

import numpy as np

from scipy import ndimage

from partinspect.vision.calibration import undistort_points

__all__ = [
    "Shading",
    "DEFAULT_SHADING",
    "RaycastScene",
    "build_scene",
    "camera_in_part",
    "pixel_rays",
    "cast",
    "shade",
    "sample_pattern",
    "render_radiance",
    "optics",
    "sensor",
    "render_pair",
]

MISS = -1
"""Label of a ray that hits nothing."""
SAMPLES = 16
"""An edge pixel is integrated with ``SAMPLES x SAMPLES`` rays. With 8 (64
rays) the coverage of a straight edge is resolved to 1/64 px along the pixel
axes but more coarsely at other angles: on noise-free renders of the sample
plate the edge points of its straight edges lay 0.008-0.015 px (standard
deviation) about the true line in a pattern repeating every 8-16 px along it,
the same in every noise draw, which widened the straightness over noise
draws and biased it upwards (bench_plan, 50 draws: plate line-3, -19 and
-20 at 0.68-0.83 of their predicted spread). With 16, 0.002-0.007 px, and every
plate straightness within 20 % of its prediction; a half-size pair takes
2.5 times as long to render (4.4 -> 11.2 s)."""
_CHUNK = 1 << 20  # rays per ray-caster call: ~100 MB of temporaries


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
    above the optical axis, like a ring or bar light on the rig. For the
    default pose it puts the part's +Z, -Y and -X faces at about 213, 163
    and 117 grey levels (at least 46 apart) and faces turned away at the
    ambient 65, 40 above the background of 25, so every silhouette shows.
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
    """A triangle mesh loaded into Open3D's ray caster, with what shading needs.

    Attributes
    ----------
    scene : open3d.t.geometry.RaycastingScene
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
    import open3d as o3d

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
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32))
    )
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
    import open3d as o3d

    origin = np.asarray(origin, dtype=float)
    # Start the rays where they enter the bounding sphere (less a margin),
    # computed in float64, so float32 ray origins stay near the part.
    skip = max(0.0, float(np.linalg.norm(origin - rs.center)) - rs.radius - 1.0)
    n = len(directions)
    label = np.empty(n, np.int64)
    tri = np.empty(n, np.int64)
    bary = np.empty((n, 2), np.float32)
    dist = np.empty(n, np.float64)
    for a in range(0, n, _CHUNK):
        d = directions[a : a + _CHUNK]
        rays = np.empty((len(d), 6), np.float32)
        rays[:, :3] = origin + skip * d
        rays[:, 3:] = d
        out = rs.scene.cast_rays(o3d.core.Tensor(rays))
        prim = out["primitive_ids"].numpy().astype(np.int64)
        hit = prim != rs.scene.INVALID_ID
        prim[~hit] = 0
        tri[a : a + len(d)] = prim
        label[a : a + len(d)] = np.where(hit, rs.labels[prim], MISS)
        bary[a : a + len(d)] = out["primitive_uvs"].numpy()
        dist[a : a + len(d)] = np.where(hit, skip + out["t_hit"].numpy().astype(np.float64), np.inf)
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
    tri = hits.triangle[hit]
    u = hits.bary[hit, 0:1].astype(float)
    v = hits.bary[hit, 1:2].astype(float)
    cn = rs.corner_normals[tri]
    n = (1.0 - u - v) * cn[:, 0] + u * cn[:, 1] + v * cn[:, 2]
    # A closed solid is seen from outside; flip by the geometric normal only,
    # so a smooth normal near a silhouette keeps its side.
    facing = np.einsum("ij,ij->i", rs.flat_normals[tri], directions[hit])
    n *= np.where(facing > 0, -1.0, 1.0)[:, None] / np.linalg.norm(n, axis=1)[:, None]
    grey[hit] = shading.ambient + shading.albedo * np.maximum(0.0, n @ light)
    return grey


def sample_pattern(n):
    """Sub-pixel sample offsets with ``n**2`` distinct x and distinct y values.

    A rotated ``n x n`` lattice (generators ``(n, 1) / n**2`` and
    ``(1, n) / n**2``): one sample in each cell of the ``n x n`` grid and one
    in each of the ``n**2`` columns and rows (an n-rooks pattern).

    Parameters
    ----------
    n : int

    Returns
    -------
    offsets : ndarray, shape (n * n, 2)
        ``(du, dv)`` in ``(-0.5, 0.5)``, pixels from the pixel centre.
    """
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    i, j = i.ravel(), j.ravel()
    m = n * n
    return np.stack([(i * n + j + 0.5) / m - 0.5, (j * n + i + 0.5) / m - 0.5], axis=1)


def _cast_grid(rs, K, D, R, t, us, vs, light, shading, want_grey):
    """Cast one ray per point of the grid ``us x vs``; labels (and greys) as (len(vs), len(us))."""
    nu = len(us)
    total = nu * len(vs)
    label = np.empty(total, np.int64)
    grey = np.empty(total, np.float32) if want_grey else None
    for a in range(0, total, _CHUNK):
        idx = np.arange(a, min(total, a + _CHUNK))
        uv = np.stack([us[idx % nu], vs[idx // nu]], axis=1)
        origin, d = pixel_rays(uv, K, D, R, t)
        h = cast(rs, origin, d)
        label[idx] = h.label
        if want_grey:
            grey[idx] = shade(rs, h, d, light, shading)
    label = label.reshape(len(vs), nu)
    return label, (None if grey is None else grey.reshape(len(vs), nu))


def _supersample(rs, K, D, R, t, rows, cols, offsets, light, shading, detail=None):
    """Mean grey of pixels (rows, cols) over the sub-pixel ``offsets``.

    With ``detail = (image, psf)``, also adds to ``image`` what the PSF
    spreads of each pixel's rays beyond what its mean grey spreads
    (see :func:`optics`).
    """
    m = len(offsets)
    out = np.empty(len(rows), np.float32)
    step = max(1, _CHUNK // m)
    if detail is not None:
        image, psf = detail
        weights, kc, rad = _ray_weights(offsets, psf)
        height, width = image.shape
        flat = image.reshape(-1)
        dy, dx = (v.ravel() for v in np.mgrid[-rad : rad + 1, -rad : rad + 1])
    for a in range(0, len(rows), step):
        r, c = rows[a : a + step], cols[a : a + step]
        uv = np.empty((len(r), m, 2))
        uv[..., 0] = c[:, None] + offsets[:, 0]
        uv[..., 1] = r[:, None] + offsets[:, 1]
        origin, d = pixel_rays(uv.reshape(-1, 2), K, D, R, t)
        g = shade(rs, cast(rs, origin, d), d, light, shading).reshape(len(r), m)
        out[a : a + step] = g.mean(axis=1)
        if detail is not None:
            extra = g.astype(np.float64) @ weights - g.mean(axis=1, dtype=np.float64)[:, None] * kc[None, :]
            yy, xx = r[:, None] + dy[None, :], c[:, None] + dx[None, :]
            ok = (yy >= 0) & (yy < height) & (xx >= 0) & (xx < width)
            np.add.at(flat, (yy * width + xx)[ok], extra[ok])
    return out


def render_radiance(
    rs, K, D, R, t, image_size, light, shading=DEFAULT_SHADING, *, samples=SAMPLES, adaptive=True, grey_tolerance=1.0,
    psf=0.0,
):
    """Noiseless grey image of one camera: the radiance blurred by the PSF, integrated over each pixel.

    Parameters
    ----------
    rs : RaycastScene
    K, D : camera matrix and distortion vector.
    R, t : part-to-camera pose, ``x_cam = R @ X + t``, mm.
    image_size : (width, height)
    light : ndarray, shape (3,)
        Unit direction towards the light, part frame.
    shading : Shading
    samples : int
        ``samples x samples`` rays integrate a pixel that is supersampled.
    adaptive : bool
        True: supersample only pixels whose corner and centre rays do not all
        hit the same CAD face, or whose five greys spread by more than
        ``grey_tolerance`` (a strongly curved face). False: supersample every
        pixel (the plain, slow baseline).
    grey_tolerance : float
        Grey levels; see ``adaptive``.
    psf : float
        Standard deviation of the optics' Gaussian PSF, px; 0 gives each
        pixel's mean radiance over its area (no blur).

    Returns
    -------
    image : ndarray of float32, shape (height, width)
        Grey levels.
    stats : dict
        ``rays`` cast and ``supersampled`` pixel count.
    """
    w, h = (int(s) for s in image_size)
    offsets = sample_pattern(samples)
    detail = (np.zeros((h, w)), float(psf)) if psf > 0 else None
    if not adaptive:
        rows, cols = np.divmod(np.arange(w * h), w)
        img = _supersample(rs, K, D, R, t, rows, cols, offsets, light, shading, detail).reshape(h, w)
        return _with_psf(img, detail, offsets), {"rays": w * h * len(offsets), "supersampled": w * h}
    corner, cgrey = _cast_grid(rs, K, D, R, t, np.arange(w + 1) - 0.5, np.arange(h + 1) - 0.5, light, shading, True)
    centre, img = _cast_grid(rs, K, D, R, t, np.arange(w, dtype=float), np.arange(h, dtype=float), light, shading, True)
    uniform = np.ones((h, w), bool)
    lo, hi = img.copy(), img.copy()
    for dv, du in ((0, 0), (0, 1), (1, 0), (1, 1)):
        uniform &= corner[dv : dv + h, du : du + w] == centre
        lo = np.minimum(lo, cgrey[dv : dv + h, du : du + w])
        hi = np.maximum(hi, cgrey[dv : dv + h, du : du + w])
    # On a curved face the centre ray's grey is the pixel's mean only while
    # the shading is nearly linear across the pixel.
    uniform &= hi - lo <= grey_tolerance
    # A face's tip or a grazing sliver can poke into a pixel between its five
    # samples; it comes from a neighbouring pixel where it is wider, so
    # supersample the neighbours of every non-uniform pixel too.
    uniform &= ~ndimage.binary_dilation(~uniform, structure=np.ones((3, 3), bool))
    rows, cols = np.nonzero(~uniform)
    img[rows, cols] = _supersample(rs, K, D, R, t, rows, cols, offsets, light, shading, detail)
    rays = (w + 1) * (h + 1) + w * h + len(rows) * len(offsets)
    return _with_psf(img, detail, offsets), {"rays": rays, "supersampled": len(rows)}


def _with_psf(img, detail, offsets):
    if detail is None:
        return img
    import cv2

    image, psf = detail
    # Uniform pixels spread with the rays' own kernel, not psf_kernel's exact
    # one, so that a pixel spreads alike whether it was supersampled or not.
    # With the exact kernel here, the rays' quadrature error (up to 0.0018
    # of a weight) was left wherever supersampled and uniform pixels meet: a
    # pattern of up to 0.6 grey along every edge's band that moved the edges
    # of rendered parts by up to 0.005 px against full supersampling.
    _, kc, rad = _ray_weights(offsets, psf)
    spread = cv2.filter2D(np.asarray(img, np.float64), -1, kc.reshape(2 * rad + 1, 2 * rad + 1),
                          borderType=cv2.BORDER_REPLICATE)
    return (spread + image).astype(np.float32)


def _box_psf(d, psf):
    """Weight a pixel gives a point at offset d (px, one axis) from its centre.

    The Gaussian PSF integrated over the pixel's width:
    ``Phi((d + 1/2) / psf) - Phi((d - 1/2) / psf)``.
    """
    from scipy.special import ndtr

    return ndtr((d + 0.5) / psf) - ndtr((d - 0.5) / psf)


def _psf_radius(psf):
    """Pixels beyond which the PSF's weight is below 1e-9."""
    return int(np.ceil(0.5 + 6.0 * psf))


def psf_kernel(psf):
    """1-D weights a pixel of uniform grey gives its neighbours.

    The Gaussian PSF integrated over the receiving pixel and averaged over
    the emitting one: ``F(k + 1) - 2 F(k) + F(k - 1)`` with ``F`` the
    integral of the PSF's CDF, ``F(x) = x Phi(x / s) + s phi(x / s)``.

    Parameters
    ----------
    psf : float
        Standard deviation of the Gaussian PSF, px (> 0).

    Returns
    -------
    ndarray, shape (2R + 1,)
        Weights for offsets -R..R px; they sum to 1.
    """
    from scipy.special import ndtr

    R = _psf_radius(psf)
    k = np.arange(-R - 1, R + 2, dtype=float)
    F = k * ndtr(k / psf) + psf * np.exp(-0.5 * (k / psf) ** 2) / np.sqrt(2.0 * np.pi)
    return F[2:] - 2.0 * F[1:-1] + F[:-2]


def _ray_weights(offsets, psf):
    """Per-ray weights of a supersampled pixel for its (2R+1)^2 neighbours.

    Returns
    -------
    weights : ndarray, shape (m, (2R+1)^2)
        Ray s to neighbour (dy, dx), divided by the m rays, row-major in
        (dy, dx) from -R to R.
    kc : ndarray, shape ((2R+1)^2,)
        The same for a pixel of uniform grey: the sum of ``weights`` over the
        rays. It is :func:`psf_kernel`'s outer product to the lattice's
        quadrature error (up to 0.0018 of a weight at 16 x 16 rays, halving
        as n doubles), and point-symmetric (so is the lattice), so it sums
        to 1 and moves nothing.
    R : int
    """
    R = _psf_radius(psf)
    k = np.arange(-R, R + 1, dtype=float)
    wx = _box_psf(k[None, :] - offsets[:, :1], psf)  # (m, 2R+1)
    wy = _box_psf(k[None, :] - offsets[:, 1:], psf)
    weights = (wy[:, :, None] * wx[:, None, :]).reshape(len(offsets), -1) / len(offsets)
    return weights, weights.sum(axis=0), R


def optics(image, psf):
    """Blur of an image whose every pixel is of uniform grey.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Mean radiance over each pixel, grey levels.
    psf : float
        Standard deviation of the Gaussian PSF, px; 0 returns a copy.

    Returns
    -------
    ndarray of float64, shape (H, W)
        Each pixel's integral of the blurred radiance (:func:`psf_kernel`
        along both axes), borders replicated. Exact where the radiance is
        uniform within each pixel (:func:`render_radiance` spreads its
        pixels with its rays' own kernel instead, see :func:`_ray_weights`).
    """
    import cv2

    image = np.asarray(image, dtype=np.float64)
    if psf <= 0:
        return image.copy()
    k = psf_kernel(psf)
    return cv2.sepFilter2D(image, -1, k, k, borderType=cv2.BORDER_REPLICATE)


def sensor(image, noise, rng):
    """Add sensor noise and quantise to 8 bits.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey levels.
    noise : float
        Standard deviation of additive Gaussian noise, grey levels.
    rng : numpy.random.Generator

    Returns
    -------
    ndarray of uint8, shape (H, W)
        ``clip(round(image + noise * N(0, 1)), 0, 255)``.
    """
    x = np.asarray(image, dtype=np.float64)
    if noise > 0:
        x = x + noise * rng.standard_normal(x.shape)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def render_pair(
    mesh_or_scene,
    calib,
    part_to_camera,
    *,
    noise=2.0,
    seed=0,
    blur_sigma=0.6,
    samples=SAMPLES,
    adaptive=True,
    shading=DEFAULT_SHADING,
    progress=None,
):
    """Render the left and right 8-bit images of a part.

    Parameters
    ----------
    mesh_or_scene : trimesh.Trimesh or RaycastScene
        The part, part frame, mm.
    calib : StereoCalibration
        Gives image size, intrinsics, distortion and the right camera's pose.
    part_to_camera : ndarray, shape (4, 4)
        Part frame to left camera (rig) frame.
    noise : float
        Sensor noise, grey levels (standard deviation).
    seed : int
        Seed of ``numpy.random.default_rng``; the left image's noise is drawn
        first, the right image's next, so they are independent.
    blur_sigma : float
        Standard deviation of the optics' Gaussian PSF, pixels.
    samples : int
        Supersampling of edge pixels is ``samples x samples``.
    adaptive : bool
        See :func:`render_radiance`.
    shading : Shading
    progress : callable or None
        Called with a short message at each stage.

    Returns
    -------
    images : tuple of two ndarray of uint8, shape (H, W)
        Left, right.
    stats : dict
        Rays cast and supersampled pixels per camera.
    """
    rs = mesh_or_scene if isinstance(mesh_or_scene, RaycastScene) else build_scene(mesh_or_scene)
    P = np.asarray(part_to_camera, dtype=float)
    light = P[:3, :3].T @ shading.direction()
    rng = np.random.default_rng(seed)
    images, stats = [], {}
    for index, name in enumerate(("left", "right")):
        if progress:
            progress(f"ray casting the {name} image")
        K, D, R, t = camera_in_part(calib, index, P)
        radiance, stats[name] = render_radiance(
            rs, K, D, R, t, calib.image_size, light, shading, samples=samples, adaptive=adaptive, psf=blur_sigma
        )
        images.append(sensor(radiance, noise, rng))
    return tuple(images), stats
