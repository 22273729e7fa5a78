"""Datum shift: a pattern located from datum features of size at MMB or LMB.

A position tolerance whose datum reference frame names a datum feature of
size at its maximum (or least) material boundary, ``| A | B(M) | C(M)``,
locates its features from datum feature simulators of the boundary's size,
not from the datum features' own axes. A hole B larger than its MMB (a boss
smaller) leaves the simulator loose in it: the toleranced features, as one
group, may shift relative to the datum reference frame within that
looseness, and rotate where a second datum feature of size leaves room
(ASME Y14.5-2018 4.11.9 and 7.17 "datum feature shift"; ISO 2692's
reciprocity, ISO 5459's datum systems). The same frame holds every feature
the tolerance applies to: they are one simultaneous requirement.

The frame's freedom, in the plane normal to the pattern's axes, with the
datum features' measured centres ``m_j`` (part frame) and nominal ones
``n_j``:

- the first datum feature of size *locates*: the frame's origin there, the
  simulator's centre ``n_0 + s``, stays within ``rho_0`` of ``m_0``,
  ``|m_0 - n_0 - s| <= rho_0``;
- a second one *clocks*: its simulator, carried round the first by the
  frame's rotation ``theta``, stays within ``rho_1`` of ``m_1`` across the
  line joining the two (ISO 5459: a tertiary datum takes only the degrees of
  freedom left, here the rotation about the primary's normal);
- without a second one the rotation is free when the DRF ends at the first
  feature of size (``| A | B(M) |``), and held (the alignment's) when a
  further datum that is no feature of size clocks it.

The allowance ``rho_j`` is half the datum feature's departure from its
boundary, from its measured size ``d``: ``(d - d_MMB) / 2`` for a hole at
MMB, ``(d_MMB - d) / 2`` for a boss, the reverse at LMB; the boundary is the
datum feature's MMC (LMC) size. A datum feature's tolerance of orientation or
location to the datums before it would enlarge the boundary's virtual
condition and with it the shift; it is not added, so the shift allowed is
never more than the drawing's. A datum feature beyond its boundary (a hole
below its MMB size) allows no shift: ``rho = 0``.

The value of each feature is its position (minus its own MMC/LMC bonus) at
the frame placement that minimises the pattern's worst excess over its
tolerance, ``max_i (2 |c_i - g(n_i)| - bonus_i - t_i)``, a convex problem
solved by SLSQP from the datum features' own axes (the frame without a
shift, always allowed), so the shift never makes a value worse than
without it.

Uncertainty: the optimum is a non-smooth function of every measured input
(the pattern's centres and bonuses, the datum features' centres and sizes,
hence the allowances), so it is propagated by Monte Carlo (JCGM 101): the
inputs drawn from their joint normal distribution, the optimum found again
for each draw, and ``u`` the root mean square of the drawn optima about
the value they are drawn at. As for one position, the measured offsets of a
norm near zero are biased up by the noise: the draws are taken about the
pattern's centres with each offset from its shifted place shrunk to zero
unless it is significant (:func:`shrunk_centres`), a parametric bootstrap
of the estimator's error rather than its spread about itself. The allowance's own uncertainty (half the datum size's)
is carried that way, and the decision's guard band covers it.

References
----------
.. [1] ASME Y14.5-2018, Dimensioning and Tolerancing, 4.11.9, 7.11.3
       (datum feature simulator at MMB/LMB), 7.17 (datum feature shift),
       7.19 (simultaneous requirements).
.. [2] ISO 5459:2011, Geometrical tolerancing -- Datums and datum systems.
.. [3] ISO 2692:2021, Maximum material requirement (MMR), least material
       requirement (LMR) and reciprocity requirement (RPR).
.. [4] JCGM 101:2008, GUM Supplement 1: propagation of distributions by a
       Monte Carlo method.
.. [5] D. Kraft, "A software package for sequential quadratic
       programming", DFVLR-FB 88-28, 1988 (SLSQP).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from partinspect.tolerances.material import bonus_sign, reference_size

__all__ = ["BOUNDARIES", "DatumRef", "ShiftResult", "parse_datum", "allowance", "plane_basis", "best_shift",
           "shift_monte_carlo", "shrunk_centres"]

BOUNDARIES = {"M": "MMB", "L": "LMB"}
_DATUM_RE = re.compile(r"^([A-Z][A-Z0-9]*)(?:\((M|L)\))?$")
# |r| smoothed at zero for the solver's gradients (by 1e-5 mm at most), mm^2.
_EPS2 = 1e-10
# A constraint violated by less than this is met, mm.
_FEASIBLE = 1e-9


def parse_datum(text):
    """``"B(M)"`` -> ``("B", "MMB")``, ``"A"`` -> ``("A", None)``; ValueError otherwise."""
    m = _DATUM_RE.match(str(text).strip())
    if m is None:
        raise ValueError(f"expected a datum letter with an optional (M) or (L), e.g. B(M), got {text!r}")
    return m.group(1), BOUNDARIES.get(m.group(2))


@dataclass(frozen=True)
class DatumRef:
    """One datum of a position's datum reference frame.

    Attributes
    ----------
    letter : str
    boundary : {"MMB", "LMB"} or None
        The material boundary it is referenced at; None: regardless of
        feature size (RFS).
    features : tuple of str
        Its CAD feature ids (rims of a datum hole or boss, lines of a
        datum plane); empty when the spec does not say.
    sizes : tuple of Characteristic
        A datum feature of size: the size characteristics of its rims,
        each rim's centre and size measure it (empty until resolved, or
        not a feature of size).
    internal : bool or None
        A hole (True) or a boss (False); None if not a feature of size.
    """

    letter: str
    boundary: str | None = None
    features: tuple = ()
    sizes: tuple = ()
    internal: bool | None = None

    @property
    def label(self):
        """As the drawing writes it: ``"B(M)"``."""
        return self.letter + {"MMB": "(M)", "LMB": "(L)"}.get(self.boundary, "")

    @property
    def of_size(self):
        """True for a datum feature of size (a hole or a boss) whose sizes are known."""
        return bool(self.sizes) and self.internal is not None

    def reference(self, size):
        """The boundary's diameter from one rim's size characteristic, mm (None at RFS)."""
        if self.boundary is None:
            return None
        return reference_size("MMC" if self.boundary == "MMB" else "LMC", self.internal, size.lower_limit,
                              size.upper_limit, 2.0 if size.type == "radius" else 1.0)

    def to_dict(self):
        """report.json's ``datum_reference`` entry."""
        out = {"datum": self.letter}
        if self.boundary:
            out["boundary"] = self.boundary
        if self.features:
            out["features"] = list(self.features)
        if self.of_size:
            out["feature_of_size"] = "hole" if self.internal else "boss"
            if self.boundary is not None:
                out["boundary_size"] = round(float(self.reference(self.sizes[0])), 12)
        return out


def allowance(boundary, internal, size, u_size, reference):
    """How far a datum feature of size lets its simulator move: ``(rho, u_rho)``, mm.

    Parameters
    ----------
    boundary : {"MMB", "LMB"} or None
        None (RFS) allows nothing.
    internal : bool
        A hole or a boss.
    size, u_size : float or ndarray
        Measured diameter and its standard uncertainty, mm.
    reference : float
        The boundary's diameter, mm.

    Returns
    -------
    rho, u_rho : float or ndarray
        Half the departure from the boundary, clipped at zero (a feature
        beyond its boundary allows no shift), and its standard uncertainty
        (half the size's, zero where clipped).
    """
    if boundary is None:
        return np.zeros_like(np.asarray(size, float)) + 0.0, 0.0 * np.asarray(u_size, float)
    s = bonus_sign("MMC" if boundary == "MMB" else "LMC", internal)
    departure = s * (np.asarray(size, float) - float(reference))
    return np.maximum(departure, 0.0) / 2.0, np.where(departure > 0, np.asarray(u_size, float) / 2.0, 0.0)


def plane_basis(normal):
    """Two orthonormal vectors spanning the plane normal to ``normal``, shape (2, 3)."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.array([e1, np.cross(n, e1)])


@dataclass(frozen=True)
class ShiftResult:
    """The pattern's values at its best allowed frame placement.

    Attributes
    ----------
    values : ndarray, shape (n,)
        Each feature's position minus its bonus at that placement, mm.
    positions : ndarray, shape (n,)
        Their positions (``2 |c_i - g(n_i)|``), mm.
    unshifted : ndarray, shape (n,)
        The values with the frame on the datum features' own axes, mm.
    translation : ndarray, shape (2,)
        The frame's shift from the first datum feature's own axis, mm.
    rotation : float
        Its rotation from the placement without a shift, rad.
    residuals : ndarray, shape (n, 2)
        Each measured centre's offset from its place in the shifted frame, mm.
    """

    values: np.ndarray
    positions: np.ndarray
    unshifted: np.ndarray
    translation: np.ndarray
    rotation: float
    residuals: np.ndarray


def _rot(theta):
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


class _Placement:
    """The datum reference frame placed within its shift, as a function of x.

    ``x = (a, b, w)``: the first datum feature's axis moved by ``rho_0 (a,
    b)`` (|(a, b)| <= 1), and the frame turned by ``w / reach`` rad about it.
    The rotation as an arc length over the pattern's reach keeps the
    solver's variables alike in scale (mm). Shapes and frames as
    :func:`best_shift`'s arguments.
    """

    def __init__(self, P, C, D, M, rho, rotation):
        self.P, self.C, self.D, self.rho, self.rotation = P, C, D, rho, rotation
        self.M1 = M[1] if len(M) > 1 else None
        self.s0 = M[0] - D[0]  # the simulator on the first datum feature's own axis
        self.theta0, self.v = 0.0, None
        if rotation == "clocked":
            L = float(np.linalg.norm(D[1] - D[0]))
            self.v = np.array([-(D[1] - D[0])[1], (D[1] - D[0])[0]]) / L
            self.theta0 = math.asin(max(-1.0, min(1.0, float(self.v @ (M[1] - D[0] - self.s0)) / L)))
        self.reach = max(float(np.max(np.linalg.norm(np.r_[P, D] - D[0], axis=1))), 1.0)
        self.turns = rotation != "fixed"

    def theta(self, x):
        return self.theta0 + (x[2] / self.reach if self.turns else 0.0)

    def frame(self, x):
        return self.D[0] + self.s0 + self.rho[0] * x[:2], _rot(self.theta(x))

    def residuals(self, x):
        """Each centre's offset from its true position in the placed frame, its smoothed length, the arms."""
        origin, R = self.frame(x)
        arms = (self.P - self.D[0]) @ R.T
        r = self.C - (origin + arms)
        return r, np.sqrt(np.einsum("ij,ij->i", r, r) + _EPS2), arms

    def excess_jac(self, y):
        """d/dy of z - (2 |r_i| - b_i - t_i), y = (a, b, w, z)."""
        r, norm, arms = self.residuals(y[:3])
        u = r / norm[:, None]
        out = np.empty((len(r), 4))
        out[:, :2] = 2.0 * self.rho[0] * u
        out[:, 2] = 2.0 * (u[:, 0] * -arms[:, 1] + u[:, 1] * arms[:, 0]) / self.reach if self.turns else 0.0
        out[:, 3] = 1.0
        return out

    def clock(self, x):
        """The second datum feature's offset across its clocking direction from the placed frame, mm."""
        origin, R = self.frame(x)
        return float(self.v @ (self.M1 - origin - R @ (self.D[1] - self.D[0])))

    def clock_jac(self, y):
        _, R = self.frame(y[:3])
        arm = R @ (self.D[1] - self.D[0])
        return np.r_[-self.rho[0] * self.v, -float(self.v @ np.array([-arm[1], arm[0]])) / self.reach, 0.0]


def _constraints(place, values, t):
    """SLSQP's constraints on y = (a, b, w, z): every excess under z, the shift on its disc, the clocking held."""
    cons = [{"type": "ineq", "fun": lambda y: y[3] - (values(y[:3]) - t), "jac": place.excess_jac},
            {"type": "ineq", "fun": lambda y: 1.0 - y[0] ** 2 - y[1] ** 2,
             "jac": lambda y: np.array([-2.0 * y[0], -2.0 * y[1], 0.0, 0.0])}]
    rho = place.rho
    if place.rotation == "clocked" and rho[1] > 0:
        cons += [{"type": "ineq", "fun": lambda y: rho[1] - place.clock(y[:3]), "jac": lambda y: -place.clock_jac(y)},
                 {"type": "ineq", "fun": lambda y: rho[1] + place.clock(y[:3]), "jac": place.clock_jac}]
    elif place.rotation == "clocked":
        cons.append({"type": "eq", "fun": lambda y: place.clock(y[:3]), "jac": place.clock_jac})
    return cons


def best_shift(nominal, measured, bonus, tolerance, datum_nominal, datum_measured, rho, rotation="clocked"):
    """The frame placement within the datum shift that fits the pattern best.

    The placement minimises the largest excess of a feature's position
    value over its tolerance (a minimax, solved as SLSQP over the placement
    and a bound z on the excesses), within the first datum feature's
    allowance and, clocked, the second's. A placement that does not improve
    on the unshifted frame is not taken.

    Parameters
    ----------
    nominal, measured : ndarray, shape (n, 2)
        The pattern's true positions and measured centres, in the plane
        normal to its axes (:func:`plane_basis` coordinates), mm.
    bonus, tolerance : ndarray, shape (n,)
        Each feature's own MMC/LMC bonus (0 without) and position
        tolerance, mm.
    datum_nominal, datum_measured : ndarray, shape (m, 2)
        The datum features of size, locating first (m = 1 or 2), mm.
    rho : ndarray, shape (m,)
        Their allowances (:func:`allowance`), mm.
    rotation : {"clocked", "free", "fixed"}
        ``clocked`` by the second datum feature (m = 2), ``free`` about the
        first (nothing clocks the frame), ``fixed`` (a datum that is no
        feature of size clocks it, as aligned).

    Returns
    -------
    ShiftResult
    """
    b, t = np.asarray(bonus, float), np.asarray(tolerance, float)
    rho = np.asarray(rho, float)
    place = _Placement(np.asarray(nominal, float), np.asarray(measured, float), np.asarray(datum_nominal, float),
                       np.asarray(datum_measured, float), rho, rotation)

    def values(x):
        return 2.0 * place.residuals(x)[1] - b

    x0 = np.zeros(3)
    z0 = float(np.max(values(x0) - t))
    best = x0
    if rho[0] > 0 or (rotation == "clocked" and rho[1] > 0) or rotation == "free":
        res = minimize(lambda y: y[3], np.r_[x0, z0], jac=lambda y: np.array([0.0, 0.0, 0.0, 1.0]), method="SLSQP",
                       constraints=_constraints(place, values, t), options={"ftol": 1e-10, "maxiter": 100})
        y = res.x[:3].copy()
        y[:2] /= max(1.0, float(np.hypot(y[0], y[1])))  # on the disc, not a rounding outside it
        held = rotation != "clocked" or abs(place.clock(y)) <= rho[1] + _FEASIBLE
        if held and np.max(values(y) - t) < z0:
            best = y
    r = place.residuals(best)[0]
    norm = np.linalg.norm(r, axis=1)  # the smoothing was for the solver only
    return ShiftResult(2.0 * norm - b, 2.0 * norm, 2.0 * np.linalg.norm(place.residuals(x0)[0], axis=1) - b,
                       rho[0] * best[:2], float(place.theta(best) - place.theta0), r)


def shift_monte_carlo(x, cov, unpack, rng, n, at=None):
    """Monte Carlo (JCGM 101) standard uncertainty of every value :func:`best_shift` gives.

    Parameters
    ----------
    x : ndarray, shape (p,)
        The measured inputs stacked (centres, sizes, ...).
    cov : ndarray, shape (p, p)
        Their joint covariance.
    unpack : callable, (p,) -> ShiftResult
        Solves the problem for one input vector.
    rng : numpy.random.Generator
    n : int
        Draws.
    at : ndarray, shape (p,), optional
        The inputs to simulate the estimator's error at (default ``x``):
        a parametric bootstrap, as :func:`~partinspect.tolerances.evaluate.true_position`
        does for one position, where the measured inputs themselves are a
        biased place to draw about (:func:`shrunk_centres`).

    Returns
    -------
    result : ShiftResult
        At the measured inputs.
    u : ndarray, shape (k,)
        Root mean square of each drawn value about its value at ``at``:
        the estimator's spread and its bias together (a norm near zero,
        minimised over the frame's freedom, is biased by noise).
    """
    result = unpack(np.asarray(x, float))
    at = np.asarray(x if at is None else at, float)
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    draws = at + rng.standard_normal((n, len(at))) @ (V * np.sqrt(np.clip(w, 0, None))).T
    drawn = np.array([unpack(d).values for d in draws])
    return result, np.sqrt(np.mean((drawn - unpack(at).values) ** 2, axis=0))


def shrunk_centres(residuals, plane_covs, factor=3.0):
    """Each residual offset shrunk towards zero unless it is significant, shape (n, 2).

    ``|mu|^2 = max(0, |r|^2 - factor tr(cov))``: the same shrinkage
    :func:`~partinspect.tolerances.evaluate.true_position` simulates a
    position at (an offset is taken as zero unless it stands out of its
    noise); the pattern's centres moved to their places plus ``mu`` are
    where the datum shift's error is simulated.

    Parameters
    ----------
    residuals : ndarray, shape (n, 2)
        :attr:`ShiftResult.residuals`, mm.
    plane_covs : ndarray, shape (n, 2, 2)
        The centres' covariances in the plane, mm^2.
    factor : float
    """
    r = np.asarray(residuals, float)
    rr = np.einsum("ij,ij->i", r, r)
    excess = rr - factor * np.trace(np.asarray(plane_covs, float), axis1=1, axis2=2)
    scale = np.sqrt(np.where(rr > 0, np.maximum(excess, 0.0) / np.where(rr > 0, rr, 1.0), 0.0))
    return r * scale[:, None]
