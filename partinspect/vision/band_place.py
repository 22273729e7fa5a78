"""Where the apparent edge of a broken rim lies across its band, predicted from the light on the part.

A machined rim is broken (rounded or chamfered, ISO 13715) while its CAD
edge is sharp, and the step the edge detector finds lies somewhere across
the break's band: where, depends on the grey levels across the band, the
view and the blur. Without more knowledge that place is uniform across
the band (:mod:`partinspect.tolerances.edge_break`); this module predicts
it from physics read off the images, for a rim of the registered part:

1. *The light.* Beside the rim the image shows the rim's planar face and,
   where the camera looks into a hole (or at a boss), its wall. For a
   Lambertian surface under a distant light a face of outward unit normal
   ``n`` has the grey ``max(0, n . k) + a`` (``k`` the light's direction
   scaled by albedo and irradiance, ``a`` the ambient) [1]_. The face's
   grey read outside the rim and the wall's read inside it, round the rim,
   give ``A = n_face . k``, the wall's ``B(theta) = n_wall(theta) . k`` (a
   sinusoid round the rim) and ``a`` by least squares (:func:`fit_light`).
2. *The band's profile.* Across a fillet of radius R the normal turns from
   the face's to the wall's, ``n(psi) = sin(psi) n_face + cos(psi)
   n_wall``, and its grey follows from ``A``, ``B`` and ``a``; across a
   chamfer it is constant at the mean normal. Projected into each camera,
   up to where the band turns away from the camera (the occluding contour
   on the near side of a hole), between the face's grey and the grey read
   just past the band, it is a 1D profile across the rim
   (:func:`band_profile`).
3. *The detector.* The detector finds the maximum of the gradient of the
   image blurred by the edge's whole blur (optics, pixel and the
   derivative filter: ``EdgePoints.width``, read from the image), so the
   profile is blurred by a Gaussian of that width and its steepest place
   taken (:func:`apparent_place`).
4. *The size.* The apparent points of both images (the sharp rim's image
   moved by the predicted place at each angle) are fitted with the chain's
   own two-view circle fit (:func:`partinspect.vision.fit3d.fit_circle_3d`),
   and the fitted radius, less the sharp rim's, divided by the break's
   size is the band place ``s`` of the rim's size: 0 at the wall, 1 at the
   face's edge of the band.

Once the place is predicted, :func:`rims_at_sharp_edge` moves each of the
rim's edge points by its angle's place onto the sharp rim's image and fits
the rim again, each point carrying the prediction's own uncertainty
instead of the whole band: the fit then measures the wall's size.

ISO 13715 leaves the break's shape open, so the place is predicted for a
fillet and for a chamfer and the rim's ``s`` taken midway, the two being
the ends of a rectangular distribution (JCGM 100, 4.3.7). The light's
least-squares uncertainty is carried by moving its four parameters along
their covariance's principal directions (JCGM 100, 5.2), and what the
Lambertian model does not explain (its residual grey levels, as a share of
the grey-level step across the band, a share of the band) as a Type B
component of its own; the place's standard uncertainty never exceeds the
uniform band's ``1 / sqrt(12)``.

Frames: rim geometry in the part frame (mm), the pose ``part_to_camera``
into the left camera (the rig frame), images in distorted pixels.

References
----------
.. [1] B. K. P. Horn, Robot Vision, MIT Press, 1986, chapter 10 (image
       irradiance of a Lambertian surface).
.. [2] ISO 13715:2019, Technical product documentation -- Edges of
       undefined shape -- Indication and dimensioning.
.. [3] JCGM 100:2008 (GUM), 4.3.7 (rectangular distribution), 5.2
       (correlated input quantities).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import gaussian_filter1d, map_coordinates
from scipy.optimize import least_squares

from partinspect.vision.calibration import project_points
from partinspect.vision.fit3d import View, circle_residuals_at, fit_circle_3d
from partinspect.vision.fitting import fit_ellipse
from partinspect.vision.matching import Match
from partinspect.vision.stereo import measure_pair_feature

__all__ = ["BandPlace", "rim_section", "fit_light", "band_profile", "apparent_place", "observed_place", "band_place",
           "rims_at_sharp_edge", "camera_views", "pixel_size", "read_grey", "refit_pair", "with_refitted"]

FINE_ANGLES = 720
"""Angles at which the sharp rim's image is sampled to give each edge point its angle."""

ANGLES = 60
"""Angles round the rim at which the band is predicted."""

SECTION_SAMPLES = 100
"""Samples across the band's section."""

READ_WIDTHS = 3.0
"""How far beyond the band a face's grey is read, in edge widths: clear of the step's blur."""

RIVAL = 0.5
"""A second step counts as a rival of the steepest where its gradient reaches this share of it: the
detector's non-maximum suppression keeps both, and which one its chain links depends on the neighbours."""

UNIFORM_STD = 1.0 / math.sqrt(12.0)
"""Standard deviation of a place uniform across the band (nothing known)."""


@dataclass(frozen=True)
class BandPlace:
    """The predicted place of a broken rim's apparent edge across its band (0 the wall, 1 the face's side).

    Attributes
    ----------
    s : float
        Best estimate: midway between the extremes the break's shapes
        (fillet, chamfer) and any rival step give.
    u : float
        Its standard uncertainty: the shape's (rival steps included), the
        light fit's and the model's components combined, at most ``1 /
        sqrt(12)``.
    s_fillet, s_chamfer : float
        The place for each shape (steepest steps).
    u_shape, u_light, u_model : float
        The components.
    theta : ndarray, shape (n,)
        Angles round the rim (about its face's normal, from
        ``cross(normal, x)``), rad.
    offsets : (ndarray, ndarray), shape (n,) each
        Per image, the apparent step's place at each angle, px along the
        image direction towards the rim's face from the sharp rim's image
        (midway between the extremes the shapes and rival steps give; NaN
        where the band is not seen).
    u_point : float
        The standard uncertainty of one point's place, as a share of the
        break: the shapes' and rival steps' range at its angle
        (rectangular), the model's misfit and the light's, combined in
        quadrature (RMS over the angles), at most ``1 / sqrt(12)``.
    modes : (ndarray, ndarray), shape (k, n) each
        Per image, the place's errors that are shared round the rim and by
        both images, each as the displacement by one standard uncertainty
        at each angle, px along ``offsets``' direction (NaN where the band
        is not seen): first the shapes' and rival steps' range over
        ``sqrt(12)`` (one break and one light for the whole rim: the place
        lies at one share of its range everywhere, rectangular), then the
        light's principal directions (:func:`_place_modes`).
    u_rest : float
        What of ``u_point`` is not in ``modes``, as a share of the break:
        the model's misfit to the image's own steps, a point's own.
    """

    s: float
    u: float
    s_fillet: float
    s_chamfer: float
    u_shape: float
    u_light: float
    u_model: float
    theta: np.ndarray = None
    offsets: tuple = None
    u_point: float = None
    modes: tuple = None
    u_rest: float = None


def rim_section(shape, material_side, n=SECTION_SAMPLES):
    """A unit break's section from the face's edge (index 0) to the wall's (last).

    Parameters
    ----------
    shape : {"fillet", "chamfer"}
    material_side : {1, -1}
        +1 for a hole (the material lies at larger radius), -1 for a boss.
    n : int

    Returns
    -------
    radial, axial : ndarray, shape (n,)
        Offsets from the sharp rim per unit break size: radially out from
        the axis and along the face's outward normal.
    w_face, w_wall : ndarray, shape (n,)
        The section's unit normal as ``w_face n_face + w_wall n_wall``.
    """
    if shape == "fillet":
        psi = np.linspace(0.5 * np.pi, 0.0, n)
        radial, axial = material_side * (1.0 - np.cos(psi)), -(1.0 - np.sin(psi))
        return radial, axial, np.sin(psi), np.cos(psi)
    tau = np.linspace(1.0, 0.0, n)
    h = np.full(n, math.sqrt(0.5))
    return material_side * tau, -(1.0 - tau), h, h


def _light_model(p, theta, kind):
    A, b1, b2, a = p
    lit = np.where(kind == 0, A, b1 * np.cos(theta) + b2 * np.sin(theta))
    return np.maximum(lit, 0.0) + a


def fit_light(theta, grey, kind):
    """Least-squares Lambertian light round a rim: ``A``, the wall's sinusoid ``(b1, b2)`` and the ambient ``a``.

    Parameters
    ----------
    theta : ndarray, shape (N,)
        Angle round the rim of each sample, rad.
    grey : ndarray, shape (N,)
        Grey levels read beside the rim.
    kind : ndarray of int, shape (N,)
        0 for a sample of the rim's planar face (model ``max(0, A) + a``), 1
        for one of its wall (``max(0, b1 cos theta + b2 sin theta) + a``).

    Returns
    -------
    params : ndarray, shape (4,)
        ``(A, b1, b2, a)``, grey levels.
    cov : ndarray, shape (4, 4)
        Their covariance from the residuals (robust loss; Gauss-Newton form).
    rms : float
        The residuals' robust RMS, grey levels: what a Lambertian light does
        not explain here.
    """
    theta, grey, kind = (np.asarray(x) for x in (theta, grey, kind))
    face, wall = grey[kind == 0], grey[kind == 1]
    a0 = float(np.percentile(wall, 5)) if wall.size else float(np.min(grey))
    X = np.c_[np.cos(theta[kind == 1]), np.sin(theta[kind == 1])]
    b0 = np.linalg.lstsq(X, wall - a0, rcond=None)[0] if wall.size >= 2 else np.zeros(2)
    p0 = np.r_[float(np.median(face)) - a0 if face.size else 0.0, b0, a0]
    # Another edge read beside the rim is an outlier, not a misfit of the light: a robust loss at the
    # scale of a plain fit's residuals.
    first = least_squares(lambda p: _light_model(p, theta, kind) - grey, p0)
    scale = max(1.4826 * float(np.median(np.abs(first.fun - np.median(first.fun)))), 1e-6 * float(np.ptp(grey)) + 1e-12)
    fit = least_squares(lambda p: _light_model(p, theta, kind) - grey, first.x, loss="soft_l1", f_scale=scale)
    r = np.asarray(_light_model(fit.x, theta, kind) - grey)
    rms = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    J = fit.jac
    return fit.x, np.linalg.pinv(J.T @ J) * rms * rms, rms


def band_profile(u, grey, g_face, g_past, width, step=0.02):
    """The image's grey profile across the band, blurred by the edge's width, on a fine grid.

    Parameters
    ----------
    u : ndarray, shape (m,)
        Image coordinate of each visible section sample along the rim's
        outward image direction, px, face's end first.
    grey : ndarray, shape (m,)
        Their grey levels.
    g_face : float
        Grey level beyond the face's end (a plane under a distant light: constant).
    g_past : float or (float, float, float)
        Grey level past the band's visible end, or ``(x, g, slope)``: the
        grey ``g`` read at ``x`` and its slope along ``u`` there, extended
        linearly to the band (what is seen past a hole's near rim, the far
        wall, is shaded across).
    width : float
        The edge's whole blur (standard deviation), px.
    step : float
        Grid step, px.

    Returns
    -------
    grid, profile : ndarray
    """
    lo, hi = float(min(u.min(), u.max())), float(max(u.min(), u.max()))
    reach = 5.0 * width + 1.0
    grid = np.arange(lo - reach, hi + reach, step)
    order = np.argsort(u)
    prof = np.interp(grid, u[order], grey[order])
    x, g, slope = g_past if np.ndim(g_past) else (0.0, float(g_past), 0.0)
    past = g + slope * (grid - x)
    face_high = u[0] > u[-1]
    prof[grid > hi] = g_face if face_high else past[grid > hi]
    prof[grid < lo] = past[grid < lo] if face_high else g_face
    return grid, gaussian_filter1d(prof, width / step, mode="nearest")


def apparent_place(u, grey, g_face, g_past, width, rival=RIVAL):
    """Where the detector finds the step: the blurred profile's steepest place, and a rival, px (as ``u``).

    A band lit otherwise than both its faces has two steps (a highlight or
    a shadow along it): the detector's chain may follow either, so the
    second steepest local maximum of the gradient, where it reaches
    ``rival`` times the steepest, is returned as the other possible place.

    Parameters
    ----------
    u, grey, g_face, g_past, width
        As :func:`band_profile`.
    rival : float
        Share of the steepest step's gradient a second step must reach.

    Returns
    -------
    place, other : float
        ``other`` equals ``place`` where there is no rival step.
    """
    grid, prof = band_profile(u, grey, g_face, g_past, width)
    slope = np.abs(np.gradient(prof))
    peaks = np.flatnonzero((slope[1:-1] > slope[:-2]) & (slope[1:-1] >= slope[2:])) + 1
    if peaks.size == 0:
        return (float(grid[np.argmax(slope)]),) * 2
    order = peaks[np.argsort(slope[peaks])[::-1]]
    best = float(grid[order[0]])
    other = float(grid[order[1]]) if order.size > 1 and slope[order[1]] >= rival * slope[order[0]] else best
    return best, other


def _rim_frame(center, axis, radius, theta):
    """Sharp rim points (n, 3) and outward radial unit vectors (n, 3), part frame."""
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    rh = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    return center + radius * rh, rh


def read_grey(image, uv):
    """Bilinear grey levels at ``uv`` (k, 2), px: ``image`` is float already (:func:`band_place` converts it once)."""
    return map_coordinates(np.asarray(image, float), [uv[:, 1], uv[:, 0]], order=1, mode="nearest")


@dataclass(frozen=True)
class _Rim:
    """A rim in the part frame: centre, the face's outward normal, radius, material side, break size (internal)."""

    center: np.ndarray
    axis: np.ndarray
    radius: float
    side: int
    size: float


def camera_views(calib, part_to_camera):
    """Per camera: K, D, the part-to-camera rotation and translation, its centre in the part frame, its rig P."""
    T = np.asarray(part_to_camera, float)
    out = []
    for i in (0, 1):
        K, D, R, t = calib.camera(i)
        Rp, tp = R @ T[:3, :3], R @ T[:3, 3] + np.ravel(t)
        out.append((K, D, Rp, tp, -Rp.T @ tp, K @ np.c_[R, np.ravel(t)]))
    return tuple(out)


def pixel_size(calib, part_to_camera, point):
    """Per camera, the size of one pixel at a part-frame point, mm: its depth over the focal length.

    What a place across a band, stated in px as the prediction is made,
    is as a distance on the part (pinhole, JCGM 100 first order: the
    depth's variation across a band is negligible).

    Parameters
    ----------
    calib : StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
    point : array_like, shape (3,)
        Part frame, mm.

    Returns
    -------
    (float, float)
        Left, right, mm per px.
    """
    p = np.asarray(point, float)
    return tuple(float((R @ p + t)[2] / K[0, 0]) for K, _, R, t, _, _ in camera_views(calib, part_to_camera))


def refit_pair(stereo, calib, k, moved, scale, band, **extra):
    """The 3D feature ``stereo.features[k]`` measured again from its two moved image features, or None.

    ``moved``: its left and right image features with their points moved
    (onto the sharp edge's image); ``scale``: their noise's correlation
    length, px; ``band``: the Type B of where the step lies, mm
    (``edge_break`` of :func:`partinspect.vision.stereo.measure_pair_feature`);
    ``extra``: fields set on the new feature beside the old one's ``guided``.
    """
    f3 = stereo.features[k]
    new, _ = measure_pair_feature(Match(f3.left, f3.right, float("nan"), float("nan"), float("nan"), float("inf")),
                                  *moved, calib, stereo.geometry, scale, band)
    return None if new is None else replace(new, guided=f3.guided, **extra)


def with_refitted(stereo, refits):
    """``stereo`` with each pair of ``refits`` (index -> (left, right image feature, Feature3D)) in place of its own."""
    if not refits:
        return stereo
    lefts, rights, feats = list(stereo.left.features), list(stereo.right.features), list(stereo.features)
    for k, (fl, fr, f) in refits.items():
        f3 = stereo.features[k]
        lefts[f3.left], rights[f3.right], feats[k] = fl, fr, f
    return replace(stereo, left=replace(stereo.left, features=lefts), right=replace(stereo.right, features=rights),
                   features=tuple(feats))


def _outward(p0, rh, side, K, D, R, t):
    """The sharp rim's pixels and the unit image direction towards its face (the band's outer side)."""
    uv0 = project_points(p0, K, D, R, t)
    d = project_points(p0 + 0.01 * side * rh, K, D, R, t) - uv0
    return uv0, d / np.linalg.norm(d, axis=1, keepdims=True)


def _sections(rim, theta, shape):
    """Section points (a, m, 3) and normal weights of the rim's band at each angle."""
    radial, axial, wf, ww = rim_section(shape, rim.side)
    p0, rh = _rim_frame(rim.center, rim.axis, rim.radius, theta)
    P = p0[:, None] + rim.size * (radial[None, :, None] * rh[:, None] + axial[None, :, None] * rim.axis)
    n_wall = -rim.side * rh
    N = wf[None, :, None] * rim.axis + ww[None, :, None] * n_wall[:, None]
    return P, N, wf, ww, p0, rh


@dataclass(frozen=True)
class _SeenBand:
    """One image's view of a rim's band for one shape: all that no light changes (internal).

    Attributes
    ----------
    index : ndarray of int, shape (k,)
        The angles (indices into ``theta``) at which the band is seen.
    u : tuple of k ndarray, shape (m,) each
        At each, the visible section samples' image places along the
        outward direction, px, face's end first.
    reads : ndarray, shape (k, 2)
        The grey read beyond the face's end and past the band's visible end.
    observed : ndarray, shape (k,)
        The image's own steepest place there (:func:`observed_place`), px.
    w_face, w_wall : ndarray, shape (n,)
        The section's normal weights (:func:`rim_section`).
    """

    index: np.ndarray
    u: tuple
    reads: np.ndarray
    observed: np.ndarray
    w_face: np.ndarray
    w_wall: np.ndarray


def _seen_band(rim, image, cam, theta, shape, width):
    """The band of one shape as one image sees it round the rim (:class:`_SeenBand`).

    At each angle the band is seen from its face's end up to where it turns
    away from the camera (at least two section samples, all projecting);
    the projection, that visibility and the grey levels read beside the
    band depend on the shape alone, so :func:`_image_places` of every
    light tried shares them.
    """
    K, D, R, t, C, _ = cam
    P, N, wf, ww, p0, rh = _sections(rim, theta, shape)
    facing = np.einsum("amk,amk->am", C - P, N) > 0
    uv0, d = _outward(p0, rh, rim.side, K, D, R, t)
    uv_all = project_points(P.reshape(-1, 3), K, D, R, t).reshape(P.shape[0], P.shape[1], 2)
    index, us, reads, observed = [], [], [], []
    for i in range(len(theta)):
        m = int(np.argmin(facing[i])) if not facing[i].all() else P.shape[1]
        if m < 2 or not np.isfinite(uv_all[i, :m]).all():
            continue
        u = (uv_all[i, :m] - uv0[i]) @ d[i]
        out = np.sign(u[0] - u[-1]) * READ_WIDTHS * width
        index.append(i)
        us.append(u)
        reads.append(read_grey(image, uv0[i] + np.array([u[0] + out, u[-1] - out])[:, None] * d[i]))
        observed.append(observed_place(image, uv0[i], d[i], min(u[0], u[-1]) - width, max(u[0], u[-1]) + width))
    return _SeenBand(np.array(index, int), tuple(us), np.reshape(reads, (-1, 2)), np.array(observed, float), wf, ww)


def _image_places(seen, theta, light, width):
    """Per angle, the apparent place across the band, its rival and the image's own, px along the outward direction.

    Parameters
    ----------
    seen : _SeenBand
        The band of one shape in one image.
    theta : ndarray, shape (angles,)
    light : ndarray, shape (4,)
        ``(A, b1, b2, a)`` (:func:`fit_light`).
    width : float
        The image's edge width, px.

    Returns
    -------
    ndarray, shape (3, angles)
        NaN where the band is not seen.
    """
    A, b1, b2, a = light
    B = b1 * np.cos(theta) + b2 * np.sin(theta)
    grey = np.maximum(seen.w_face[None] * A + seen.w_wall[None] * B[:, None], 0.0) + a
    places = np.full((3, len(theta)), np.nan)
    for i, u, (g_face, g_past), observed in zip(seen.index, seen.u, seen.reads, seen.observed):
        places[:2, i] = apparent_place(u, grey[i, :len(u)], g_face, g_past, width)
        places[2, i] = observed
    return places


def observed_place(image, origin, direction, lo, hi, step=0.05):
    """The steepest place of the image's own profile between ``lo`` and ``hi`` px along ``direction``.

    The profile is read at ``step`` px and smoothed by the detector's
    derivative filter (a Gaussian of 1 px): where the detector finds the
    step, read without its chaining, to check the prediction against.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey levels, float.
    origin : ndarray, shape (2,)
        The sharp edge's image point, distorted px.
    direction : ndarray, shape (2,)
        Unit image direction across the edge.
    lo, hi : float
        The window along ``direction``, px from ``origin``.

    Returns
    -------
    float
        px from ``origin`` along ``direction``.
    """
    x = np.arange(lo - 4.0, hi + 4.0, step)
    prof = gaussian_filter1d(read_grey(image, origin + x[:, None] * direction), 1.0 / step, mode="nearest")
    slope = np.abs(np.gradient(prof))
    inside = (x >= lo) & (x <= hi)
    return float(x[inside][np.argmax(slope[inside])])


def _light_samples(rim, images, cams, theta, width):
    """Grey levels of the rim's face just outside the band and of its wall just inside, where seen (both images)."""
    th, g, kind = [], [], []
    for image, cam in zip(images, cams):
        K, D, R, t, C, _ = cam
        p0, rh = _rim_frame(rim.center, rim.axis, rim.radius, theta)
        uv0, d = _outward(p0, rh, rim.side, K, D, R, t)
        out_px = READ_WIDTHS * width + rim.size * float(np.median(np.linalg.norm(
            project_points(p0 + rim.side * rh, K, D, R, t) - uv0, axis=1)))
        face = uv0 + out_px * d
        wall_seen = np.einsum("ak,ak->a", C - (p0 - rim.size * rim.axis), -rim.side * rh) > 0
        wall = uv0 - out_px * d
        ok = np.isfinite(face).all(1)
        th += [theta[ok], theta[ok & wall_seen]]
        g += [read_grey(image, face[ok]), read_grey(image, wall[ok & wall_seen])]
        kind += [np.zeros(ok.sum(), int), np.ones((ok & wall_seen).sum(), int)]
    return np.concatenate(th), np.concatenate(g), np.concatenate(kind)


def _places(seen, theta, light, width):
    """Per image, :func:`_image_places` of the rim's band as each sees it (one shape) under one light."""
    return [_image_places(band, theta, light, w) for band, w in zip(seen, width)]


def _band_px(rim, cam, p0, rh):
    """The break's width in the image at each angle, px."""
    K, D, R, t = cam[:4]
    return rim.size * np.linalg.norm(project_points(p0 + rim.side * rh, K, D, R, t) - project_points(p0, K, D, R, t),
                                     axis=1)


def _sharp_rim(rim, cams, theta, seen):
    """The sharp rim's ideal image at the angles seen, per image, and the radius its two-view fit gives.

    Parameters
    ----------
    seen : tuple of ndarray of bool, shape (angles,)
        Per image, the angles at which the band is seen.

    Returns
    -------
    per_image : list of (ok, uv0, d, sigma, P, band)
        The angles seen; the sharp rim's ideal pixels (k, 2) and unit
        outward directions (k, 2) there; the points' standard deviation,
        px; the camera's rig matrix; the break's median width in the
        image, px.
    c_rig, n_rig : ndarray, shape (3,)
        The rim's centre and axis in the rig frame: the fits' start.
    r_sharp : float
        The sharp rim's fitted radius, mm: the apparent rims' sizes are
        read from it, so the fit's own small error cancels.
    """
    p0, rh = _rim_frame(rim.center, rim.axis, rim.radius, theta)
    per_image = []
    for cam, ok in zip(cams, seen):
        K, D, R, t, _, P = cam
        uv0, d = _outward(p0[ok], rh[ok], rim.side, K, np.zeros(5), R, t)
        per_image.append((ok, uv0, d, np.full(ok.sum(), 0.1), P,
                          float(np.median(_band_px(rim, cam, p0[ok], rh[ok])))))
    K, D, R, t, C, _ = cams[0]
    c_rig, n_rig = R @ rim.center + t, R @ rim.axis
    r_sharp = fit_circle_3d([View(uv0, sigma, P) for _, uv0, _, sigma, P, _ in per_image], c_rig, n_rig,
                            rim.radius).radius
    return per_image, c_rig, n_rig, r_sharp


def _fitted_place(rim, cams, theta, places, sharp, rival=True):
    """The rim's band place from the apparent points of both images through the two-view circle fit.

    The fit takes ideal (undistorted) pixels: the places, read on the
    images as they are, move the ideal image of the sharp rim.

    Parameters
    ----------
    places : list of ndarray, shape (3, angles)
        Per image, :func:`_image_places`.
    sharp : dict
        :func:`_sharp_rim` by the angles seen, filled here: every shape
        and light with the same angles seen shares the sharp rim's fit.
    rival : bool
        Also the rivals' place and the misfit; else the place alone.

    Returns
    -------
    (s, s_rival, misfit), or s where ``rival`` is False, or None
        The place from the steepest steps, from their rivals, and the RMS
        of the predicted less the image's own steepest places round the
        rim, what a rigid move and a size of the rim in both images (the
        pose's error and the size measured) leave, as a share of the band's
        width in the image (RMS over the images).
        None where an image sees fewer than 6 angles.
    """
    seen = tuple(np.isfinite(pl[0]) for pl in places)
    if any(ok.sum() < 6 for ok in seen):
        return None
    key = b"".join(ok.tobytes() for ok in seen)
    if key not in sharp:
        sharp[key] = _sharp_rim(rim, cams, theta, seen)
    per_image, c_rig, n_rig, r_sharp = sharp[key]

    def size(row):
        views = [View(uv0 + pl[row, ok, None] * d, sigma, P) for (ok, uv0, d, sigma, P, _), pl in zip(per_image, places)]
        return rim.side * (fit_circle_3d(views, c_rig, n_rig, rim.radius).radius - r_sharp) / rim.size

    if not rival:
        return size(0)
    # The pose's error moves the rim rigidly (its tilt too) in both images at once, and the size is
    # measured: a two-view circle fit of the image's own steps less the predicted takes out those and
    # leaves what the model does not explain.
    views = [View(uv0 + (pl[2, ok] - pl[0, ok])[:, None] * d, sigma, P)
             for (ok, uv0, d, sigma, P, _), pl in zip(per_image, places)]
    r, _ = circle_residuals_at(views, fit_circle_3d(views, c_rig, n_rig, rim.radius))
    parts = np.split(r, np.cumsum([len(v.xy) for v in views])[:-1])
    misfit = [float(np.sqrt(np.mean(np.square(e * v.sigma)))) / band
              for e, v, (*_, band) in zip(parts, views, per_image)]
    return size(0), size(1), float(np.sqrt(np.mean(np.square(misfit))))


def _point_places(rim, cams, theta, shapes):
    """Per image, the place at each angle midway between the shapes' and rivals' extremes, and its range, px.

    Returns
    -------
    list of (mid, share, range)
        Per image, each shape (angles,): the place, px; its range as a
        share of the break's width in the image; the range, px.
    """
    out = []
    p0, rh = _rim_frame(rim.center, rim.axis, rim.radius, theta)
    for i, cam in enumerate(cams):
        c = np.concatenate([pl[i][:2] for pl in shapes])
        lo, hi = np.min(c, axis=0), np.max(c, axis=0)
        out.append((0.5 * (lo + hi), (hi - lo) / _band_px(rim, cam, p0, rh), hi - lo))
    return out


def _place_modes(ranges, places, moved):
    """Per image, the band place's errors shared round the rim and by both images, px at each angle.

    A rim has one break and is under one light, so what is not known of
    them moves the place at every angle and in both images at once, by
    amounts the model predicts: the rim's fit then takes the part of the
    move common round the rim as its radius and only the part that varies
    round it (the light's direction, the view's obliquity) as its centre.
    Two kinds: the place somewhere across the range the shapes and rival
    steps give (one share of it everywhere, rectangular: the range over
    ``sqrt(12)``, JCGM 100 4.3.7), and the light moved along each principal
    direction of its covariance by one standard deviation (JCGM 100, 5.2).

    Parameters
    ----------
    ranges : sequence of ndarray, shape (angles,)
        Per image, the range of the place, px.
    places : sequence of ndarray, shape (3, angles)
        Per image, :func:`_image_places` under the fitted light.
    moved : sequence of sequence of ndarray, shape (3, angles)
        Per light direction, per image, the same under the moved light.

    Returns
    -------
    tuple of ndarray, shape (1 + directions, angles)
        NaN where the band is not seen.
    """
    return tuple(np.vstack([rng / math.sqrt(12.0)] + [m[i][0] - pl[0] for m in moved])
                 for i, (rng, pl) in enumerate(zip(ranges, places)))


def band_place(images, calib, part_to_camera, center, axis, radius, hole, size, width):
    """The predicted band place of a broken rim's size, or None where it cannot be predicted.

    Parameters
    ----------
    images : (ndarray, ndarray)
        Left and right grey images, shape (H, W).
    calib : StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
        The registered pose (part frame to the left camera).
    center, axis : array_like, shape (3,)
        The rim's centre and its planar face's outward unit normal, part frame, mm.
    radius : float
        The sharp rim's radius, mm.
    hole : bool
        True for a hole's rim, False for a boss's.
    size : float
        The break's size (fillet radius or chamfer leg), mm: its expected value.
    width : (float, float)
        Each image's edge width (``EdgePoints.width``, median), px.

    Returns
    -------
    BandPlace or None
        None where the light cannot be fitted (too few samples) or too
        little of the rim is seen in an image.
    """
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    # Read as float once (each reading would convert the whole image again).
    images = tuple(np.asarray(image, float) for image in images)
    cams = camera_views(calib, part_to_camera)
    rim = _Rim(np.asarray(center, float), axis, float(radius), 1 if hole else -1, float(size))
    theta = np.linspace(0.0, 2.0 * np.pi, ANGLES, endpoint=False)
    T, g, kind = _light_samples(rim, images, cams, theta, float(np.mean(width)))
    if (kind == 0).sum() < 6 or (kind == 1).sum() < 6:
        return None
    light, cov, rms = fit_light(T, g, kind)

    # The bands as seen and the sharp rim's fits depend on the shape alone: once for every light.
    seen = {shape: [_seen_band(rim, image, cam, theta, shape, w) for image, cam, w in zip(images, cams, width)]
            for shape in ("fillet", "chamfer")}
    sharp = {}
    shapes = {shape: _places(seen[shape], theta, light, width) for shape in ("fillet", "chamfer")}
    fillet, chamfer = (_fitted_place(rim, cams, theta, shapes[k], sharp) for k in ("fillet", "chamfer"))
    if fillet is None or chamfer is None:
        return None
    # Shape and rival steps: the place lies anywhere between the extremes they give.
    lo, hi = min(fillet[:2] + chamfer[:2]), max(fillet[:2] + chamfer[:2])
    s_mid, u_shape = 0.5 * (lo + hi), (hi - lo) / math.sqrt(12.0)
    w, V = np.linalg.eigh(cov)
    lights = [_places(seen["fillet"], theta, light + math.sqrt(max(wi, 0.0)) * V[:, j], width)
              for j, wi in enumerate(w)]
    moves = [_fitted_place(rim, cams, theta, m, sharp, rival=False) for m in lights]
    u_light = math.sqrt(sum((m - fillet[0]) ** 2 for m in moves if m is not None))
    # What the model does not explain of the image's own steps round the rim (the better shape's).
    u_model = min(fillet[2], chamfer[2])
    u = min(UNIFORM_STD, math.sqrt(u_shape**2 + u_light**2 + u_model**2))
    s_f, s_c = fillet[0], chamfer[0]
    points = _point_places(rim, cams, theta, list(shapes.values()))
    ranges = np.concatenate([r[np.isfinite(r)] for _, r, _ in points])
    u_point = min(UNIFORM_STD, math.sqrt(float(np.mean(ranges**2)) / 12.0 + u_light**2 + u_model**2))
    modes = _place_modes([r for _, _, r in points], shapes["fillet"], lights)
    return BandPlace(float(np.clip(s_mid, 0.0, 1.0)), u, s_f, s_c, u_shape, u_light, u_model, theta,
                     tuple(p for p, _, _ in points), u_point, modes, min(UNIFORM_STD, u_model))


def _round_rim(theta, values, fine):
    """``values`` (angles,) interpolated round the rim at ``fine``, NaN (not seen) taking the nearest seen; None if < 2 seen."""
    seen = np.isfinite(values)
    if seen.sum() < 2:
        return None
    period = np.r_[theta[seen] - 2 * np.pi, theta[seen], theta[seen] + 2 * np.pi]
    return np.interp(fine, period, np.tile(values[seen], 3))


def _moved_to_sharp(feature, rim, cam, theta, offsets, corr_length, modes=None, names=None):
    """An image arc with each point moved by minus its predicted place (towards the sharp rim's image), refitted.

    Each point takes the place of the nearest of the sharp rim's image
    samples (the 60 predicted angles interpolated round the rim; an angle
    where the band is not seen takes its nearest seen one). The move is
    made in the distorted image and carried to the ideal one by each
    point's Jacobian; covariances are kept (the place's uncertainty is the
    Type B the fit is given). The place's shared errors ``modes`` (k,
    angles), px, are read at each point alike and carried to the ideal
    image by the Jacobian's stretch across the edge: the feature's
    ``band_modes``, named ``names``.
    """
    fine = np.linspace(0.0, 2.0 * np.pi, FINE_ANGLES, endpoint=False)
    offset = _round_rim(theta, offsets, fine)
    if offset is None:
        return None
    p0, rh = _rim_frame(rim.center, rim.axis, rim.radius, fine)
    uv0, d = _outward(p0, rh, rim.side, *cam[:4])
    near = np.argmin(np.linalg.norm(feature.uv[:, None] - uv0[None], axis=2), axis=1)
    shift = -offset[near, None] * d[near]
    xy = feature.ideal.xy + np.einsum("nij,nj->ni", feature.ideal.jacobian, shift)
    ideal = replace(feature.ideal, xy=xy)
    fit = fit_ellipse(xy, ideal.cov, corr_length=corr_length, start=feature.fit.params)
    extra = {}
    if modes is not None:
        stretch = np.linalg.norm(np.einsum("nij,nj->ni", feature.ideal.jacobian, d[near]), axis=1)
        rows = [_round_rim(theta, m, fine) for m in modes]
        rows = [np.zeros(len(fine)) if r is None else r for r in rows]
        extra = {"band_modes": np.array([r[near] * stretch for r in rows]), "band_mode_names": tuple(names)}
    return replace(feature, uv=feature.uv + shift, ideal=ideal, fit=fit, **extra)


def rims_at_sharp_edge(stereo, calib, part_to_camera, arcs, places):
    """Broken rims refitted with their points moved onto the sharp rim's image by their predicted places.

    The rim's two-view fit then measures the sharp rim, whose size is the
    wall's, and the rim carries, in place of the whole band, the
    prediction's own uncertainty: ``u_point`` of the break's expected
    size, as the size of :func:`partinspect.vision.band_modes.edge_band`
    (round the rim, the modes of its mean and longest waves,
    :func:`~partinspect.vision.band_modes.band_harmonics`). A
    rim whose place is predicted no better than uniform across the band
    (``u`` or ``u_point`` at ``1 / sqrt(12)``: the model does not explain
    the image's own steps there) is left as it was: its points, moved by
    places the images contradict, would bend it out of round.

    Parameters
    ----------
    stereo : StereoResult
    calib : StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
        The registered pose.
    arcs : dict of int to str
        Index into ``stereo.features`` of a measured circle -> its CAD edge.
    places : dict of str to (BandPlace, tuple)
        CAD edge -> its predicted place and its rim ``(center, axis,
        radius, hole, size)`` as :func:`band_place` takes them.

    Returns
    -------
    stereo : StereoResult
        Those rims refitted (their image features too), each with its
        ``band_place``; a rim whose refit fails stays as it was.
    refitted : set of str
    """
    L, R = stereo.left, stereo.right
    cams = camera_views(calib, part_to_camera)
    refits, refitted = {}, set()
    for k, cid in arcs.items():
        if cid not in places or places[cid][0].offsets is None:
            continue
        place, (center, axis, radius, hole, size) = places[cid]
        if max(place.u, place.u_point) >= UNIFORM_STD:
            continue  # no better than anywhere across the band: moving the points would only bend the rim
        axis = np.asarray(axis, float) / np.linalg.norm(axis)
        rim = _Rim(np.asarray(center, float), axis, float(radius), 1 if hole else -1, float(size))
        f3 = stereo.features[k]
        scale = L.features[f3.left].corr_length or float(L.edges.sigma)
        modes = place.modes or (None, None)
        names = None if place.modes is None else [f"{cid} band place {j}" for j in range(len(place.modes[0]))]
        try:
            moved = [_moved_to_sharp(res.features[i], rim, cam, place.theta, off, scale, m, names)
                     for res, i, cam, off, m in zip((L, R), (f3.left, f3.right), cams, place.offsets, modes)]
        except (np.linalg.LinAlgError, ValueError):
            continue
        if any(m is None for m in moved):
            continue
        rest = place.u_point if place.modes is None else place.u_rest
        new = refit_pair(stereo, calib, k, moved, scale, rest * rim.size, band_place=place)
        if new is None:
            continue
        refits[k] = (*moved, new)
        refitted.add(cid)
    return with_refitted(stereo, refits), refitted
