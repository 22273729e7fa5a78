"""Form deviation (straightness, circularity) from measured edge points, corrected for noise.

The form value is the width of the zone the points span about a
least-squares reference line or circle. Noise widens that zone: the
peak-to-valley of N noisy points is biased upward by about
``2 sqrt(2 ln N) sigma``, as large as a fine tolerance, so an uncorrected
value would fail good parts on noise alone.

Method (JCGM 101-style Monte Carlo of the noise-only case): fit the
reference and take the raw zone ``F_raw``; simulate noise-only point sets
on the fitted reference with errors drawn as the measurement makes them
(``errors``: correlated along the edge, with the Type B displacements; by
default independent per point; ``shared``: the calibration's, common to
the edge), evaluated the same way; report
``F = F_raw - b`` with ``u = s``, their mean and standard deviation. ``F``
is left unclipped so that it stays unbiased (it may be slightly negative);
where the true form is large against the noise it is low by at most ``b``
(``noise_bias``). Points far less certain than the rest (``MAX_SD_RATIO``)
are left out of the zone, chosen by the error model alone.

Straightness is the diameter of a cylinder about the reference line (ISO
1101, 3D straightness); circularity the radial width of two concentric
circles in the fitted circle's plane (roundness). The least-squares zone is
never narrower than the minimum zone, so the raw value bounds the ISO 1101
default from above. Units: mm; any frame (form does not depend on the pose).

References
----------
.. [1] ISO 1101:2017, 18.1 (straightness), 18.4 (roundness).
.. [2] ISO 12780-1:2011, ISO 12181-1:2011 (reference lines and circles).
.. [3] JCGM 101:2008, propagation of distributions by Monte Carlo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FormResult", "FormSimulationError", "straightness", "circularity", "scene_spreads", "fit_line_points", "fit_circle_points"]

N_DRAWS = 200

N_PATTERNS = 200
"""Scenes drawn for a spread over the images of one scene (``held``), each
seen in ``HELD_IMAGES`` images. That spread varies from scene to scene (a
fixed pattern decides which points set the zone), so its RMS needs many
scenes to be stable to a few per cent; only the planner's noise-only
prediction asks for it, so the time is affordable."""

HELD_IMAGES = 5

N_SCENES = 400
"""Scenes :func:`scene_spreads` draws by default: enough that the 2.5 % and
97.5 % quantiles of their spreads move by a few per cent between seeds."""

SCENE_BATCH = 20
"""Scenes simulated at once (bounds the memory of long checks)."""

MAX_SD_RATIO = 2.5
"""Points whose standard uncertainty across the reference exceeds this many
times the median point's are left out of the zone. A zone is a maximum
minus a minimum, so it cannot weight its points as a fit does: a few points
several times noisier than the rest (where the epipolar line runs along
the edge, or the shading's Type B rest is large, as at the tips of an
oblique hole) would set it alone. 2.5 cuts such tips and keeps most of a
rim; a lower ratio cuts into sound points. Lines, whose points are alike,
keep all. The cut depends on the error model, not on the residuals, so the
value stays unbiased for the points kept; the uncertainty is taken exactly
from the simulated errors' covariances, since estimated from draws it would
change with the seed which points next to the cut are kept."""


@dataclass(frozen=True)
class FormResult:
    """A noise-corrected form value, mm.

    Attributes
    ----------
    value : float
        ``raw - noise_bias``.
    u : float
        Standard uncertainty (spread of the noise-only value).
    raw : float
        Zone width of the measured points about their LS reference.
    noise_bias : float
        Expected zone width of noise alone.
    n_points : int
        Points the zone was evaluated on.
    n_excluded : int
        Points left out as too uncertain (see ``MAX_SD_RATIO``).
    """

    value: float
    u: float
    raw: float
    noise_bias: float
    n_points: int
    n_excluded: int = 0


def fit_line_points(P):
    """Least-squares (orthogonal) line: (centroid (3,), unit direction (3,))."""
    c = P.mean(0)
    _, _, Vt = np.linalg.svd(P - c, full_matrices=False)
    return c, Vt[0]


def _line_zone(P):
    c, d = fit_line_points(P)
    v = P - c
    r = v - np.outer(v @ d, d)
    return 2.0 * float(np.sqrt((r * r).sum(1).max()))


def fit_circle_points(P):
    """Least-squares circle in 3D: plane by SVD, circle in the plane (Kasa, then geometric Gauss-Newton).

    Returns
    -------
    center (3,), normal (3,), radius, in-plane basis (3, 2)
    """
    c0 = P.mean(0)
    _, _, Vt = np.linalg.svd(P - c0, full_matrices=False)
    E = Vt[:2].T
    xy = (P - c0) @ E
    A = np.c_[2 * xy, np.ones(len(xy))]
    sol = np.linalg.lstsq(A, (xy * xy).sum(1), rcond=None)[0]
    a, b = sol[:2]
    r = np.sqrt(sol[2] + a * a + b * b)
    for _ in range(3):
        dx, dy = xy[:, 0] - a, xy[:, 1] - b
        rho = np.hypot(dx, dy)
        J = np.c_[-dx / rho, -dy / rho, -np.ones(len(rho))]
        step = np.linalg.lstsq(J, -(rho - r), rcond=None)[0]
        a, b, r = a + step[0], b + step[1], r + step[2]
    return c0 + E @ np.array([a, b]), Vt[2], float(r), E


def _circle_zone(P):
    c, _, _, E = fit_circle_points(P)
    rho = np.linalg.norm((P - c) @ E, axis=1)
    return float(rho.max() - rho.min())


class FormSimulationError(ValueError):
    """A form value's noise-only zone could not be simulated; the message says why."""


def _enough(w, need):
    """Raise :class:`FormSimulationError` if a draw keeps fewer than ``need`` points.

    The measurement's own fits would refuse so few points: such a draw
    has no zone, and a simulation that lost draws would misstate the spread.
    """
    few = int((w.sum(1) < need).sum())
    if few:
        raise FormSimulationError(f"in {few} of {len(w)} simulated draws the outlier test left fewer than "
                                  f"{need} points")


def _line_zones(Ps, w=None):
    """``_line_zone`` of a stack of point sets (D, M, 3) at once: (D,).

    ``w``: boolean (D, M), the points each set keeps (default all); the
    others take no part in its line or its zone.
    """
    if w is None:
        w = np.ones(Ps.shape[:2], bool)
    _enough(w, 3)
    wf = w.astype(float)
    v = Ps - _weighted_sums(wf, Ps)[:, None] / wf.sum(1)[:, None, None]
    _, V = np.linalg.eigh(_weighted_grams(wf, v, v))
    d = V[:, :, -1]  # the largest principal axis: the orthogonal LS line
    r = v - (v @ d[:, :, None]) * d[:, None, :]
    return 2.0 * np.sqrt(np.where(w, (r * r).sum(2), 0.0).max(1))


def _weighted_sums(wf, X):
    """``sum_m wf[d, m] X[d, m, :]`` for a stack (D, M, k): (D, k).

    As batched matrix products (BLAS), not three-operand einsums, which run
    many times slower on the simulations' (200, hundreds, 3) stacks.
    """
    return np.matmul(wf[:, None, :], X)[:, 0]


def _weighted_grams(wf, X, Y):
    """``sum_m wf[d, m] X[d, m, :]^T Y[d, m, :]`` for stacks (D, M, k), (D, M, l): (D, k, l)."""
    return np.matmul((X * wf[..., None]).swapaxes(1, 2), Y)


def _circle_zones(Ps, w=None):
    """``_circle_zone`` of a stack of point sets (D, M, 3) at once: (D,); ``w`` as in :func:`_line_zones`."""
    if w is None:
        w = np.ones(Ps.shape[:2], bool)
    _enough(w, 4)
    try:
        return _fitted_circle_zones(Ps, w)
    except np.linalg.LinAlgError as e:
        raise FormSimulationError(f"a simulated draw's points fix no circle ({e})") from None


def _fitted_circle_zones(Ps, w):
    wf = w.astype(float)
    c0 = _weighted_sums(wf, Ps)[:, None] / wf.sum(1)[:, None, None]
    v = Ps - c0
    _, V = np.linalg.eigh(_weighted_grams(wf, v, v))
    E = V[:, :, 1:][:, :, ::-1]  # the plane's two largest axes, (D, 3, 2)
    xy = v @ E
    # Kasa, then Gauss-Newton on the geometric distance, as fit_circle_points.
    A = np.concatenate([2 * xy, np.ones(xy.shape[:2] + (1,))], axis=2)
    sol = np.linalg.solve(_weighted_grams(wf, A, A),
                          _weighted_sums(wf * (xy * xy).sum(2), A)[..., None])[..., 0]
    a, b = sol[:, 0], sol[:, 1]
    r = np.sqrt(sol[:, 2] + a * a + b * b)
    for _ in range(3):
        dx, dy = xy[:, :, 0] - a[:, None], xy[:, :, 1] - b[:, None]
        rho = np.hypot(dx, dy)
        J = np.stack([-dx / rho, -dy / rho, -np.ones_like(rho)], axis=2)
        step = np.linalg.solve(_weighted_grams(wf, J, J),
                               _weighted_sums(wf * -(rho - r[:, None]), J)[..., None])[..., 0]
        a, b, r = a + step[:, 0], b + step[:, 1], r + step[:, 2]
    rho = np.hypot(xy[:, :, 0] - a[:, None], xy[:, :, 1] - b[:, None])
    return np.where(w, rho, -np.inf).max(1) - np.where(w, rho, np.inf).min(1)


def _noise_factors(covs):
    """Square roots ``L`` with ``L L^T = cov`` per point (eigen-form: semi-definite covariances allowed)."""
    w, V = np.linalg.eigh(covs)
    return V * np.sqrt(np.clip(w, 0, None))[:, None, :]


def _across_sd(covs, ideal, axis):
    """Standard uncertainty of each point across the reference, from its covariance (M,).

    ``axis``: the line's unit direction (across it: its normal plane), or
    the circle's (centre, in-plane basis E (3, 2)) (across it: radially).
    """
    if isinstance(axis, tuple):
        c, E = axis
        q = (ideal - c) @ E
        radial = (q / np.linalg.norm(q, axis=1)[:, None]) @ E.T
        return np.sqrt(np.einsum("ni,nij,nj->n", radial, covs, radial))
    return np.sqrt(np.clip(np.einsum("nii->n", covs) - np.einsum("i,nij,j->n", axis, covs, axis), 0.0, None))


def _line_reference(P):
    c, d = fit_line_points(P)
    return c + np.outer((P - c) @ d, d), d


def _circle_reference(P):
    c, _, r, E = fit_circle_points(P)
    q = (P - c) @ E
    return c + (r * q / np.linalg.norm(q, axis=1)[:, None]) @ E.T, (c, E)


_FORMS = {"straightness": (_line_reference, _line_zone, _line_zones),
          "circularity": (_circle_reference, _circle_zone, _circle_zones)}
"""Per form value: its LS reference (ideal points, axis), its zone, its zones of a stack."""


def _across(e, ideal, axis):
    """Size of simulated errors ``e`` (..., M, 3) across the reference (..., M), as :func:`_across_sd` measures it."""
    if isinstance(axis, tuple):
        c, E = axis
        q = (ideal - c) @ E
        radial = (q / np.linalg.norm(q, axis=1)[:, None]) @ E.T
        return np.abs(np.einsum("...mi,mi->...m", e, radial))
    return np.linalg.norm(e - np.einsum("...m,i->...mi", e @ axis, axis), axis=-1)


def _kept(covs, ideal, axis):
    """The points the zone is evaluated on (``MAX_SD_RATIO``), a boolean mask (M,), and their ``_across_sd``."""
    sd = _across_sd(covs, ideal, axis)
    med = float(np.median(sd))
    return (sd <= MAX_SD_RATIO * med if med > 0 else np.ones(len(ideal), bool)), sd


def _passed(e, ideal, axis, sd, outlier_z):
    """Which simulated points the measurement's outlier test would keep, boolean (..., M); None keeps all."""
    if outlier_z is None:
        return None
    return _across(e, ideal, axis) <= outlier_z * sd


def _corrected(kind, P, covs, rng, n_draws, errors, held=None, outlier_z=None, shared=None):
    reference, zone, zones = _FORMS[kind]
    ideal, axis = reference(P)
    if errors is None:
        L = _noise_factors(covs)  # once: the draws differ only in their normal deviates
        z = np.stack([rng.standard_normal((len(covs), 3)) for _ in range(n_draws)])
        e = np.einsum("nij,dnj->dni", L, z)
    else:
        e = np.asarray(errors(rng, n_draws), float)
        if e.shape != (n_draws,) + P.shape:
            raise ValueError(f"errors drew shape {e.shape}, expected {(n_draws,) + P.shape}")
    keep, sd = _kept(covs, ideal, axis)
    P, ideal, e, sd = P[keep], ideal[keep], e[:, keep], sd[keep]
    raw = zone(P)
    passed = _passed(e, ideal, axis, sd, outlier_z)
    if shared is not None:
        common = shared(rng, n_draws)
        if common is not None:
            e = e + np.asarray(common, float)[:, keep]
    sims = zones(ideal + e, passed)
    if not (np.isfinite(sims).all() and np.isfinite(raw)):
        raise FormSimulationError(f"{int((~np.isfinite(sims)).sum())} of {len(sims)} simulated zones are not finite")
    b, s = float(sims.mean()), float(sims.std(ddof=1))
    if held is not None:
        s = float(np.sqrt(np.mean(_scene_spreads(zones, ideal, axis, sd, keep, held, rng, N_PATTERNS, HELD_IMAGES,
                                                 outlier_z) ** 2)))
    return FormResult(raw - b, s, raw, b, len(P), int((~keep).sum()))


def straightness(points, point_covs, rng=None, n_draws=N_DRAWS, errors=None, held=None, outlier_z=None, shared=None):
    """Noise-corrected straightness of measured edge points.

    Parameters
    ----------
    points : array_like, shape (M, 3)
        Edge points, any frame (form does not depend on the pose), mm.
    point_covs : array_like, shape (M, 3, 3)
        Their covariances, mm^2; with ``errors``, the covariances of what it
        draws (they choose the points left out, ``MAX_SD_RATIO``).
    rng : numpy.random.Generator, optional
        Seeded for reproducible results (default seed 0).
    n_draws : int
    errors : callable, optional
        ``errors(rng, n_draws)`` -> simulated errors of the points, shape
        (n_draws, M, 3), mm, with their correlations (e.g.
        :meth:`partinspect.vision.pointerrors.PointErrorModel.draw`). The
        default, each point drawn independently from ``point_covs``,
        overstates the noise-only zone of an edge whose neighbouring points
        share smoothed noise.
    held : callable, optional
        ``held(rng, n_patterns, n_draws)`` -> errors of ``n_draws`` images of
        each of ``n_patterns`` scenes, shape (n_patterns, n_draws, M, 3)
        (e.g. :meth:`~partinspect.vision.pointerrors.PointErrorModel.draw_held`,
        Type B parts held within a scene). ``u`` is then the spread over the
        images of one scene (RMS over scenes), what noise draws of one render
        can show; the planner's noise-only prediction uses it.
    outlier_z : float, optional
        The measurement's fits reject a point beyond this many standard
        uncertainties (Chauvenet, :func:`partinspect.vision.imagefeatures.chauvenet_z`),
        so a simulated point beyond it is left out of that draw's reference
        and zone too: a zone is set by the errors' tails, and keeping tails the
        measurement cuts would overstate its noise-only spread. None: every
        point kept.
    shared : callable, optional
        ``shared(rng, n_draws)`` -> errors common to the whole edge, shape
        (n_draws, M, 3), mm, or None: added to the simulated points but not
        judged by the outlier test, which sees each image's points about
        their own fitted curve (e.g.
        :meth:`~partinspect.vision.pointerrors.PointErrorModel.draw_calibration`:
        a calibration's error bends the triangulated edge, and a zone
        simulated without it reads that bend as form). Not drawn with
        ``held``: one scene's images share it.

    Returns
    -------
    FormResult
    """
    P = np.asarray(points, float).reshape(-1, 3)
    covs = np.asarray(point_covs, float).reshape(-1, 3, 3)
    if len(P) < 3:
        raise ValueError("straightness needs at least 3 points")
    rng = np.random.default_rng(0) if rng is None else rng
    return _corrected("straightness", P, covs, rng, n_draws, errors, held, outlier_z, shared)


def circularity(points, point_covs, rng=None, n_draws=N_DRAWS, errors=None, held=None, outlier_z=None, shared=None):
    """Noise-corrected circularity (roundness) of measured edge points.

    Parameters and returns as :func:`straightness`; at least 5 points
    spread round the circle.
    """
    P = np.asarray(points, float).reshape(-1, 3)
    covs = np.asarray(point_covs, float).reshape(-1, 3, 3)
    if len(P) < 5:
        raise ValueError("circularity needs at least 5 points")
    rng = np.random.default_rng(0) if rng is None else rng
    return _corrected("circularity", P, covs, rng, n_draws, errors, held, outlier_z, shared)


def scene_spreads(kind, points, point_covs, held, n_images, n_scenes=N_SCENES, rng=None, outlier_z=None):
    """Spreads of a form value over ``n_images`` images of each of ``n_scenes`` scenes.

    What a check on ``n_images`` noise draws of one render can show of the
    value's image-noise part: its sample standard deviation. The Type B
    displacements, held within a scene, change which points set the zone, so
    that spread differs from scene to scene beyond the chance of ``n_images``
    draws; the quantiles of these spreads are the interval a measured spread
    is judged by.

    Parameters
    ----------
    kind : {"straightness", "circularity"}
    points : array_like, shape (M, 3)
        Measured (or predicted) edge points, mm.
    point_covs : array_like, shape (M, 3, 3)
        Their covariances, mm^2 (they choose the points left out).
    held : callable
        ``held(rng, n_scenes, n_images)`` as in :func:`straightness`.
    n_images : int
        At least 2.
    n_scenes : int
    rng : numpy.random.Generator, optional
        Default seed 0.
    outlier_z : float, optional
        As in :func:`straightness`.

    Returns
    -------
    ndarray, shape (n_scenes,)
        The sample standard deviations (ddof 1), mm; their RMS is the ``u`` of
        :func:`straightness` / :func:`circularity` with ``held``.

    References
    ----------
    .. [1] JCGM 101:2008, 7.6 (the standard deviation of output values).
    """
    if kind not in _FORMS:
        raise ValueError(f"no form value {kind!r}")
    if n_images < 2:
        raise ValueError("a spread needs at least 2 images")
    P = np.asarray(points, float).reshape(-1, 3)
    covs = np.asarray(point_covs, float).reshape(-1, 3, 3)
    rng = np.random.default_rng(0) if rng is None else rng
    reference, _, zones = _FORMS[kind]
    ideal, axis = reference(P)
    keep, sd = _kept(covs, ideal, axis)
    return _scene_spreads(zones, ideal[keep], axis, sd[keep], keep, held, rng, n_scenes, n_images, outlier_z)


def _scene_spreads(zones, ideal, axis, sd, keep, held, rng, n_scenes, n_images, outlier_z=None):
    """Sample standard deviation of the noise-only zone over the images of each scene, (n_scenes,).

    ``ideal`` are the kept points' places and ``sd`` their ``_across_sd``
    (``keep`` selects them from what ``held`` draws); ``SCENE_BATCH``
    scenes at a time, which bounds the memory.
    """
    out = []
    for n in np.diff(np.r_[0:n_scenes:SCENE_BATCH, n_scenes]):
        h = np.asarray(held(rng, n, n_images), float)[:, :, keep].reshape((-1,) + ideal.shape)
        out.append(zones(ideal + h, _passed(h, ideal, axis, sd, outlier_z)).reshape(n, n_images).std(axis=1, ddof=1))
    return np.concatenate(out)
