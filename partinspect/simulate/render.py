"""Ray-cast rendering of a tessellated part through calibrated cameras.

Every sample of the image is a ray: a position in *distorted* pixel
coordinates is mapped to its viewing direction by the calibration's exact
undistortion, so lens distortion is rendered through the model itself. The
image forms as in a camera: the optics blur the radiance with a Gaussian
PSF, each pixel integrates the blurred irradiance over its square, and the
sensor adds noise and quantises to 8 bits. The order matters: blurring the
pixels' means afterwards, as a digital filter would, gives an edge profile
the sub-pixel estimator reads with a different bias from a camera's.

Area integration is adaptive: one ray at every pixel corner and centre; a
pixel whose five samples hit the same CAD face (or all miss) with greys
within ``grey_tolerance`` is *uniform* and takes its centre's grey; the
rest, and their eight neighbours (a face's tip can poke in between the
samples), are supersampled with ``n x n`` rays on a rotated lattice whose
``n**2`` x and y offsets are all distinct, so an edge along a pixel axis is
resolved to ``1 / n**2`` px. Each ray is spread over the surrounding pixels
with the PSF integrated over their squares, a uniform pixel's grey with the
rays' own kernel (:func:`_ray_weights`). Shading is Lambertian and
view-independent (:class:`partinspect.cad.raycast.Shading`), so a surface
point has the same grey in both images. Rays start at the part's bounding
sphere, in the part frame, so float32 ray casting loses nothing measurable.

References
----------
.. [1] Pharr, M., Jakob, W., Humphreys, G. *Physically Based Rendering*,
       3rd ed., ch. 7 (sampling and reconstruction; stratified and
       n-rooks patterns). Morgan Kaufmann, 2016.
.. [2] Wald, I. et al. (2014). Embree: a kernel framework for efficient CPU
       ray tracing. ACM Trans. Graph. 33(4), 143 (the ray caster, through
       embreex).
"""

import numpy as np

from scipy import ndimage

from partinspect.cad.raycast import (
    DEFAULT_SHADING,
    RAY_CHUNK,
    RaycastScene,
    build_scene,
    camera_in_part,
    cast,
    pixel_rays,
    shade,
)

__all__ = [
    "sample_pattern",
    "render_radiance",
    "optics",
    "sensor",
    "render_pair",
    "render_radiance_pair",
    "scene_radiance_pair",
    "camera_vignetting",
]

SAMPLES = 16
"""An edge pixel is integrated with ``SAMPLES x SAMPLES`` rays. Fewer resolve
an edge's coverage coarsely at angles off the pixel axes, which leaves a
fixed ripple of edge points about the true line, the same in every noise
draw, that widens straightness over draws and biases it upward; 16 brings
that ripple well below the noise."""
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


def _grey(rs, hits, origin, d, light, shading, finish, K, marks=True):
    """Grey of every ray: Lambertian ``shading``, or the metal ``finish`` seen through camera ``K``."""
    if finish is None:
        return shade(rs, hits, d, light, shading)
    from partinspect.simulate.material import shade_material

    return shade_material(rs, hits, origin, d, light, shading, finish, 1.0 / float(K[0, 0]), marks=marks)


def _cast_grid(rs, K, D, R, t, us, vs, light, shading, finish=None):
    """Cast one ray per point of the grid ``us x vs``.

    Returns labels, greys and the greys that decide uniformity (without a
    finish's machining marks, which are band-limited to the pixel already),
    each (len(vs), len(us)).
    """
    nu = len(us)
    total = nu * len(vs)
    label = np.empty(total, np.int64)
    grey = np.empty(total, np.float32)
    smooth = grey if finish is None else np.empty(total, np.float32)
    for a in range(0, total, RAY_CHUNK):
        idx = np.arange(a, min(total, a + RAY_CHUNK))
        uv = np.stack([us[idx % nu], vs[idx // nu]], axis=1)
        origin, d = pixel_rays(uv, K, D, R, t)
        h = cast(rs, origin, d)
        label[idx] = h.label
        grey[idx] = _grey(rs, h, origin, d, light, shading, finish, K)
        if finish is not None:
            smooth[idx] = _grey(rs, h, origin, d, light, shading, finish, K, marks=False)
    shape = (len(vs), nu)
    return label.reshape(shape), grey.reshape(shape), smooth.reshape(shape)


def _supersample(rs, K, D, R, t, rows, cols, offsets, light, shading, detail=None, finish=None):
    """Mean grey of pixels (rows, cols) over the sub-pixel ``offsets``.

    With ``detail = (image, psf)``, also adds to ``image`` what the PSF
    spreads of each pixel's rays beyond what its mean grey spreads
    (see :func:`optics`).
    """
    m = len(offsets)
    out = np.empty(len(rows), np.float32)
    step = max(1, RAY_CHUNK // m)
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
        g = _grey(rs, cast(rs, origin, d), origin, d, light, shading, finish, K).reshape(len(r), m)
        out[a : a + step] = g.mean(axis=1)
        if detail is not None:
            extra = g.astype(np.float64) @ weights - g.mean(axis=1, dtype=np.float64)[:, None] * kc[None, :]
            yy, xx = r[:, None] + dy[None, :], c[:, None] + dx[None, :]
            ok = (yy >= 0) & (yy < height) & (xx >= 0) & (xx < width)
            np.add.at(flat, (yy * width + xx)[ok], extra[ok])
    return out


def render_radiance(
    rs, K, D, R, t, image_size, light, shading=DEFAULT_SHADING, *, samples=SAMPLES, adaptive=True, grey_tolerance=1.0,
    psf=0.0, finish=None,
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
    finish : Finish or None
        None: Lambertian ``shading``. Else a metal
        (:func:`partinspect.simulate.material.shade_material`); uniformity
        is then judged on the grey without machining marks.

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
        img = _supersample(rs, K, D, R, t, rows, cols, offsets, light, shading, detail, finish).reshape(h, w)
        return _with_psf(img, detail, offsets), {"rays": w * h * len(offsets), "supersampled": w * h}
    corner, _, cgrey = _cast_grid(rs, K, D, R, t, np.arange(w + 1) - 0.5, np.arange(h + 1) - 0.5, light, shading,
                                  finish)
    centre, img, smooth = _cast_grid(rs, K, D, R, t, np.arange(w, dtype=float), np.arange(h, dtype=float), light,
                                     shading, finish)
    uniform = np.ones((h, w), bool)
    lo, hi = smooth.copy(), smooth.copy()
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
    img[rows, cols] = _supersample(rs, K, D, R, t, rows, cols, offsets, light, shading, detail, finish)
    rays = (w + 1) * (h + 1) + w * h + len(rows) * len(offsets)
    return _with_psf(img, detail, offsets), {"rays": rays, "supersampled": len(rows)}


def _with_psf(img, detail, offsets):
    if detail is None:
        return img
    import cv2

    image, psf = detail
    # Uniform pixels spread with the rays' own kernel, not psf_kernel's exact
    # one, so that a pixel spreads alike whether it was supersampled or not:
    # with the exact kernel the rays' quadrature error would be left wherever
    # supersampled and uniform pixels meet, a grey pattern along every edge's
    # band that moves the edges.
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
        rays. It is :func:`psf_kernel`'s outer product up to the lattice's
        quadrature error (which shrinks as n grows), and point-symmetric (so
        is the lattice), so it sums to 1 and moves nothing.
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
    finish=None,
    lens=None,
    photon=None,
    pitch=None,
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
    finish : Finish or None
        None: Lambertian ``shading``. Else a metal's microfacet reflection
        and machining marks (:func:`partinspect.simulate.material.finish`).
    lens : ThinLens or None
        None: every depth in focus. Else the depth of field of
        :mod:`partinspect.simulate.defocus`, on top of the optics' PSF.
    photon : PhotonSensor or None
        None: Gaussian noise of ``noise`` grey levels. Else the photon
        sensor of :mod:`partinspect.simulate.photon` with cos^4 vignetting,
        and ``noise`` is not used.
    pitch : float or None
        Pixel pitch, mm, for ``lens`` (its focal length is ``K[0, 0] *
        pitch``).

    Returns
    -------
    images : tuple of two ndarray of uint8, shape (H, W)
        Left, right.
    stats : dict
        Rays cast and supersampled pixels per camera; with ``lens``, also
        each camera's smallest and largest blur circle (``coc_px``).
    """
    radiances, stats = scene_radiance_pair(
        mesh_or_scene, calib, part_to_camera, blur_sigma=blur_sigma, samples=samples, adaptive=adaptive,
        shading=shading, progress=progress, finish=finish, lens=lens, pitch=pitch,
    )
    # The left image's noise is drawn before the right's: the same seed gives the same pair as ever.
    rng = np.random.default_rng(seed)
    images = []
    for index, radiance in enumerate(radiances):
        if photon is None:
            images.append(sensor(radiance, noise, rng))
        else:
            from partinspect.simulate.photon import photon_sensor

            images.append(photon_sensor(radiance, photon, rng, camera_vignetting(calib, index)))
    return tuple(images), stats


def camera_vignetting(calib, index):
    """cos^4 relative irradiance of camera ``index`` (0 left, 1 right), shape (H, W)."""
    from partinspect.simulate.photon import cos4_vignetting

    K, D, _, _ = calib.camera(index)
    return cos4_vignetting(K, D, calib.image_size)


def scene_radiance_pair(
    mesh_or_scene,
    calib,
    part_to_camera,
    *,
    blur_sigma=0.6,
    samples=SAMPLES,
    adaptive=True,
    shading=DEFAULT_SHADING,
    progress=None,
    finish=None,
    lens=None,
    pitch=None,
):
    """The noiseless left and right radiance a sensor would read (float grey levels).

    What :func:`render_pair` forms before its sensor: the optics' PSF, a
    metal ``finish`` and a ``lens``'s depth of field included, no noise, no
    vignetting, no quantisation. A Monte Carlo check casts the rays once and
    draws each noise from these (:func:`sensor`, or
    :func:`partinspect.simulate.photon.photon_sensor` with
    :func:`camera_vignetting`).

    Parameters are those of :func:`render_pair`.

    Returns
    -------
    radiances : tuple of two ndarray of float, shape (H, W)
        Left, right.
    stats : dict
        As :func:`render_pair`'s.
    """
    rs = mesh_or_scene if isinstance(mesh_or_scene, RaycastScene) else build_scene(mesh_or_scene)
    P = np.asarray(part_to_camera, dtype=float)
    light = P[:3, :3].T @ shading.direction()
    radiances, stats = [], {}
    for index, name in enumerate(("left", "right")):
        if progress:
            progress(f"ray casting the {name} image")
        K, D, R, t = camera_in_part(calib, index, P)
        radiance, stats[name] = render_radiance(
            rs, K, D, R, t, calib.image_size, light, shading, samples=samples, adaptive=adaptive, psf=blur_sigma,
            finish=finish,
        )
        if lens is not None:
            from partinspect.simulate.defocus import defocus_camera

            if progress:
                progress(f"defocusing the {name} image")
            radiance, coc = defocus_camera(radiance, rs, K, D, R, t, lens, pitch)
            stats[name]["coc_px"] = [float(coc.min()), float(coc.max())]
        radiances.append(radiance)
    return tuple(radiances), stats


def render_radiance_pair(scene, calib, part_to_camera, *, blur_sigma=0.6, shading=None, samples=None):
    """The noiseless, blurred left and right images (float32 grey levels): :func:`scene_radiance_pair`'s.

    Each draw of a Monte Carlo check is ``sensor(image, noise, rng)`` of
    these: the ray casting is done once.
    """
    radiances, _ = scene_radiance_pair(scene, calib, part_to_camera, blur_sigma=blur_sigma,
                                       shading=shading or DEFAULT_SHADING,
                                       samples=SAMPLES if samples is None else samples)
    return radiances
