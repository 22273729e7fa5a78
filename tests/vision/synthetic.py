"""Synthetic grey images with exact analytic truth, for the 2D vision tests.

The image forms as in a camera: the optics blur the scene with a Gaussian
point-spread function (PSF) of standard deviation ``blur`` px, each pixel
integrates the blurred irradiance over its square, Gaussian noise is added
and the result is quantised to 8 bits. A shape's blurred indicator is
computed exactly where a closed form exists (a half-plane: the normal CDF of
its signed distance; a disc: the non-central chi-square CDF; a rectangle: a
product of two normal-CDF differences in its own frame) and from the
osculating circle or the nearest side elsewhere (an ellipse; a polygon's or
a slot's corners); the pixel's square is integrated by 6 x 6-point
Gauss-Legendre quadrature (error below 1e-7 for blur >= 0.4 px). Shapes are
painted in order, each over what lies below it, which is exact while their
outlines stay a few blur widths apart. With ``blur = 0`` the pixels are
area-integrated exactly (a straight side crossing a pixel: the exact area of
a half-plane; curves and polygon vertices: supersampled ``ss`` x ``ss``).
Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0),
x to the right, y down.

A shape is a small object with ``sdist(x, y)`` -- a lower bound on the true
distance to the boundary outside, exact or conservative inside (negative) --
and ``inside(x, y)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from partinspect.vision.contours import chain_edges
from partinspect.vision.edges import edge_points
from partinspect.vision.fitting import ellipse_kcr_bound, fit_ellipse, fit_line, line_kcr_bound

__all__ = ["Disc", "Ellipse", "Polygon", "HalfPlane", "Slot", "rectangle", "render", "render_clean", "render_optics",
           "render_profile", "line_draws", "ellipse_draws"]


@dataclass(frozen=True)
class HalfPlane:
    """The set ``A x + B y + C < 0`` with ``A^2 + B^2 = 1``."""

    A: float
    B: float
    C: float

    def sdist(self, x, y):
        return self.A * x + self.B * y + self.C

    def inside(self, x, y):
        return self.sdist(x, y) < 0

    def coverage(self, rows, cols, ss):
        return _halfplane_area(self.A, self.B, self.sdist(cols, rows))

    def blurred(self, x, y, blur):
        return ndtr(-self.sdist(x, y) / blur)

    def distance(self, xy):
        """Signed distance of points (N, 2) to the boundary line, px."""
        xy = np.asarray(xy, float)
        return self.A * xy[:, 0] + self.B * xy[:, 1] + self.C


@dataclass(frozen=True)
class Polygon:
    """Convex polygon, vertices (K, 2) in counter-clockwise or clockwise order."""

    vertices: tuple

    def _planes(self):
        v = np.asarray(self.vertices, float)
        c = v.mean(axis=0)
        planes = []
        for p, q in zip(v, np.roll(v, -1, axis=0)):
            d = q - p
            n = np.array([d[1], -d[0]]) / np.hypot(*d)
            C = -n @ p
            if n @ c + C > 0:  # orient so the interior is negative
                n, C = -n, -C
            planes.append((n[0], n[1], C))
        return planes

    def sdist(self, x, y):
        return np.max([A * x + B * y + C for A, B, C in self._planes()], axis=0)

    def inside(self, x, y):
        return self.sdist(x, y) < 0

    def coverage(self, rows, cols, ss):
        # One side crossing the pixel: exact area; a vertex in it: supersampled.
        planes = self._planes()
        d = np.array([A * cols + B * rows + C for A, B, C in planes])
        near = np.abs(d) < 0.75
        cov = np.ones(len(rows))
        for k, (A, B, C) in enumerate(planes):
            cov *= np.where(near[k], _halfplane_area(A, B, d[k]), (d[k] < 0).astype(float))
        many = near.sum(axis=0) > 1
        if many.any():
            cov[many] = _supersample(self, rows[many], cols[many], max(ss, 64))
        return cov

    def blurred(self, x, y, blur):
        # Exact for a rectangle (perpendicular sides: the Gaussian factorises
        # in its frame), and for any convex polygon away from its vertices.
        out = 1.0
        for A, B, C in self._planes():
            out = out * ndtr(-(A * x + B * y + C) / blur)
        return out

    def distance(self, xy):
        """Exact signed distance of points (N, 2) to the polygon outline, px."""
        xy = np.asarray(xy, float)
        v = np.asarray(self.vertices, float)
        best = np.full(len(xy), np.inf)
        for p, q in zip(v, np.roll(v, -1, axis=0)):
            d = q - p
            t = np.clip(((xy - p) @ d) / (d @ d), 0, 1)
            best = np.minimum(best, np.hypot(*(xy - p - t[:, None] * d).T))
        return np.where(self.inside(xy[:, 0], xy[:, 1]), -best, best)


def rectangle(cx, cy, w, h, angle=0.0):
    """Polygon of a w x h rectangle centred at (cx, cy), rotated by angle (rad)."""
    c, s = np.cos(angle), np.sin(angle)
    corners = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
    R = np.array([[c, -s], [s, c]])
    return Polygon(tuple(map(tuple, corners @ R.T + [cx, cy])))


@dataclass(frozen=True)
class Ellipse:
    """Ellipse with centre (xc, yc), semi-axes a, b and angle theta (rad) of the a axis."""

    xc: float
    yc: float
    a: float
    b: float
    theta: float = 0.0

    def _local(self, x, y):
        c, s = np.cos(self.theta), np.sin(self.theta)
        dx, dy = x - self.xc, y - self.yc
        return c * dx + s * dy, -s * dx + c * dy

    def sdist(self, x, y):
        # (rho - 1) min(a, b) bounds the distance from below outside and inside,
        # because rho*E = E + (rho-1)E contains E plus a disc of radius (rho-1)b.
        u, v = self._local(x, y)
        rho = np.sqrt((u / self.a) ** 2 + (v / self.b) ** 2)
        return (rho - 1.0) * min(self.a, self.b)

    def inside(self, x, y):
        u, v = self._local(x, y)
        return (u / self.a) ** 2 + (v / self.b) ** 2 < 1.0

    def blurred(self, x, y, blur):
        # The disc of the osculating circle at the nearest outline point:
        # exact for a circle, off by the change of curvature elsewhere.
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        d, kappa = self._distance_curvature(x.ravel(), y.ravel())
        r = 1.0 / kappa
        return _disc_blurred(r + d, r, blur).reshape(x.shape)

    def distance(self, xy):
        """Signed orthogonal distance of points (N, 2) to the ellipse, px (Newton on the phase)."""
        xy = np.asarray(xy, float)
        return self._distance_curvature(xy[:, 0], xy[:, 1])[0]

    def _distance_curvature(self, x, y):
        """Signed distance to the outline and its curvature at the nearest point."""
        u, v = self._local(x, y)
        a, b = self.a, self.b
        phi = np.arctan2(v * a, u * b)
        for _ in range(30):
            ex, ey = a * np.cos(phi), b * np.sin(phi)
            dx, dy = -a * np.sin(phi), b * np.cos(phi)
            f = (u - ex) * dx + (v - ey) * dy
            fp = -(dx * dx + dy * dy) + (u - ex) * (-ex) + (v - ey) * (-ey)
            phi = phi - f / fp
        ex, ey = a * np.cos(phi), b * np.sin(phi)
        d = np.hypot(u - ex, v - ey)
        sp, cp = np.sin(phi), np.cos(phi)
        kappa = a * b / (a * a * sp * sp + b * b * cp * cp) ** 1.5
        return np.where((u / a) ** 2 + (v / b) ** 2 < 1, -d, d), kappa


@dataclass(frozen=True)
class Slot:
    """Points within ``r`` of the segment from (x0, y0) to (x1, y1): two
    straight sides, each tangent to the two half-circle ends."""

    x0: float
    y0: float
    x1: float
    y1: float
    r: float

    def sdist(self, x, y):
        d = np.array([self.x1 - self.x0, self.y1 - self.y0])
        t = np.clip(((x - self.x0) * d[0] + (y - self.y0) * d[1]) / (d @ d), 0.0, 1.0)
        return np.hypot(x - self.x0 - t * d[0], y - self.y0 - t * d[1]) - self.r

    def inside(self, x, y):
        return self.sdist(x, y) < 0

    def blurred(self, x, y, blur):
        # Beside the segment: exact (two parallel sides); beyond its ends:
        # the end's disc; approximate only where the two meet.
        d = np.array([self.x1 - self.x0, self.y1 - self.y0])
        L = np.hypot(*d)
        along = ((x - self.x0) * d[0] + (y - self.y0) * d[1]) / L
        across = (-(x - self.x0) * d[1] + (y - self.y0) * d[0]) / L
        side = ndtr((self.r - across) / blur) - ndtr((-self.r - across) / blur)
        rho = np.hypot(np.clip(along, 0.0, L) - along, across)
        end = _disc_blurred(rho, self.r, blur)
        return np.where((along >= 0) & (along <= L), side, end)


def _disc_blurred(rho, r, blur):
    """Disc of radius r blurred by an isotropic Gaussian, at distance rho from its centre.

    The probability that a 2-D normal of std ``blur`` centred at distance rho
    falls within r: a non-central chi-square CDF with 2 degrees of freedom.
    """
    from scipy.stats import ncx2

    rho, r = np.broadcast_arrays(np.asarray(rho, float), np.asarray(r, float))
    out = np.empty(rho.shape)
    # Far from the outline the answer is 0 or 1 to double precision.
    far = np.abs(rho - r) > 12.0 * blur
    out[far] = (rho[far] < r[far]).astype(float)
    near = ~far
    out[near] = ncx2.cdf((r[near] / blur) ** 2, 2, (rho[near] / blur) ** 2)
    return out


def Disc(xc, yc, r):
    """A disc is an ellipse with a = b."""
    return Ellipse(xc, yc, r, r, 0.0)


def _halfplane_area(A, B, c):
    """Exact area of {(u, v) in [-1/2, 1/2]^2 : A u + B v + c < 0}, A^2 + B^2 = 1.

    The CDF of A U + B V for independent uniform U, V (a trapezoidal
    density), evaluated at -c.
    """
    p = np.maximum(abs(A), abs(B)) / 2.0
    q = np.minimum(abs(A), abs(B)) / 2.0
    t = -np.asarray(c, float)
    out = np.where(t >= p + q, 1.0, 0.0)
    mid = (t > -p + q) & (t < p - q)
    out = np.where(mid, (t + p) / (2 * p), out)
    if q > 1e-12:
        lo = (t > -p - q) & (t <= -p + q)
        hi = (t >= p - q) & (t < p + q)
        out = np.where(lo, (t + p + q) ** 2 / (8 * p * q), out)
        out = np.where(hi, 1.0 - (p + q - t) ** 2 / (8 * p * q), out)
    return out


def _supersample(shape, rows, cols, ss):
    off = (np.arange(ss) + 0.5) / ss - 0.5
    oy, ox = np.meshgrid(off, off, indexing="ij")
    out = np.empty(len(rows))
    for s in range(0, len(rows), 256):  # bounded memory
        sx = cols[s:s + 256, None] + ox.ravel()[None, :]
        sy = rows[s:s + 256, None] + oy.ravel()[None, :]
        out[s:s + 256] = shape.inside(sx, sy).mean(axis=1)
    return out


def _coverage(shape, height, width, ss):
    """Area fraction (H, W) of each pixel covered by the shape."""
    y, x = np.mgrid[0:height, 0:width].astype(float)
    sd = shape.sdist(x, y)
    cov = (sd < 0).astype(float)
    band = np.abs(sd) < 0.75  # half the pixel diagonal is 0.707
    rows, cols = np.nonzero(band)
    if len(rows):
        if hasattr(shape, "coverage"):
            cov[rows, cols] = shape.coverage(rows.astype(float), cols.astype(float), ss)
        else:
            cov[rows, cols] = _supersample(shape, rows.astype(float), cols.astype(float), ss)
    return cov


def render_clean(shapes, height, width, background=40.0, ss=64):
    """Noise-free, unblurred area-integrated image.

    Parameters
    ----------
    shapes : list of (shape, value)
        Painted in order; each covers what lies below it.
    """
    img = np.full((height, width), float(background))
    for shape, value in shapes:
        c = _coverage(shape, height, width, ss)
        img = img * (1.0 - c) + value * c
    return img


_GL_U, _GL_W = (v / 2.0 for v in np.polynomial.legendre.leggauss(6))


def _pixel_mean(shape, rows, cols, blur):
    """Mean of the shape's blurred indicator over the pixels (rows, cols)."""
    out = np.zeros(len(rows))
    for du, wu in zip(_GL_U, _GL_W):
        for dv, wv in zip(_GL_U, _GL_W):
            out += wu * wv * shape.blurred(cols + du, rows + dv, blur)
    return out


def render_optics(shapes, height, width, background=40.0, blur=0.6, ss=64):
    """Noise-free image: the scene blurred by the PSF, then integrated over each pixel.

    Parameters
    ----------
    shapes : list of (shape, value)
        Painted in order; each covers what lies below it.
    blur : float
        Standard deviation of the Gaussian PSF, px; 0 gives :func:`render_clean`.

    Returns
    -------
    ndarray of float64, shape (H, W)
    """
    if blur <= 0:
        return render_clean(shapes, height, width, background, ss)
    y, x = np.mgrid[0:height, 0:width].astype(float)
    img = np.full((height, width), float(background))
    for shape, value in shapes:
        sd = shape.sdist(x, y)
        c = (sd < 0).astype(float)
        # Beyond 0.75 px (half the pixel diagonal, rounded up) plus 9 blur
        # widths the blurred indicator is 0 or 1 to 1e-19.
        rows, cols = np.nonzero(np.abs(sd) < 0.75 + 9.0 * blur)
        c[rows, cols] = _pixel_mean(shape, rows.astype(float), cols.astype(float), blur)
        img = img * (1.0 - c) + value * c
    return img


def render(shapes, height, width, background=40.0, blur=0.6, noise=2.0, seed=0, ss=64,
           quantise=True, clean=None):
    """Blurred, area-integrated, noisy, 8-bit image of the shapes.

    Parameters
    ----------
    clean : ndarray, optional
        The noise-free image (:func:`render_optics`) when already computed;
        ``shapes``, ``background``, ``blur`` and ``ss`` are then ignored.

    Returns
    -------
    img : ndarray, shape (H, W), uint8 (float64 if ``quantise`` is False)
    """
    img = render_optics(shapes, height, width, background, blur, ss) if clean is None else clean.copy()
    rng = np.random.default_rng(seed)
    img = img + rng.normal(0.0, noise, img.shape)
    if quantise:
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return img


# ------------------------------------------------ repeated-draw experiments
# Shared by tests/vision/test_fitting.py (few draws) and
# benchmarks/bench_fitting.py (many draws).

LINE = HalfPlane(np.cos(0.3), np.sin(0.3), -(np.cos(0.3) * 70.3 + np.sin(0.3) * 60.2))
ELLIPSE = Ellipse(100.3, 95.7, 62.0, 38.0, 0.4)


def line_draws(n_draws, noise=2.0, contrast=80.0, seed0=0):
    """Fit errors of (alpha, C), predicted std, and the KCR bounds."""
    H, W = 120, 140
    clean = render_optics([(LINE, 60 + contrast)], H, W, 60.0, 0.6)
    a0, c0 = np.arctan2(LINE.B, LINE.A), LINE.C
    errs, preds, point_err, resid_mean = [], [], [], []
    for k in range(n_draws):
        ep = edge_points(render([], H, W, blur=0, noise=noise, seed=seed0 + k, clean=clean), 1.0)
        ok = (ep.xy[:, 1] > 12) & (ep.xy[:, 1] < H - 12) & (ep.xy[:, 0] > 12) & (ep.xy[:, 0] < W - 12)
        xy, cov = ep.xy[ok], ep.cov[ok]
        xy, cov = xy[np.argsort(xy[:, 1])], cov[np.argsort(xy[:, 1])]
        f = fit_line(xy, cov, corr_length=ep.sigma)
        A, B, C = f.params
        if A * LINE.A + B * LINE.B < 0:
            A, B, C = -A, -B, -C
        errs.append([np.arctan2(B, A) - a0, C - c0])
        preds.append(np.sqrt(np.diag(f.cov_angle_offset)))
        point_err.append(LINE.distance(xy))
        resid_mean.append(f.residuals.mean())
    d = np.concatenate(point_err)
    s_emp = d.std()
    xy_true = xy - LINE.distance(xy)[:, None] * np.array([LINE.A, LINE.B])
    n = np.array([LINE.A, LINE.B])
    kcr_ind = np.sqrt(np.diag(line_kcr_bound(xy_true, n, s_emp)))
    kcr_cor = np.sqrt(np.diag(line_kcr_bound(xy_true, n, s_emp, corr_length=1.0)))
    return np.array(errs), np.array(preds), kcr_ind, kcr_cor, np.array(resid_mean), s_emp


def ellipse_draws(n_draws, noise=2.0, contrast=80.0, seed0=0):
    """Fit errors of (xc, yc, a, b, theta), predicted std, and the KCR bounds."""
    H, W = 200, 200
    E = ELLIPSE
    clean = render_optics([(E, 60 + contrast)], H, W, 60.0, 0.6)
    truth = np.array([E.xc, E.yc, E.a, E.b, E.theta])
    errs, preds, point_err, resid_mean, conv = [], [], [], [], []
    for k in range(n_draws):
        ep = edge_points(render([], H, W, blur=0, noise=noise, seed=seed0 + k, clean=clean), 1.0)
        c = chain_edges(ep)[0]
        xy, cov = ep.xy[c.index], ep.cov[c.index]
        f = fit_ellipse(xy, cov, corr_length=ep.sigma, blur=float(np.median(ep.width[c.index])))
        e = f.params - truth
        e[4] = (e[4] + np.pi / 2) % np.pi - np.pi / 2
        errs.append(e)
        preds.append(np.sqrt(np.diag(f.cov)))
        point_err.append(E.distance(xy))
        resid_mean.append(f.residuals.mean())
        conv.append(f.converged)
    d = np.concatenate(point_err)
    s_emp = d.std()  # spread of the point errors (their mean is the smoothing bias)
    kcr_ind = np.sqrt(np.diag(ellipse_kcr_bound(truth, xy, s_emp)))
    kcr_cor = np.sqrt(np.diag(ellipse_kcr_bound(truth, xy, s_emp, corr_length=1.0)))
    return np.array(errs), np.array(preds), kcr_ind, kcr_cor, np.array(resid_mean), s_emp, np.all(conv)


def toed_in_rig(size, f=4000.0, baseline=60.0, distance=300.0):
    """A distortion-free stereo rig: the right camera ``baseline`` mm along x, both aimed at (0, 0, ``distance``) mm."""
    from partinspect.vision.calibration import StereoCalibration

    K = np.array([[f, 0, size[0] / 2 - 0.5], [0, f, size[1] / 2 - 0.5], [0, 0, 1.0]])
    C = np.array([baseline, 0.0, 0.0])
    z = np.array([0.0, 0.0, distance]) - C
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return StereoCalibration(size, K, np.zeros(5), K.copy(), np.zeros(5), R, -R @ C)


def render_profile(profile, point, normal, size, blur=0.6, ss=6):
    """Noiseless image of a straight edge whose grey across it is ``profile``: shading beside an edge.

    The scene's grey at signed distance ``u`` (px) from the line through
    ``point`` is ``profile(u)`` (``u`` grows along ``normal``, dark to
    bright for a step), supersampled ``ss`` x ``ss`` per pixel, blurred by
    the Gaussian PSF and area-integrated over each pixel (to the
    supersampling's accuracy; shapes of uniform grey have exact renders
    above).

    Parameters
    ----------
    profile : callable
        ndarray of u, px -> grey levels.
    point, normal : array_like, shape (2,)
        A point of the line, px (OpenCV frame), and its unit normal.
    size : (int, int)
        (width, height) of the image.

    Returns
    -------
    ndarray, shape (height, width), float64
    """
    from scipy.ndimage import gaussian_filter

    W, H = size
    ys, xs = np.mgrid[0 : H * ss, 0 : W * ss]
    u = ((xs + 0.5) / ss - 0.5 - point[0]) * normal[0] + ((ys + 0.5) / ss - 0.5 - point[1]) * normal[1]
    return gaussian_filter(profile(u), blur * ss).reshape(H, ss, W, ss).mean(axis=(1, 3))
