"""Depth of field: a thin lens's blur circle, growing with depth away from focus.

A thin lens of focal length ``f`` focused at distance ``z_f`` puts its
sensor at ``s_f = f z_f / (z_f - f)``; a point at depth ``z`` converges at
``s = f z / (z - f)``, so its cone of light, as wide as the aperture
``A = f / N`` at the lens, cuts the sensor in a circle of diameter

    c = A |s - s_f| / s = (f / N) * f |z - z_f| / (z (z_f - f)),

the circle of confusion (geometric optics; diffraction is the optics PSF's
part). ``f`` in mm comes from the camera matrix's focal length in pixels
times the pixel pitch, ``z`` is the depth along the optical axis (the camera
frame's z), and ``c`` in pixels is ``c / pitch``.

The image is blurred with a uniform disc of that diameter per pixel, from
the depth of the surface its centre ray hits: the image is blurred once per
level of a ladder of diameters ``LEVEL_STEP`` px apart, and each pixel takes
the linear blend of the two levels around its own diameter (a gather, as
layered depth-of-field renderers do; at an occluding edge the nearer and
farther surfaces share one pixel's blur). Background pixels take the depth
of the nearest pixel that hits the part, so a silhouette spreads with its
own surface's blur.

References
----------
.. [1] Potmesil, M., Chakravarty, I. (1981). A lens and aperture camera
       model for synthetic image generation. Computer Graphics 15(3),
       297-305 (SIGGRAPH '81).
.. [2] Smith, W. J. *Modern Optical Engineering*, 4th ed., sec. 6.7 (depth
       of focus and the blur circle). McGraw-Hill, 2008.
"""

from dataclasses import dataclass

import numpy as np

__all__ = ["LEVEL_STEP", "ThinLens", "parse_defocus", "circle_of_confusion", "depth_map", "disc_kernel", "defocus", "defocus_camera"]

LEVEL_STEP = 0.5
"""Spacing of the blur ladder's diameters, px."""


@dataclass(frozen=True)
class ThinLens:
    """Aperture and focus of the camera lenses.

    Attributes
    ----------
    f_number : float
        N, focal length over aperture diameter.
    focus : float
        Depth of the plane in focus along each camera's optical axis, mm.
    """

    f_number: float
    focus: float


def parse_defocus(text):
    """``F_NUMBER,FOCUS_MM`` as a :class:`ThinLens`.

    Raises
    ------
    ValueError
        Not two numbers, or an f-number not in [0.5, 64] or a focus not > 0.
    """
    try:
        n, focus = (float(v) for v in str(text).split(","))
    except ValueError:
        raise ValueError(f"expected F_NUMBER,FOCUS_MM, got {text!r}") from None
    if not (0.5 <= n <= 64 and 0 < focus < 1e6):
        raise ValueError(f"f-number must be in [0.5, 64] and the focus distance > 0 mm, got {text!r}")
    return ThinLens(n, focus)


def circle_of_confusion(depth, lens, focal_length, pitch):
    """Blur circle diameter on the sensor, px.

    Parameters
    ----------
    depth : ndarray
        Depth along the optical axis, mm (> focal_length).
    lens : ThinLens
    focal_length : float
        mm.
    pitch : float
        Pixel pitch, mm.

    Returns
    -------
    ndarray
        ``(f / N) f |z - z_f| / (z (z_f - f)) / pitch``, the shape of ``depth``.

    Raises
    ------
    ValueError
        If the focus lies within the focal length (no real image).
    """
    f = float(focal_length)
    if not lens.focus > f:
        raise ValueError(f"the focus distance {lens.focus} mm must exceed the focal length {f:.1f} mm")
    z = np.asarray(depth, dtype=float)
    return (f / lens.f_number) * f * np.abs(z - lens.focus) / (z * (lens.focus - f)) / pitch


def depth_map(rs, K, D, R, t, image_size):
    """Depth (camera z, mm) of the surface each pixel centre sees; NaN where it sees nothing.

    Parameters
    ----------
    rs : RaycastScene
    K, D : camera matrix and distortion vector.
    R, t : part-to-camera pose, ``x_cam = R @ X + t``, mm.
    image_size : (width, height)

    Returns
    -------
    ndarray of float64, shape (height, width)
    """
    from partinspect.cad.raycast import RAY_CHUNK, cast, pixel_rays

    w, h = (int(s) for s in image_size)
    out = np.empty(w * h)
    for a in range(0, w * h, RAY_CHUNK):
        idx = np.arange(a, min(w * h, a + RAY_CHUNK))
        uv = np.stack([idx % w, idx // w], axis=1).astype(float)
        origin, d = pixel_rays(uv, K, D, R, t)
        dist = cast(rs, origin, d).distance
        # the ray's camera-frame z per mm of travel is its direction's third camera coordinate
        out[idx] = np.where(np.isfinite(dist), dist * (d @ R[2]), np.nan)
    return out.reshape(h, w)


def disc_kernel(diameter, oversample=8):
    """A uniform disc of ``diameter`` px, each weight the disc's area within that pixel.

    Returns
    -------
    ndarray, shape (2 r + 1, 2 r + 1)
        Sums to 1; ``[[1]]`` for a diameter of 0.
    """
    radius = 0.5 * float(diameter)
    r = int(np.ceil(radius))
    if radius <= 0:
        return np.ones((1, 1))
    s = (np.arange(oversample) + 0.5) / oversample - 0.5
    k = np.arange(-r, r + 1, dtype=float)
    x = (k[:, None] + s[None, :]).ravel()
    inside = (x[:, None] ** 2 + x[None, :] ** 2 <= radius * radius).astype(float)
    n = 2 * r + 1
    kernel = inside.reshape(n, oversample, n, oversample).sum(axis=(1, 3))
    if kernel.sum() == 0:  # a disc smaller than the sub-pixel lattice
        kernel[r, r] = 1.0
    return kernel / kernel.sum()


def defocus(image, coc):
    """Blur each pixel by the disc of its own diameter (levels blended linearly).

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey levels.
    coc : ndarray, shape (H, W)
        Blur circle diameter per pixel, px (>= 0, finite).

    Returns
    -------
    ndarray of float64, shape (H, W)
    """
    import cv2

    image = np.asarray(image, dtype=np.float64)
    level = np.asarray(coc, dtype=float) / LEVEL_STEP
    k = np.floor(level).astype(int)
    frac = level - k
    out = np.zeros_like(image)
    for j in range(int(k.max()) + 2):
        weight = np.where(k == j, 1.0 - frac, 0.0) + np.where(k == j - 1, frac, 0.0)
        if not weight.any():
            continue
        blurred = cv2.filter2D(image, -1, disc_kernel(j * LEVEL_STEP), borderType=cv2.BORDER_REPLICATE)
        out += weight * blurred
    return out


def defocus_camera(image, rs, K, D, R, t, lens, pitch):
    """The defocused image of one camera and its blur circle map.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        The in-focus image, grey levels.
    rs, K, D, R, t
        As :func:`depth_map`.
    lens : ThinLens
    pitch : float
        Pixel pitch, mm; the focal length is ``K[0, 0] * pitch``.

    Returns
    -------
    image : ndarray of float64, shape (H, W)
    coc : ndarray, shape (H, W)
        Blur circle diameter used at each pixel, px.
    """
    from scipy import ndimage

    h, w = image.shape
    depth = depth_map(rs, K, D, R, t, (w, h))
    miss = np.isnan(depth)
    if miss.all():
        return np.asarray(image, np.float64).copy(), np.zeros((h, w))
    if miss.any():
        index = ndimage.distance_transform_edt(miss, return_distances=False, return_indices=True)
        depth = depth[tuple(index)]
    coc = circle_of_confusion(depth, lens, float(K[0, 0]) * pitch, pitch)
    return defocus(image, coc), coc
