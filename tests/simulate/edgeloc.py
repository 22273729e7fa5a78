"""Measure where a rendered image puts a CAD edge, independently of the renderer.

Used by the sub-pixel accuracy test: for points along a projected CAD edge,
take the image profile along the projected edge normal (cubic B-spline
interpolation of the 8-bit image) and locate the edge in it by fitting the
model of a blurred step with linear shading on either side,

    I(s) = a + b u + c Phi(u / sigma) + d (u Phi(u / sigma) + sigma phi(u / sigma)),
    u = s - s0,

which is exactly a piecewise-linear radiance (one slope on each side, a
jump at s0) convolved with a Gaussian of standard deviation sigma. For
fixed s0 the model is linear in (a, b, c, d); s0 is found on a 0.05 px grid
and refined by a parabola through the residuals. The linear terms matter on
hole walls, whose grey changes across the profile: a derivative-of-Gaussian
peak there is pulled by several hundredths of a pixel.

Only clean points are used: visible with contrast in the truth sense,
away from the edge's ends, and with exactly one change of CAD face within
+-5 px across and +-2 px along the edge (checked by ray casting), so the
step model holds.
"""

import numpy as np
from scipy import ndimage
from scipy.special import ndtr

from partinspect.cad.raycast import camera_in_part, cast, pixel_rays
from partinspect.cad.sightlines import edge_visibility
from partinspect.cad.edge_sampling import feature_geometry, sample_edge

STEP = 0.05  # px between profile samples
HALF = 3.0  # px: profile half length used in the fit
SEARCH = 1.0  # px: the edge is looked for within this of the projected edge
END_MARGIN = 5.0  # px kept clear of a line's or arc's ends
ACROSS = 5.0  # px of one face each side required across the edge
ALONG = 2.0  # px along the edge over which that is required


def fit_step(profiles, s, sigma):
    """Sub-pixel position of a blurred step in each profile.

    Parameters
    ----------
    profiles : ndarray, shape (N, M)
    s : ndarray, shape (M,)
        Sample positions, px.
    sigma : float
        Total blur of the step, px.

    Returns
    -------
    ndarray, shape (N,)
        Step positions, px.
    """
    grid = np.arange(-SEARCH, SEARCH + STEP / 2, STEP)
    sse = np.empty((len(profiles), len(grid)))
    for k, s0 in enumerate(grid):
        u = s - s0
        z = u / sigma
        pdf = np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)
        A = np.stack([np.ones_like(u), u, ndtr(z), u * ndtr(z) + sigma * pdf], axis=1)
        r = profiles.T - A @ (np.linalg.pinv(A) @ profiles.T)
        sse[:, k] = (r * r).sum(axis=0)
    j = np.clip(sse.argmin(axis=1), 1, len(grid) - 2)
    i = np.arange(len(j))
    a, b, c = sse[i, j - 1], sse[i, j], sse[i, j + 1]
    den = a - 2 * b + c
    return grid[j] + STEP * 0.5 * (a - c) / np.where(den > 0, den, np.inf)


def _clean(rs, K, D, R, t, uv, normal):
    """Points whose surroundings hold exactly one change of face, at the edge."""
    across = np.concatenate([np.arange(-ACROSS, -0.99, 0.25), np.arange(-0.9, 0.0, 0.1)])
    across = np.concatenate([across, -across[::-1]])
    along = np.arange(-ALONG, ALONG + 0.01, 1.0)
    tangent = np.stack([normal[:, 1], -normal[:, 0]], axis=1)
    q = (
        uv[:, None, None, :]
        + along[None, :, None, None] * tangent[:, None, None, :]
        + across[None, None, :, None] * normal[:, None, None, :]
    )
    o, d = pixel_rays(q.reshape(-1, 2), K, D, R, t)
    lab = cast(rs, o, d).label.reshape(len(uv), len(along), len(across))
    half = len(across) // 2
    neg, pos = lab[..., :half], lab[..., half:]
    a, b = neg[:, :1, :1], pos[:, :1, -1:]
    return (neg == a).all(axis=(1, 2)) & (pos == b).all(axis=(1, 2)) & (a[:, 0, 0] != b[:, 0, 0])


def edge_offsets(image, rs, calib, index, part_to_camera, inv, blur_sigma):
    """Signed distances (px) from projected CAD edges to the image's edges.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        A rendered image of camera ``index``.
    rs : RaycastScene
        The part as rendered.
    calib : StereoCalibration
    index : int
    part_to_camera : ndarray (4, 4)
    inv : Inventory
        Its features are the edges to check (their nominal geometry).
    blur_sigma : float
        The optics blur of the render; with the pixel's box it sets the
        step width of the model.

    Returns
    -------
    dict of str to ndarray
        Feature id to the signed offsets (px, along the projected edge's
        normal) of its clean sample points; features without any are left
        out.
    """
    K, D, R, t = camera_in_part(calib, index, part_to_camera)
    coef = ndimage.spline_filter(np.asarray(image, float), order=3)
    sigma = np.sqrt(blur_sigma**2 + 1.0 / 12.0)
    s = np.arange(-HALF, HALF + STEP / 2, STEP)
    out = {}
    for f in inv.features:
        pts, tan = sample_edge(f.kind, feature_geometry(f))
        v = edge_visibility(rs, calib, index, part_to_camera, pts, tan)
        ok = v["in_image"] & v["unoccluded"] & v["contrast"]
        if f.kind != "circle":
            arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(v["uv"], axis=0), axis=1))]
            ok &= (arc > END_MARGIN) & (arc < arc[-1] - END_MARGIN)
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            continue
        uv, normal = v["uv"][idx], v["normal_uv"][idx]
        keep = _clean(rs, K, D, R, t, uv, normal)
        uv, normal = uv[keep], normal[keep]
        if len(uv) == 0:
            continue
        pp = uv[:, None, :] + s[None, :, None] * normal[:, None, :]
        prof = ndimage.map_coordinates(coef, [pp[..., 1].ravel(), pp[..., 0].ravel()], order=3, prefilter=False)
        out[f.id] = fit_step(prof.reshape(len(uv), -1), s, sigma)
    return out
