"""Form deviation (straightness, circularity) from measured edge points, corrected for noise.

The form deviation of a measured edge is the width of the zone its points
span about a reference line or circle. Measurement noise widens that zone:
the peak-to-valley of N noisy points about their fit is biased upward, by
about ``2 * sqrt(2 ln N) * sigma`` for pure noise, which for N = 60 points is
some 5 sigma -- as large as a fine tolerance. Reporting it uncorrected would
fail good parts on noise alone.

Method (JCGM 101-style Monte Carlo of the noise-only case):

1. Fit the reference (least squares) to the points and take the raw form
   value ``F_raw`` about it.
2. Simulate ``n_draws`` noise-only data sets: points on the fitted reference
   at the measured points' positions, disturbed by errors drawn as the
   measurement makes them (``errors``: correlated along the edge, with the
   Type B displacements of the edge points; or, without it, independently
   from each point's 3x3 covariance); fit and evaluate each the same way. Their mean
   ``b`` is the expected noise-only form value for that many points and
   that noise; their standard deviation ``s``.
3. Report ``F = F_raw - b`` with standard uncertainty ``s``.

Points much less certain than the rest are left out of the zone (step 1
and 2 alike): those whose standard uncertainty across the reference
exceeds ``MAX_SD_RATIO`` times the median point's. That uncertainty is
taken exactly from the covariances of the simulated errors, not from the
draws: read from 200 draws it varied by some 5 % from one seed to the
next, and so did which points next to the cut were kept (on one noise
draw of the plate's 6 mm hole the raw zone read 0.057-0.058 mm with four
seeds and 0.161 mm with a fifth). A zone is a maximum minus a minimum, so
it cannot weight its points as a fit does: a few points several times
noisier than the rest set it alone, and the value's spread with it. On a stereo rig such
points are where the epipolar line runs nearly along the edge (the
partner along the curve is ill-determined) and where the shading's Type B
rest is large, e.g. at the tips of a hole seen obliquely; with them the
bracket's wall holes read circularities of 0.35-0.42 mm in 6 of 50 noise
draws of a perfect part. The choice depends on the error model alone, not
on the residuals, so the value stays unbiased for the points evaluated;
a defect where the points are that uncertain could not be resolved
anyway. ``n_excluded`` says how many were left out.

For a form-free edge ``F`` is zero on average, with the spread ``s``
(``F`` may be slightly negative: it is an estimate, not a zone width, and
is kept unclipped so that it stays unbiased). Where the true form is large
against the noise, the noise widens the zone by less than ``b`` and the
correction over-corrects by up to ``b``; the value is then low by at most
``b`` (reported in ``details`` as ``noise_bias``, so a user can judge).

References are least-squares (LSLI / LSCI, ISO 12780-1, ISO 12181-1), not
minimum-zone: the LS zone is never narrower than the minimum zone, so the
raw value is an upper bound of the ISO 1101 default (minimum zone).

Straightness is the diameter of a cylinder about the reference line
containing all points (ISO 1101, 3D straightness with a diameter zone);
circularity the radial width of two concentric circles in the plane of the
fitted circle (ISO 1101 roundness), out-of-plane components ignored.

References
----------
.. [1] ISO 1101:2017, 18.1 (straightness), 18.4 (roundness).
.. [2] ISO 12780-1:2011, ISO 12181-1:2011 (reference lines and circles).
.. [3] JCGM 101:2008, propagation of distributions by Monte Carlo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FormResult", "straightness", "circularity", "scene_spreads", "fit_line_points", "fit_circle_points"]

N_DRAWS = 200

N_PATTERNS = 200
"""Scenes drawn for a spread over the images of one scene (``held``), each
seen in ``HELD_IMAGES`` images. That spread varies from scene to scene (a
fixed pattern decides which points set the zone), so its RMS needs many
scenes: with 20 scenes of 10 images it varied by 6-7.5 % from one seed to
the next on the sample parts' planned rims and lines, with these 1.5-3.5 %
(three times the time: 40-120 ms a characteristic; only the planner's
noise-only prediction asks for it)."""

HELD_IMAGES = 5

N_SCENES = 400
"""Scenes :func:`scene_spreads` draws by default: the 2.5 % and 97.5 %
quantiles of their spreads over 20 images then move by 1.3-3.7 % from one
seed to the next (eight seeds, the sample parts' planned rims and lines)."""

SCENE_BATCH = 20
"""Scenes simulated at once (bounds the memory of long checks)."""

MAX_SD_RATIO = 2.5
"""Points whose standard uncertainty across the reference exceeds this many
times the median point's are left out of the zone. Over 50 noise draws of
each sample part (rendered, 1224 x 1024) it keeps 77-93 % of a rim's points
on average (71-100 % in single draws); the rims' circularities spread
0.011-0.025 mm over the draws (plate) and 0.019-0.024 mm (bracket), the
values' RMS over their u 0.67-1.14, and every rim's value lies within
+-2 u in 96-100 % of the draws (``benchmarks/bench_plan.py``). Lines,
whose points are alike, keep all. With 3 a rim kept 80-96 % and the
values spread 0.013-0.036 and 0.022-0.037 mm: on the bracket's wall hole
circle-5, seen obliquely, the last points of a visible run at its tips
carry 2.5-4 times the median uncertainty and lie outward of the rim (by
0.2-0.6 of it on average over 49 draws, single points by up to 2.5), and
in 3 of the 49 draws they set values 3.3-5.7 standard deviations above the
rest's. At 2 a rim keeps only 71-88 %. With no cut at all (half-size
renders) the bracket's wall holes read 0.35-0.42 mm in 6 of 50 draws."""


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


def _line_zones(Ps, w=None):
    """``_line_zone`` of a stack of point sets (D, M, 3) at once: (D,).

    ``w``: boolean (D, M), the points each set keeps (default all); the
    others take no part in its line or its zone.
    """
    if w is None:
        w = np.ones(Ps.shape[:2], bool)
    wf = w.astype(float)
    v = Ps - np.einsum("dm,dmi->di", wf, Ps)[:, None] / wf.sum(1)[:, None, None]
    _, V = np.linalg.eigh(np.einsum("dm,dmi,dmj->dij", wf, v, v))
    d = V[:, :, -1]  # the largest principal axis: the orthogonal LS line
    r = v - np.einsum("dm,di->dmi", np.einsum("dmi,di->dm", v, d), d)
    return 2.0 * np.sqrt(np.where(w, (r * r).sum(2), 0.0).max(1))


def _circle_zones(Ps, w=None):
    """``_circle_zone`` of a stack of point sets (D, M, 3) at once: (D,); ``w`` as in :func:`_line_zones`."""
    if w is None:
        w = np.ones(Ps.shape[:2], bool)
    wf = w.astype(float)
    c0 = np.einsum("dm,dmi->di", wf, Ps)[:, None] / wf.sum(1)[:, None, None]
    v = Ps - c0
    _, V = np.linalg.eigh(np.einsum("dm,dmi,dmj->dij", wf, v, v))
    E = V[:, :, 1:][:, :, ::-1]  # the plane's two largest axes, (D, 3, 2)
    xy = np.einsum("dmi,dik->dmk", v, E)
    # Kasa, then Gauss-Newton on the geometric distance, as fit_circle_points.
    A = np.concatenate([2 * xy, np.ones(xy.shape[:2] + (1,))], axis=2)
    sol = np.linalg.solve(np.einsum("dm,dmi,dmj->dij", wf, A, A),
                          np.einsum("dm,dmi,dm->di", wf, A, (xy * xy).sum(2))[..., None])[..., 0]
    a, b = sol[:, 0], sol[:, 1]
    r = np.sqrt(sol[:, 2] + a * a + b * b)
    for _ in range(3):
        dx, dy = xy[:, :, 0] - a[:, None], xy[:, :, 1] - b[:, None]
        rho = np.hypot(dx, dy)
        J = np.stack([-dx / rho, -dy / rho, -np.ones_like(rho)], axis=2)
        step = np.linalg.solve(np.einsum("dm,dmi,dmj->dij", wf, J, J),
                               np.einsum("dm,dmi,dm->di", wf, J, -(rho - r[:, None]))[..., None])[..., 0]
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


def _corrected(kind, P, covs, rng, n_draws, errors, held=None, outlier_z=None):
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
    sims = zones(ideal + e, _passed(e, ideal, axis, sd, outlier_z))
    b, s = float(sims.mean()), float(sims.std(ddof=1))
    if held is not None:
        s = float(np.sqrt(np.mean(_scene_spreads(zones, ideal, axis, sd, keep, held, rng, N_PATTERNS, HELD_IMAGES,
                                                 outlier_z) ** 2)))
    return FormResult(raw - b, s, raw, b, len(P), int((~keep).sum()))


def straightness(points, point_covs, rng=None, n_draws=N_DRAWS, errors=None, held=None, outlier_z=None):
    """Noise-corrected straightness of measured edge points.

    Parameters
    ----------
    points : array_like, shape (M, 3)
        Edge points, any frame (form does not depend on the pose), mm.
    point_covs : array_like, shape (M, 3, 3)
        Their covariances, mm^2; with ``errors``, the covariances of what
        it draws (they choose the points left out, ``MAX_SD_RATIO``).
    rng : numpy.random.Generator, optional
        Seeded for reproducible results (default seed 0).
    n_draws : int
    errors : callable, optional
        ``errors(rng, n_draws)`` -> simulated errors of the points, shape
        (n_draws, M, 3), mm, with their correlations (e.g.
        :meth:`partinspect.vision.pointerrors.PointErrorModel.draw`); by
        default each point's error is drawn independently from its
        ``point_covs``, which overstates the noise-only zone of an edge
        whose neighbouring points share smoothed noise.
    held : callable, optional
        ``held(rng, n_patterns, n_draws)`` -> errors of ``n_draws`` images
        of each of ``n_patterns`` scenes, shape (n_patterns, n_draws, M,
        3) (e.g. :meth:`~partinspect.vision.pointerrors.PointErrorModel.draw_held`:
        the Type B parts held over the images of a scene). With it ``u`` is
        the spread of the value over the images of one scene (RMS over the
        scenes), not its whole uncertainty: a fixed displacement pattern
        changes which points set the zone, so that spread is wider than
        that of the noise alone. The planner's noise-only prediction
        (what noise draws of one render can show) uses it.
    outlier_z : float, optional
        The measurement's fits reject an edge point whose residual exceeds
        this many of its standard uncertainties (Chauvenet's criterion,
        :func:`partinspect.vision.matching.chauvenet_z`), so the points
        measured are those that passed: a simulated point further across
        the reference than this many of its ``point_covs``' standard
        uncertainties is left out of that draw's reference and zone. A zone
        is the largest residual, set by the errors' tails: with the tails
        beyond 3.9 cut as the fits cut them, the noise-only zone of the
        plate's 507-point line-8 spread 14 % less, as the chain's values
        did over 800 noise draws (0.0071 against 0.0082 px with the tails
        kept; its mean 0.1 % less). None: no test (every point kept).

    Returns
    -------
    FormResult
    """
    P = np.asarray(points, float).reshape(-1, 3)
    covs = np.asarray(point_covs, float).reshape(-1, 3, 3)
    if len(P) < 3:
        raise ValueError("straightness needs at least 3 points")
    rng = np.random.default_rng(0) if rng is None else rng
    return _corrected("straightness", P, covs, rng, n_draws, errors, held, outlier_z)


def circularity(points, point_covs, rng=None, n_draws=N_DRAWS, errors=None, held=None, outlier_z=None):
    """Noise-corrected circularity (roundness) of measured edge points.

    Parameters and returns as :func:`straightness`; at least 5 points
    spread round the circle.
    """
    P = np.asarray(points, float).reshape(-1, 3)
    covs = np.asarray(point_covs, float).reshape(-1, 3, 3)
    if len(P) < 5:
        raise ValueError("circularity needs at least 5 points")
    rng = np.random.default_rng(0) if rng is None else rng
    return _corrected("circularity", P, covs, rng, n_draws, errors, held, outlier_z)


def scene_spreads(kind, points, point_covs, held, n_images, n_scenes=N_SCENES, rng=None, outlier_z=None):
    """Spreads of a form value over ``n_images`` images of each of ``n_scenes`` scenes.

    What a check on ``n_images`` noise draws of one render can show of the
    form value's image-noise part: its sample standard deviation. The Type
    B displacements of the points (the shading's, held within a scene)
    change which points set the zone, so that spread differs from scene
    to scene beyond the chance of ``n_images`` draws: for the sample parts'
    rims its 5-95 % range over scenes, with 50 images each, spans -21 to
    -34 % and +22 to +38 % of its RMS (planned rims, 1224 x 1024). The spreads' quantiles are the interval a
    measured spread of that many draws is judged by.

    Parameters
    ----------
    kind : {"straightness", "circularity"}
    points : array_like, shape (M, 3)
        Measured (or predicted) edge points, mm.
    point_covs : array_like, shape (M, 3, 3)
        Their covariances, mm^2 (they choose the points left out, as in
        :func:`straightness`).
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
        The sample standard deviations (ddof 1), mm; their RMS is the
        ``u`` of :func:`straightness` / :func:`circularity` with ``held``.

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
