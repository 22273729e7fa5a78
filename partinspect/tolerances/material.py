"""Material condition modifiers of a position tolerance: the bonus from the feature's size.

A position tolerance at maximum material (MMC, ISO 2692 (M)) or least
material (LMC, (L)) grows by the feature's departure from that size: the
requirement is the virtual condition boundary, ``position <= t + bonus``
with

=========  ===========================  ===========================
modifier   hole (internal feature)      boss, shaft (external)
=========  ===========================  ===========================
MMC        ``bonus = d - d_MMC``        ``bonus = d_MMC - d``
LMC        ``bonus = d_LMC - d``        ``bonus = d - d_LMC``
=========  ===========================  ===========================

``d`` is the measured diameter, ``d_MMC`` the smallest size a hole may have
(the largest for a boss), ``d_LMC`` the other limit. The bonus is not
clipped at zero: a hole smaller than its MMC size makes the position check
stricter, which is the virtual condition boundary's own statement (and the
size itself then fails its own limits).

The conformance test is on one measured quantity,

    q = position - bonus(d) <= t,

decided with the same ISO 14253-1 guard band as every other characteristic
(:mod:`.decision`). ``q`` is linear in the position and the size, so its
standard uncertainty follows the GUM law of propagation exactly for the
pair:

    u(q)^2 = u(position)^2 + u(d)^2 - 2 s cov(position, d),

``s = +1`` where the bonus grows with ``d`` (hole at MMC, boss at LMC),
``-1`` otherwise. Position and diameter come from the same circle fit, so
their covariance is the fit's centre-radius covariance carried through the
position's gradient ``d position / d centre = 2 P m / |P m|``, ``m`` the
in-plane offset (at the bias-corrected offset :func:`.evaluate.true_position`
simulates at; zero there when the offset is not significant, where by
symmetry the position and the centre's error are uncorrelated).

References
----------
.. [1] ISO 2692:2021, Geometrical product specifications (GPS) --
       Geometrical tolerancing -- Maximum material requirement (MMR), least
       material requirement (LMR) and reciprocity requirement (RPR).
.. [2] ASME Y14.5-2018, Dimensioning and Tolerancing, 5.8 (bonus
       tolerance), 7.3.3 (virtual condition).
.. [3] JCGM 100:2008 (GUM), 5.2.2 (correlated input quantities).
.. [4] ISO 14253-1:2017, decision rules (:mod:`.decision`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MODIFIERS", "MaterialCondition", "bonus_sign", "reference_size", "position_with_bonus"]

MODIFIERS = ("MMC", "LMC")


@dataclass(frozen=True)
class MaterialCondition:
    """A position tolerance's material modifier and the size its bonus is taken from.

    Attributes
    ----------
    modifier : {"MMC", "LMC"}
    internal : bool or None
        True for a hole, False for a boss or shaft; None until resolved.
    size : Characteristic or None
        The feature's size characteristic (diameter or radius, with its
        limits and edge break) whose measured value gives the bonus; None
        until resolved.
    """

    modifier: str
    internal: bool | None = None
    size: object = None

    @property
    def reference(self):
        """The diameter at the modifier's condition, mm (None until resolved)."""
        if self.size is None or self.internal is None:
            return None
        return reference_size(self.modifier, self.internal, self.size.lower_limit, self.size.upper_limit,
                              2.0 if self.size.type == "radius" else 1.0)

    def to_dict(self):
        """The report.json ``material`` entry."""
        out = {"modifier": self.modifier}
        if self.internal is not None:
            out["feature"] = "hole" if self.internal else "boss"
        if self.size is not None:
            out["size"] = self.size.id
            out["reference_size"] = round(float(self.reference), 12)
        return out


def bonus_sign(modifier, internal):
    """+1 where the bonus grows with the diameter (hole at MMC, boss at LMC), else -1."""
    if modifier not in MODIFIERS:
        raise ValueError(f"unknown material modifier {modifier!r}; expected one of {', '.join(MODIFIERS)}")
    return 1.0 if (modifier == "MMC") == bool(internal) else -1.0


def reference_size(modifier, internal, lower, upper, scale=1.0):
    """The diameter at MMC or LMC from a size's limits, mm.

    Parameters
    ----------
    modifier : {"MMC", "LMC"}
    internal : bool
        A hole (its MMC is its smallest size) or a boss (its largest).
    lower, upper : float
        The size's limits (diameter, or radius with ``scale`` 2).
    scale : float
        2 for radius limits.
    """
    # The bonus grows with d exactly where d's reference is its lower limit.
    return scale * float(lower if bonus_sign(modifier, internal) > 0 else upper)


def position_with_bonus(position, u_position, gradient, size, u_size, cov_center_size, modifier, internal,
                        reference):
    """The quantity ``q = position - bonus(d)`` and its standard uncertainty.

    Parameters
    ----------
    position, u_position : float
        Measured position (diameter of the centre's offset, mm) and its
        standard uncertainty.
    gradient : ndarray, shape (3,)
        ``d position / d centre`` (part frame), mm/mm.
    size, u_size : float
        Measured diameter and its standard uncertainty, mm.
    cov_center_size : ndarray, shape (3,)
        Covariance of the centre with the measured diameter, mm^2 (the
        fit's centre-radius covariance, times 2).
    modifier : {"MMC", "LMC"}
    internal : bool
    reference : float
        Diameter at the modifier's condition, mm.

    Returns
    -------
    q, u_q, bonus, u_bonus, correlation : float
        ``correlation`` is that of the position with the bonus (the
        covariance term's share), clipped to [-1, 1].
    """
    s = bonus_sign(modifier, internal)
    bonus = s * (float(size) - float(reference))
    u_bonus = abs(s) * float(u_size)
    cov_pb = s * float(np.asarray(gradient, float) @ np.asarray(cov_center_size, float))
    denom = float(u_position) * u_bonus
    rho = max(-1.0, min(1.0, cov_pb / denom)) if denom > 0 else 0.0
    var = u_position**2 + u_bonus**2 - 2.0 * rho * denom
    return float(position) - bonus, math.sqrt(max(var, 0.0)), bonus, u_bonus, rho
