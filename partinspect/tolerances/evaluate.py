"""Measured value and measurement uncertainty of every toleranced characteristic.

Each :class:`~partinspect.tolerances.resolve.Characteristic` is evaluated on
the registered measurement: value, deviation from nominal, standard
uncertainty ``u`` and ``U = k u`` (k = 2, JCGM 100 6.2). Values:

- diameter, radius: ``2 r`` / ``r`` of the fitted circle; on a rim the
  spec states broken, the wall's, with the break's Type B
  (:mod:`.edge_break`);
- distance, angle: :func:`geometry.feature_distance` /
  :func:`geometry.line_angle` on the measured features; parallelism (an
  angle between parallel lines): :func:`geometry.line_tilt`;
- straightness, circularity: the noise-corrected form (:mod:`.form`);
- position: 2 x the centre's offset from its true position in the nominal
  circle's plane (ISO 1101; datum frame = the registration's datums); at
  MMC or LMC, that minus the bonus from the measured size
  (:mod:`.material`), the limit staying the stated tolerance; where its
  datums allow a datum shift (a datum feature of size at MMB/LMB), the
  positions with those datums placed together at their best within it
  (:func:`with_datum_shifts`, :mod:`.datum_shift`);
- profile: 2 x the largest offset of the measured edge (a line over its
  measured extent, a circle over the nominal range) from the nominal CAD
  edge, plus the form (ISO 1101 line profile, two-sided zone).

Sizes, distances and angles are invariant under the rigid pose: computed
in the rig frame from the measured features, ``u`` by first-order
propagation (numerical Jacobian) of their covariances, different features'
errors independent (separate fits; a shared calibration scale error is the
vision side's budget); form values carry :mod:`.form`'s own ``u``. Position
and profile use the part-frame features of
:meth:`~partinspect.cad.registration.Registration.features_in_part_frame`,
pose covariance included. Being norms, they are not differentiable and are
biased upward at zero deviation (Rice), so their ``u`` is Monte Carlo (JCGM
101): the RMS of ``n_mc`` draws about the measured value, bias included,
which keeps ``u`` as large as the typical error there too.

References
----------
.. [1] JCGM 100:2008 (GUM), 5.1 (law of propagation), 6.2 (expanded
       uncertainty).
.. [2] JCGM 101:2008, GUM Supplement 1: propagation of distributions by a
       Monte Carlo method.
.. [3] ISO 1101:2017, 18.2 (line profile), 18.12 (position).
.. [4] ISO 14253-1:2017 (how the result is used: :mod:`.decision`).
"""

from __future__ import annotations

import functools
import math
import zlib
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from partinspect.cad.pose_refine import calibration_response
from partinspect.tolerances import geometry
from partinspect.tolerances.edge_break import band_offset, band_rms, cylinder_side, seen_from_its_face, size_on_broken_rim
from partinspect.tolerances.form import N_SCENES, FormSimulationError, circularity, scene_spreads, straightness
from partinspect.tolerances.datum_shift import allowance, best_shift, plane_basis, shift_monte_carlo, shrunk_centres
from partinspect.tolerances.material import position_with_bonus

__all__ = [
    "COVERAGE_FACTOR",
    "Evaluation",
    "evaluate",
    "evaluate_characteristic",
    "with_datum_shifts",
    "without_datum_shifts",
    "form_scene_spreads",
    "propagate",
    "monte_carlo",
    "true_position",
    "position_gradient",
    "line_profile",
    "circle_profile",
    "measured_distance",
    "measured_angle",
    "nominal_legs",
    "measured_tilt",
    "PAIR_VALUES",
    "pick_feature",
    "measured_result",
    "unmeasured_result",
]

COVERAGE_FACTOR = 2.0
N_MC = 4000
# Draws of a pattern's datum shift: each solves the frame placement again.
N_SHIFT = 400
_SHRINK = 3.0  # see true_position


@dataclass(frozen=True)
class Evaluation:
    """The measured result of one characteristic.

    Attributes
    ----------
    characteristic : Characteristic
    measured : float or None
        Measured value, the characteristic's unit (mm or rad); None when it
        could not be measured.
    deviation : float or None
        ``measured - nominal``.
    standard_uncertainty : float or None
        ``u``, same unit.
    expanded_uncertainty : float or None
        ``U = k u``.
    coverage_factor : float
    method : str
        How ``u`` was obtained, for the report.
    reason : str or None
        Why the characteristic could not be measured.
    details : dict
        Intermediate figures (raw form value, noise bias, ...).
    """

    characteristic: object
    measured: float | None
    deviation: float | None
    standard_uncertainty: float | None
    expanded_uncertainty: float | None
    coverage_factor: float = COVERAGE_FACTOR
    method: str = ""
    reason: str | None = None
    details: dict = field(default_factory=dict)

    @property
    def id(self):
        return self.characteristic.id

    @property
    def measured_ok(self):
        return self.measured is not None

    def to_dict(self):
        """The report.json fields this result fills (degrees for angles)."""
        conv = math.degrees if self.characteristic.unit == "rad" else float
        d = self.characteristic.to_dict()
        for key in ("measured", "deviation", "standard_uncertainty", "expanded_uncertainty"):
            v = getattr(self, key)
            d[key] = None if v is None else round(conv(v), 12)
        d["coverage_factor"] = self.coverage_factor
        d["method"] = self.method
        if self.reason:
            d["reason"] = self.reason
        if self.details:
            # Intermediate figures a user needs to judge the value (a form's
            # raw zone and the noise zone subtracted from it), same unit.
            d["details"] = {k: round(float(v), 12) if isinstance(v, (float, np.floating)) else v
                            for k, v in self.details.items()}
        return d


def unmeasured_result(c, reason):
    """The :class:`Evaluation` of a characteristic that could not be measured, with why."""
    return Evaluation(c, None, None, None, None, method="", reason=reason)


def measured_result(c, value, u, k, method, **details):
    """The :class:`Evaluation` of a measured value with standard uncertainty ``u`` and ``U = k u``."""
    return Evaluation(c, float(value), float(value - c.nominal), float(u), float(k * u), k, method, None, details)


# ---------------------------------------------------------------------------
# generic propagation


def propagate(f, x, cov, h=None):
    """First-order (GUM 5.1) standard uncertainty of scalar ``f(x)``.

    Parameters
    ----------
    f : callable, (n,) -> float
    x : ndarray, shape (n,)
    cov : ndarray, shape (n, n)
    h : ndarray, shape (n,), optional
        Central-difference steps; default 1e-6 (units of x).

    Returns
    -------
    value, u : float
    """
    x = np.asarray(x, float)
    h = np.full(x.size, 1e-6) if h is None else h
    g = np.array([(f(x + e) - f(x - e)) / (2 * s) for e, s in zip(np.diag(h), h)])
    return float(f(x)), float(np.sqrt(max(g @ cov @ g, 0.0)))


def _sqrt_psd(C):
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return V * np.sqrt(np.clip(w, 0, None))


def monte_carlo(f, x, cov, rng, n=N_MC):
    """Value and Monte Carlo (JCGM 101) standard uncertainty of ``f(x)``, ``x ~ N(x, cov)``.

    ``u`` is the root mean square of ``f(draw) - f(x)``: spread and bias of
    a non-linear (e.g. norm-like) function together, which keeps ``u``
    honest where ``f`` is not differentiable.

    Parameters
    ----------
    f : callable, (n_draws, n) -> (n_draws,)
        Vectorised over draws.
    x : ndarray, shape (n,)
    cov : ndarray, shape (n, n)
    rng : numpy.random.Generator
    n : int

    Returns
    -------
    value, u : float
    """
    x = np.asarray(x, float)
    draws = x + rng.standard_normal((n, x.size)) @ _sqrt_psd(np.asarray(cov, float)).T
    v0 = float(f(x[None])[0])
    return v0, float(np.sqrt(np.mean((f(draws) - v0) ** 2)))


# ---------------------------------------------------------------------------
# pose-dependent values (part frame)


def true_position(center, cov, nominal_center, nominal_normal, rng, n=N_MC):
    """ISO 1101 position of a circle centre: 2 x its radial offset from the true position.

    Parameters
    ----------
    center : ndarray, shape (3,)
        Measured centre, part frame, mm.
    cov : ndarray, shape (3, 3)
        Its covariance including the pose's, mm^2.
    nominal_center, nominal_normal : ndarray, shape (3,)
        The true position and the circle's axis (part frame); the offset
        is taken in the plane normal to the axis.
    rng : numpy.random.Generator

    Returns
    -------
    value, u : float
        mm. ``value`` is ``2 |P (center - nominal_center)|``; ``u`` the root
        mean square error of that estimator, by Monte Carlo (JCGM 101) at a
        bias-corrected offset (see the comment in the code): at zero offset
        it is the Rice/Rayleigh RMS, far from zero the radial standard
        uncertainty.
    """
    d, mu, P = _offsets(center, cov, nominal_center, nominal_normal)
    value = 2.0 * float(np.linalg.norm(d))
    draws = mu + rng.standard_normal((n, 3)) @ _sqrt_psd(np.asarray(cov, float)).T
    v = 2.0 * np.linalg.norm(draws @ P, axis=1)
    return value, float(np.sqrt(np.mean((v - 2.0 * np.linalg.norm(mu)) ** 2)))


def position_gradient(center, cov, nominal_center, nominal_normal):
    """``d position / d centre`` at the offset :func:`true_position` simulates at, shape (3,).

    ``2 P m / |P m|`` with ``m`` the bias-corrected in-plane offset; zero
    when that offset is not significant (at a zero offset the position's
    error is uncorrelated with the centre's by symmetry).
    """
    _, mu, _ = _offsets(center, cov, nominal_center, nominal_normal)
    norm = float(np.linalg.norm(mu))
    return 2.0 * mu / norm if norm > 0 else np.zeros(3)


def _offsets(center, cov, nominal_center, nominal_normal):
    """The in-plane offset, its bias-corrected value and the in-plane projector."""
    N = np.asarray(nominal_normal, float)
    P = np.eye(3) - np.outer(N, N)
    cov = np.asarray(cov, float)
    d = P @ (np.asarray(center, float) - np.asarray(nominal_center, float))
    # Near the true position the offset's length is Rice-distributed and
    # biased up: E|d|^2 = |mu|^2 + tr(P cov P). The RMS error of the
    # estimate is therefore simulated at a shrunk offset mu_hat, a
    # parametric bootstrap of the estimator's error rather than its spread
    # about itself. The shrinkage |mu_hat|^2 = max(0, |d|^2 - 3 tr) takes
    # the offset as zero unless it is significant (|d|^2 > 3 tr happens by
    # chance in ~5 % of cases at zero offset for an isotropic 2D error); a
    # milder, unbiased shrinkage (1 tr) leaves u anti-correlated with the
    # error at zero offset, and the interval undercovers.
    excess = float(d @ d) - _SHRINK * float(np.trace(P @ cov @ P))
    mu = d * np.sqrt(max(excess, 0.0) / float(d @ d)) if d @ d > 0 else d
    return d, mu, P


def line_profile(point, direction, cov, s0, s1, nominal_start, nominal_end, rng, n=N_MC):
    """Twice the largest offset of a measured line stretch from the nominal line.

    The distance from a line is convex along another line, so over the
    stretch ``point + s direction``, ``s0 <= s <= s1``, it is largest at an
    end.

    Parameters
    ----------
    point, direction : ndarray, shape (3,)
        Measured line, part frame.
    cov : ndarray, shape (6, 6)
        Covariance of (point, direction), pose included.
    s0, s1 : float
        Measured extent along the line, mm.
    nominal_start, nominal_end : ndarray, shape (3,)

    Returns
    -------
    value, u : float
    """
    A = np.asarray(nominal_start, float)
    D = np.asarray(nominal_end, float) - A
    D = D / np.linalg.norm(D)

    def f(x):
        p, d = x[:, :3], x[:, 3:]
        d = d / np.linalg.norm(d, axis=1)[:, None]
        worst = 0.0
        for s in (s0, s1):
            v = p + s * d - A
            perp = v - (v @ D)[:, None] * D
            worst = np.maximum(worst, np.linalg.norm(perp, axis=1))
        return 2.0 * worst

    return monte_carlo(f, np.r_[point, direction], cov, rng, n)


def circle_profile(center, normal, radius, cov, nominal, rng, n=N_MC, n_angles=72):
    """Twice the largest distance of a measured circle (or arc) from the nominal one.

    The measured circle is sampled over the nominal angular range, its
    in-plane axes being the nominal frame's projected into the measured
    plane; each sample's distance to the nominal circle is
    ``sqrt((rho - R)^2 + h^2)`` (``h`` along the nominal axis, ``rho``
    across it).

    Parameters
    ----------
    center, normal : ndarray, shape (3,)
    radius : float
    cov : ndarray, shape (7, 7)
        Of (center, normal, radius), part frame, pose included.
    nominal : Feature-like
        ``center``, ``normal``, ``radius``, ``kind``, ``angle_start``/``angle_end`` for arcs.

    Returns
    -------
    value, u : float
    """
    C0, N0, R0 = np.asarray(nominal.center, float), np.asarray(nominal.normal, float), float(nominal.radius)
    x0 = geometry_reference(N0)
    if nominal.kind == "arc":
        th = np.linspace(nominal.angle_start, nominal.angle_end, n_angles)
    else:
        th = np.linspace(0.0, 2 * np.pi, n_angles, endpoint=False)
    ct, st = np.cos(th), np.sin(th)

    def f(x):
        c, nrm, r = x[:, :3], x[:, 3:6], x[:, 6]
        nrm = nrm / np.linalg.norm(nrm, axis=1)[:, None]
        nrm = nrm * np.where(nrm @ N0 < 0, -1.0, 1.0)[:, None]  # a measured normal's sign is arbitrary
        u = x0 - (nrm @ x0)[:, None] * nrm
        u /= np.linalg.norm(u, axis=1)[:, None]
        v = np.cross(nrm, u)
        q = c[:, None] + r[:, None, None] * (ct[None, :, None] * u[:, None] + st[None, :, None] * v[:, None]) - C0
        h = q @ N0
        rho = np.linalg.norm(q - h[..., None] * N0, axis=2)
        return 2.0 * np.sqrt((rho - R0) ** 2 + h**2).max(1)

    return monte_carlo(f, np.r_[center, normal, radius], cov, rng, n)


def geometry_reference(normal):
    """A circle's in-plane x axis from its normal alone (as the CAD inventory defines it)."""
    from partinspect.frames import reference_direction

    return reference_direction(normal)


# ---------------------------------------------------------------------------
# pose-invariant values (rig frame)


def _record(kind, x, extent=None):
    if kind == "line":
        p, d = x[:3], x[3:6] / np.linalg.norm(x[3:6])
        s0, s1 = extent
        return SimpleNamespace(kind="line", start=p + s0 * d, end=p + s1 * d)
    return SimpleNamespace(kind="circle", center=x[:3], normal=x[3:6], radius=x[6])


def _line_line_distance(a, b):
    # Same definition as geometry.feature_distance for parallel lines (the
    # midpoint of the second to the first), without its parallelism check: a
    # measured line is never exactly parallel to another.
    return geometry._point_line_distance(0.5 * (b.start + b.end), a)


def measured_distance(fa, fb):
    """Distance between two measured features, as the nominal is defined (mm)."""
    if fa.kind == "line" and fb.kind == "line":
        return _line_line_distance(fa, fb)
    return geometry.feature_distance(fa, fb)


def measured_angle(fa, fb, legs=None):
    """Angle between two measured lines, as the nominal is defined (rad).

    ``legs``: the nominal edges' legs (:func:`nominal_legs`) in the
    measured features' frame; each measured direction is turned to agree
    with its own, so that segments that cross read the nominal's angle,
    not its supplement (:func:`geometry.line_angle`).
    """
    return geometry.line_angle(fa.start, fa.end, fb.start, fb.end, legs=legs)


def nominal_legs(c, inventory, rotation=None):
    """The legs of an angle characteristic's CAD edges, shape (3,) each, part frame or turned by ``rotation``.

    Parameters
    ----------
    c : Characteristic
        Of type "angle", two line features.
    inventory : Inventory
    rotation : ndarray, shape (3, 3), optional
        Part to measurement frame (the registration's rotation for rig-frame
        features); the estimated pose is good to far less than the right
        angle that would turn a leg's side.
    """
    a, b = (inventory[fid] for fid in c.features)
    legs = geometry.line_legs(a.start, a.end, b.start, b.end)
    return legs if rotation is None else tuple(np.asarray(rotation, float) @ u for u in legs)


def measured_tilt(fa, fb, towards=None):
    """Tilt of measured line fa against fb towards a direction (same frame), as the nominal is defined (rad)."""
    return geometry.line_tilt(fa.start, fa.end, fb.start, fb.end, towards)


# The values between two measured features, by characteristic type.
PAIR_VALUES = {"distance": measured_distance, "angle": measured_angle, "parallelism": measured_tilt}


def _stacked(recs):
    """Rig-frame parameter vectors, joint covariance and rebuild info of measured records.

    ``recs``: ``(kind, record, (x, C))`` with ``x``, ``C`` the record's
    stacked rig-frame parameters and their covariance, as
    ``Registration.measured_params`` gives them. Two records' image noise
    is independent; the calibration's error they share gives the
    off-diagonal blocks ``G_a G_b^T``
    (:func:`partinspect.cad.pose_refine.calibration_response`), so that a
    distance between two features is not charged for the calibration's
    error that moves both alike.
    """
    xs, covs, info, responses = [], [], [], []
    for kind, rec, (x, C) in recs:
        if kind == "circle":
            info.append((kind, None))
        else:
            p, d = x[:3], x[3:6]
            info.append((kind, (float((np.asarray(rec.start, float) - p) @ d), float((np.asarray(rec.end, float) - p) @ d))))
        xs.append(np.asarray(x, float))
        covs.append(C)
        responses.append(calibration_response(kind, rec))
    sizes = [len(x) for x in xs]
    q = {G.shape[1] for G in responses}
    G = np.vstack(responses) if len(q) == 1 else np.zeros((sum(sizes), 0))
    cov = G @ G.T
    o = 0
    for C in covs:
        cov[o : o + len(C), o : o + len(C)] = C
        o += len(C)
    return np.concatenate(xs), cov, info, sizes


def _pair_function(g, info, sizes):
    def f(x):
        a = _record(info[0][0], x[: sizes[0]], info[0][1])
        b = _record(info[1][0], x[sizes[0] :], info[1][1])
        return g(a, b)

    return f


# ---------------------------------------------------------------------------


def pick_feature(part_features, cad_id):
    """The measured feature taken for a CAD id: the longest line stretch, or the circle."""
    cands = [p for p in part_features if p.cad_id == cad_id]
    if not cands:
        return None
    if cands[0].kind == "line":
        return max(cands, key=lambda p: np.linalg.norm(p.end - p.start) if p.start is not None else 0.0)
    return cands[0]


def _rng(seed, cid):
    return np.random.default_rng([seed, zlib.crc32(cid.encode())])


def evaluate(characteristics, registration, inventory, *, k=COVERAGE_FACTOR, seed=0, n_mc=N_MC, datum_shift=True):
    """Evaluate characteristics on a registered measurement.

    Parameters
    ----------
    characteristics : sequence of Characteristic
    registration : partinspect.cad.registration.Registration
        Gives the assignment, the pose, the measured features and their
        rig-frame parameters (``measured_params``).
    inventory : Inventory
        Nominal CAD features (part frame).
    k : float
        Coverage factor of the expanded uncertainty.
    seed : int
        Seed of the Monte Carlo draws (results are reproducible).
    n_mc : int
        Monte Carlo draws for position and profile.
    datum_shift : bool
        Evaluate the positions whose datums allow a datum shift as their
        patterns (:func:`with_datum_shifts`); False for a caller that
        evaluates a pattern's members in parts and applies it after.

    Returns
    -------
    list of Evaluation
        In the order given; a characteristic whose feature was not
        measured (not seen, not matched, no edge points for a form
        value) has ``measured`` None and a ``reason``.
    """
    parts = registration.features_in_part_frame()
    out = [evaluate_characteristic(c, parts, registration, inventory, k=k, seed=seed, n_mc=n_mc) for c in characteristics]
    return with_datum_shifts(out, registration, inventory, k=k, seed=seed) if datum_shift else out


def with_datum_shifts(evaluations, registration, inventory, *, k=COVERAGE_FACTOR, seed=0, n_draws=N_SHIFT):
    """Positions whose datum reference frame allows a datum shift, evaluated as patterns.

    Positions with the same datums (letters, boundaries and features) are
    one simultaneous requirement (ASME Y14.5-2018 7.19): their measured
    features shift, and rotate where the datums allow, together
    (:mod:`partinspect.tolerances.datum_shift`). Each value becomes the
    position (minus its bonus) at the best placement the shift allows;
    ``details["datum_shift"]`` gives the shift applied, or why none was.

    Parameters
    ----------
    evaluations : list of Evaluation
        As :func:`evaluate_characteristic` gives them.
    registration : Registration
    inventory : Inventory
    k : float
    seed : int
    n_draws : int
        Monte Carlo draws of the pattern's inputs.

    Returns
    -------
    list of Evaluation
        In the same order.
    """
    groups = {}
    for i, e in enumerate(evaluations):
        c = e.characteristic
        if c.type == "position" and any(d.boundary for d in c.datums):
            groups.setdefault(tuple((d.letter, d.boundary, d.features) for d in c.datums), []).append(i)
    out = list(evaluations)
    if not groups:
        return out
    parts = registration.features_in_part_frame()
    for key, idx in groups.items():
        members = [evaluations[i] for i in idx if evaluations[i].measured is not None]
        if not members:
            continue
        rng = np.random.default_rng([seed, zlib.crc32("|".join(e.id for e in members).encode())])
        shifted = _pattern(members, parts, registration, inventory, k, rng, n_draws)
        done = {e.id: e for e in shifted}
        for i in idx:
            out[i] = done.get(out[i].id, out[i])
    return out


def without_datum_shifts(evaluations, why):
    """The evaluations, each position whose datums allow a datum shift saying why none was applied.

    For callers that evaluate positions one by one where a pattern cannot
    be placed together (several views: each feature from its own views).
    """
    out = []
    for e in evaluations:
        c = e.characteristic
        shifted = c.type == "position" and e.measured is not None and any(d.boundary for d in c.datums)
        out.append(_not_shifted([e], c.datums, why)[0] if shifted else e)
    return out


def _not_shifted(members, datums, why):
    """The members as evaluated without a shift, saying why none was applied."""
    text = " | ".join(d.label for d in datums)
    return [Evaluation(e.characteristic, e.measured, e.deviation, e.standard_uncertainty, e.expanded_uncertainty,
                       e.coverage_factor, f"{e.method}; no datum shift applied ({why})", e.reason,
                       {**e.details, "datum_shift": {"datums": text, "applied": False, "reason": why}})
            for e in members]


def _datum_rims(datums, parts, registration, inventory, k):
    """Each datum of size's measured rim: [(DatumRef, PartFeature, size Evaluation)], or a reason why not."""
    out = []
    for d in datums:
        if not d.of_size:
            if d.boundary is not None:
                return (f"datum {d.letter}'s features are not known as a hole or boss with a size tolerance (give "
                        f"them under datum_features)" if not d.features else
                        f"datum {d.letter} ({', '.join(d.features)}) is not one hole or boss with a size tolerance")
            out.append((d, None, None))
            continue
        for size in d.sizes:
            pf = pick_feature(parts, size.features[0])
            if pf is not None and pf.kind == "circle":
                rec = registration.measured_feature(pf.kind, pf.index)
                out.append((d, pf, _size_result(size, rec, registration, inventory, k)))
                break
        else:
            return f"no rim of datum {d.letter} ({', '.join(d.features)}) was measured"
    return out


def _pattern(members, parts, registration, inventory, k, rng, n_draws):
    """A pattern's positions at the best placement its datum shift allows (:func:`with_datum_shifts`)."""
    datums = members[0].characteristic.datums
    rims = _datum_rims(datums, parts, registration, inventory, k)
    if isinstance(rims, str):
        return _not_shifted(members, datums, rims)
    sized = [i for i, (_, pf, _) in enumerate(rims) if pf is not None]
    if not sized:
        return _not_shifted(members, datums, "no datum is a feature of size")
    located = rims[sized[0]]
    clocking = rims[sized[1]] if len(sized) > 1 and sized[1] == sized[0] + 1 else None
    rotation = "clocked" if clocking else ("free" if sized[0] == len(rims) - 1 else "fixed")
    use = [located] + ([clocking] if clocking else [])
    feats = [pick_feature(parts, e.characteristic.features[0]) for e in members]
    nominal = [inventory[e.characteristic.features[0]] for e in members]
    axis = np.asarray(nominal[0].normal, float)
    normals = [n.normal for n in nominal] + [inventory[pf.cad_id].normal for _, pf, _ in use]
    if any(abs(float(np.asarray(n, float) @ axis)) < math.cos(1e-6) for n in normals):
        return _not_shifted(members, datums, "the pattern's and the datum features' axes are not parallel")
    E = plane_basis(axis)
    x, cov, cov_c, sizes, u_sizes, refs = _pattern_inputs(members, feats + [pf for _, pf, _ in use], use, registration)
    n_c, m = len(feats) + len(use), len(members)
    P = np.array([n.center for n in nominal]) @ E.T
    D = np.array([inventory[pf.cad_id].center for _, pf, _ in use]) @ E.T
    t = np.array([e.characteristic.upper_limit for e in members], float)

    def solve(z):
        centres = z[:3 * n_c].reshape(-1, 3) @ E.T
        rho = np.array([float(allowance(d.boundary, d.internal, size, 0.0, ref)[0])
                        for (d, _, _), size, ref in zip(use, z[3 * n_c + m:], refs)])
        return best_shift(P, centres[:m], z[3 * n_c:3 * n_c + m], t, D, centres[m:], rho, rotation)

    # The error is simulated about the pattern's places in the shifted
    # frame plus each offset shrunk as true_position does (the measured
    # offsets, norms near zero, are biased up by the noise).
    measured = solve(x)
    plane_covs = np.array([E @ cov_c[3 * i:3 * i + 3, 3 * i:3 * i + 3] @ E.T for i in range(m)])
    at = x.copy()
    at[:3 * m] -= ((measured.residuals - shrunk_centres(measured.residuals, plane_covs)) @ E).ravel()
    result, u = shift_monte_carlo(x, cov, solve, rng, n_draws, at=at)
    shift = _shift_details(datums, use, result, E, rotation, sizes, u_sizes, refs, [e.id for e in members])
    method = (f"datum shift ({shift['datums']}): the pattern of {m} placed together at its best within the "
              f"shift, Monte Carlo (JCGM 101, {n_draws} draws of centres, sizes and the datum features' "
              "sizes, about the offsets shrunk unless significant), pose covariance included")
    return [measured_result(e.characteristic, result.values[i], u[i], k, method,
                            **{**e.details, "position": float(result.positions[i]),
                               "without_shift": float(result.unshifted[i]), "datum_shift": shift})
            for i, e in enumerate(members)]


def _pattern_inputs(members, pfs, use, registration):
    """A pattern's inputs stacked: every centre, then the bonuses and the datum sizes, with their covariance.

    The centres keep their joint covariance (the shared pose's and
    calibration's parts included); the bonuses and the datum sizes are
    taken as independent of them (a full circle's fit leaves its centre and
    radius uncorrelated to first order).

    Returns
    -------
    x, cov, cov_centres, sizes, u_sizes, refs
    """
    n_c = len(pfs)
    cov_c = np.block([[a.param_cov[:3, :3] if a is b else registration.cross_covariance(a, b)[:3, :3] for b in pfs]
                      for a in pfs])
    bonus = [float(e.details.get("bonus", 0.0)) for e in members]
    u_bonus = [float(e.details.get("bonus_standard_uncertainty", 0.0)) for e in members]
    sizes = [float(sz.measured) / (1.0 if sz.characteristic.type == "diameter" else 0.5) for _, _, sz in use]
    u_sizes = [float(sz.standard_uncertainty) / (1.0 if sz.characteristic.type == "diameter" else 0.5)
               for _, _, sz in use]
    refs = [d.reference(sz.characteristic) for d, _, sz in use]
    x = np.r_[np.concatenate([pf.center for pf in pfs]), bonus, sizes]
    cov = np.zeros((len(x), len(x)))
    cov[:3 * n_c, :3 * n_c] = cov_c
    cov[3 * n_c:, 3 * n_c:] = np.diag(np.square(u_bonus + u_sizes))
    return x, cov, cov_c, sizes, u_sizes, refs


def _shift_details(datums, use, result, E, rotation, sizes, u_sizes, refs, pattern):
    """report.json's ``details.datum_shift`` of a pattern placed within its datum shift."""
    rho_u = [allowance(d.boundary, d.internal, size, u_s, ref) for (d, _, _), size, u_s, ref in
             zip(use, sizes, u_sizes, refs)]
    return {"datums": " | ".join(d.label for d in datums), "applied": True,
            "translation": float(np.linalg.norm(result.translation)),
            "translation_vector": [round(float(v), 12) for v in result.translation @ E],
            "rotation_deg": math.degrees(result.rotation), "rotation": rotation,
            "allowance": {d.letter: float(r) for (d, _, _), (r, _) in zip(use, rho_u)},
            "allowance_standard_uncertainty": {d.letter: float(ur) for (d, _, _), (_, ur) in zip(use, rho_u)},
            "datum_sizes": {d.letter: s_ for (d, _, _), s_ in zip(use, sizes)},
            "boundary_sizes": {d.letter: float(r) for (d, _, _), r in zip(use, refs) if r is not None},
            "pattern": pattern}


def _form_points(record):
    """A record's edge points and their covariances, or None (too few, or none with covariances, for a form value)."""
    pts, pcs = getattr(record, "points", None), getattr(record, "point_covs", None)
    return None if pts is None or pcs is None or len(pts) < 5 else (pts, pcs)


def _errors(record):
    """The measured record's draws of its points' correlated errors, or None (independent draws)."""
    model = getattr(record, "point_errors", None)
    return None if model is None else model.draw


def _outlier_z(record):
    """The measured record's outlier threshold for its points' simulated errors, or None."""
    return getattr(getattr(record, "point_errors", None), "outlier_z", None)


def _simulation(record, one_scene):
    """Keyword arguments of a form function that simulate the record's points as the chain made them."""
    model = getattr(record, "point_errors", None)
    shared = getattr(model, "draw_calibration", None) if getattr(model, "calibration", None) is not None else None
    return {"errors": _errors(record), "held": _held(record) if one_scene else None, "outlier_z": _outlier_z(record),
            "shared": shared}


def _held(record):
    """Draws with the record's Type B parts held per scene, or None (no error model).

    A model without Type B parts draws its images alike: held or not, the
    spread is the noise's, from the many scenes' images of a held draw.
    """
    model = getattr(record, "point_errors", None)
    return model.draw_held if model is not None else None


def form_scene_spreads(c, parts, registration, n_images, *, seed=0, n_scenes=N_SCENES):
    """A form characteristic's spreads over ``n_images`` images of each of ``n_scenes`` scenes, or None.

    See :func:`partinspect.tolerances.form.scene_spreads`: what a check on
    ``n_images`` noise draws of one render may measure, the Type B parts
    of the points held within a scene (for points without any, the
    sampling distribution of the spread of n values, their tails
    included). None for other characteristics, for a feature not measured,
    for points without an error model, or where the zone cannot be
    simulated (:class:`~partinspect.tolerances.form.FormSimulationError`).

    Returns
    -------
    ndarray, shape (n_scenes,) or None
        Standard deviations, mm.
    """
    if c.type not in ("straightness", "circularity"):
        return None
    p = pick_feature(parts, c.features[0])
    if p is None:
        return None
    rec = registration.measured_feature(p.kind, p.index)
    held, points = _held(rec), _form_points(rec)
    if held is None or points is None:
        return None
    try:
        return scene_spreads(c.type, *points, held, n_images, n_scenes, _rng(seed, c.id), _outlier_z(rec))
    except FormSimulationError:
        return None  # no range over scenes: the caller judges by chance alone


def _size_result(c, rec, registration, inventory, k):
    """The measured diameter or radius of a circle record (:class:`Evaluation` of size characteristic ``c``)."""
    f = 2.0 if c.type == "diameter" else 1.0
    if c.edge_break is None:
        return measured_result(c, f * float(rec.radius), f * float(rec.radius_std), k, "first order (pose-invariant)")
    convex = cylinder_side(inventory, c.features[0])
    if not seen_from_its_face(inventory, c.features[0], registration.part_to_camera):
        # A rim seen through its hole (or past its boss) shows the wall's
        # own silhouette, where the break has not begun.
        return measured_result(c, f * float(rec.radius), f * float(rec.radius_std), k,
                               "first order (pose-invariant); the wall's silhouette, seen through the hole past its "
                               "broken rim")
    moved = getattr(rec, "band_place", None)
    if moved is not None:
        # The rim's points were moved onto the sharp rim by E[b] times their place: what is left is
        # the break's size about E[b] (the places' own u is in the fit's covariance).
        _, u_b = band_offset(*c.edge_break, place=(moved.s, 0.0))
        r, u, corr = float(rec.radius), math.hypot(float(rec.radius_std), u_b), 0.0
        place = {"band_place": "predicted from the light on the part; the rim's points moved by it and fitted again",
                 "s": moved.s, "s_standard_uncertainty": moved.u}
    else:
        r, u, corr, u_b = size_on_broken_rim(float(rec.radius), float(rec.radius_std), convex, *c.edge_break,
                                             place=c.band_place)
        place = ({"band_place": "uniform across the band"} if c.band_place is None else
                 {"band_place": "predicted from the light on the part", "s": c.band_place[0],
                  "s_standard_uncertainty": c.band_place[1]})
    wall = {False: "the hole's wall", True: "the boss's wall", None: "the wall (material side unknown)"}[convex]
    return measured_result(c, f * r, f * u, k, "first order (pose-invariant), edge break Type B",
                           edge_break={"min": c.edge_break[0], "max": c.edge_break[1], "correction": f * corr,
                                       "standard_uncertainty": f * u_b, "rim": f * float(rec.radius),
                                       "measured_as": f"{wall}, from its broken rim", **place})


def _position_with_bonus(c, position, u_position, pf, rec, nominal, registration, inventory, k, method):
    """A position at MMC or LMC: ``position - bonus(d) <= t`` (:mod:`.material`), ``d`` as its size characteristic measures it."""
    m = c.material
    size = _size_result(m.size, rec, registration, inventory, k)
    scale = 2.0 if m.size.type == "radius" else 1.0
    d, u_d = scale * size.measured, scale * size.standard_uncertainty
    grad = position_gradient(pf.center, pf.covariance, nominal.center, nominal.normal)
    # Centre and radius come out of one fit: their covariance is in the
    # feature's parameter covariance (centre rows, radius column); an edge
    # break's correction is an independent Type B shift and adds none.
    cov_cd = 2.0 * np.asarray(pf.param_cov, float)[:3, 6]
    q, u, bonus, u_bonus, rho = position_with_bonus(position, u_position, grad, d, u_d, cov_cd, m.modifier,
                                                    m.internal, m.reference)
    return measured_result(
        c, q, u, k, f"{method}; minus the {m.modifier} bonus from the measured size, GUM law of propagation with the "
        "fit's centre-size covariance", datums=list(registration.datums), position=position,
        position_standard_uncertainty=u_position, bonus=bonus, bonus_standard_uncertainty=u_bonus,
        position_bonus_correlation=rho, measured_size=d, measured_size_standard_uncertainty=u_d,
        size_at_condition=m.reference, size_characteristic=m.size.id, modifier=m.modifier,
        feature_of_size="hole" if m.internal else "boss")


def evaluate_characteristic(c, parts, registration, inventory, *, k=COVERAGE_FACTOR, seed=0, n_mc=N_MC,
                            one_scene=False):
    """One characteristic; ``parts`` as ``registration.features_in_part_frame()`` returns.

    ``one_scene``: state the form's u as its spread over images of one
    scene (the Type B parts of its points held, see
    :func:`partinspect.tolerances.form.straightness`), for the planner's
    noise-only prediction; by default the whole uncertainty.
    """
    picked = [pick_feature(parts, fid) for fid in c.features]
    missing = [fid for fid, p in zip(c.features, picked) if p is None]
    if missing:
        return unmeasured_result(c, f"{', '.join(missing)} not measured (not visible in both images or not matched)")
    rng = _rng(seed, c.id)
    rec = [registration.measured_feature(p.kind, p.index) for p in picked]
    pf = picked[0]
    t = c.type
    if t in ("diameter", "radius", "position") and pf.kind != "circle":
        return unmeasured_result(c, f"{c.features[0]} is not measured as a circle")
    if t in ("diameter", "radius"):
        return _size_result(c, rec[0], registration, inventory, k)
    if t in ("straightness", "circularity"):
        return _form_result(c, rec[0], registration, inventory, rng, k, one_scene)
    if t in PAIR_VALUES:
        return _pair_result(c, picked, rec, registration, inventory, k)
    if t == "position":
        nominal = inventory[c.features[0]]
        value, u = true_position(pf.center, pf.covariance, nominal.center, nominal.normal, rng, n_mc)
        method = "Monte Carlo (JCGM 101), pose covariance included"
        if c.material is None:
            return measured_result(c, value, u, k, method, datums=list(registration.datums))
        return _position_with_bonus(c, value, u, pf, rec[0], nominal, registration, inventory, k, method)
    if t == "profile":
        return _profile_result(c, pf, rec[0], inventory, rng, k, n_mc, one_scene)
    return unmeasured_result(c, f"unknown characteristic type {t!r}")


def _form_result(c, rec, registration, inventory, rng, k, one_scene):
    """A straightness or circularity from the feature's edge points (:mod:`partinspect.tolerances.form`)."""
    t = c.type
    points = _form_points(rec)
    if points is None:
        return unmeasured_result(c, f"no edge points with covariances for the {t} of {c.features[0]}")
    try:
        fr = (straightness if t == "straightness" else circularity)(*points, rng, **_simulation(rec, one_scene))
    except FormSimulationError as e:
        return unmeasured_result(c, f"the {t} of {c.features[0]} has no uncertainty: its noise-only zone cannot be "
                              f"simulated ({e})")
    details = dict(raw=fr.raw, noise_bias=fr.noise_bias, n_points=fr.n_points, n_excluded=fr.n_excluded)
    u = fr.u
    if c.edge_break is not None and seen_from_its_face(inventory, c.features[0], registration.part_to_camera):
        # Where the step lies on a rounded rim's band changes around it: an
        # out-of-roundness of the rim seen, not of the wall, up to the break.
        u_b = band_rms(*c.edge_break)
        u = math.hypot(u, u_b)
        details["edge_break"] = {"min": c.edge_break[0], "max": c.edge_break[1], "standard_uncertainty": u_b}
    return measured_result(c, fr.value, u, k, "noise-bias corrected form, Monte Carlo noise-only reference (pose-invariant)",
                   **details)


def _pair_result(c, picked, rec, registration, inventory, k):
    """A value of two measured features (distance, angle, parallelism, ...), first order in their rig-frame parameters."""
    t = c.type
    x, cov, info, sizes = _stacked([(p.kind, r, registration.measured_params(p.kind, p.index))
                                    for p, r in zip(picked, rec)])
    g = PAIR_VALUES[t]
    if t == "parallelism" and c.towards is not None:
        # The direction into the rig frame with the estimated pose: an
        # error of the pose turns both lines alike, and their tilt not.
        towards = np.asarray(registration.rotation, float) @ np.asarray(c.towards, float)
        g = functools.partial(measured_tilt, towards=towards)
    elif t == "angle":
        g = functools.partial(measured_angle, legs=nominal_legs(c, inventory, registration.rotation))
    try:
        value, u = propagate(_pair_function(g, info, sizes), x, cov)
    except ValueError as e:
        return unmeasured_result(c, f"{t} of the measured features undefined: {e}")
    return measured_result(c, value, u, k, "first order (pose-invariant)")


def _profile_result(c, pf, rec, inventory, rng, k, n_mc, one_scene):
    """A line or circle profile: the fitted feature's departure from nominal plus its form."""
    nominal = inventory[c.features[0]]
    form_fn = straightness if pf.kind == "line" else (circularity if nominal.kind == "circle" else None)
    if pf.kind == "line":
        if pf.start is None:
            return unmeasured_result(c, f"{c.features[0]}: the measured line has no extent")
        s0, s1 = (float((pf.start - pf.point) @ pf.direction), float((pf.end - pf.point) @ pf.direction))
        value, u = line_profile(pf.point, pf.direction, pf.param_cov, s0, s1, nominal.start, nominal.end, rng, n_mc)
    else:
        value, u = circle_profile(pf.center, pf.normal, pf.radius, pf.param_cov, nominal, rng, n_mc)
    details = {"fitted": value}
    points = _form_points(rec)
    if form_fn is not None and points is not None:
        try:
            fr = form_fn(*points, rng, **_simulation(rec, one_scene))
        except FormSimulationError as e:
            return unmeasured_result(c, f"the profile of {c.features[0]} has no uncertainty: its form's noise-only "
                                  f"zone cannot be simulated ({e})")
        value, u = value + fr.value, math.hypot(u, fr.u)
        details.update(form=fr.value, form_raw=fr.raw, noise_bias=fr.noise_bias, n_points=fr.n_points,
                       n_excluded=fr.n_excluded)
    return measured_result(c, value, u, k, "Monte Carlo (JCGM 101), pose covariance included", **details)
