"""Characteristics judged across poses that explain the measured features equally well.

Where the measured features are symmetric and the CAD model is not (the
feature that would tell the poses apart, a clocking hole, not measured),
registration keeps every such pose
(:attr:`~partinspect.cad.registration.Registration.competing`). Which one
is right is unknown, so a characteristic is judged only where the answer
does not depend on it: under every pose

- the same measured features are assigned to each of its CAD features (a
  hole's diameter is that hole's only if the hole is the same one),
- the decision is the same, and
- the values agree within their uncertainty: ``|y_a - y_b|`` no larger
  than ``sqrt(U_a^2 + U_b^2)``, the normalised error ``E_n <= 1`` of
  ISO 13528 (a characteristic measured under one pose and not under
  another does not agree).

Otherwise it is inconclusive, its reason naming the poses, the features
that would tell, and what differs; its value stays the best fitting
pose's, the others' beside it in ``details``. Being the same decision under
each candidate, the judged ones are right whichever pose is.

References
----------
.. [1] ISO 13528:2022, Statistical methods for use in proficiency testing
       by interlaboratory comparison, 9.7 (E_n numbers).
.. [2] ISO 14253-1:2017, 5 to 7: a result that cannot prove conformity or
       nonconformity is inconclusive.
"""

from __future__ import annotations

import math
from dataclasses import replace

from partinspect.tolerances.decision import INCONCLUSIVE

__all__ = ["assigned", "alike", "agree", "reconcile", "pose_words", "depends_on_words", "dependence"]


def assigned(registration, cad_id):
    """The measured features a registration assigns to a CAD feature: frozenset of ``(kind, index)``."""
    return frozenset((kind, i) for kind, table in registration.assignment.items()
                     for i, fid in table.items() if fid == cad_id)


def _differing(c, registration, rival):
    """The characteristic's CAD ids whose measured features differ between two registrations."""
    return [fid for fid in c.features if assigned(registration, fid) != assigned(rival, fid)]


def alike(characteristics, registration, rival):
    """The characteristics whose CAD features have the same measured features under both registrations.

    Only these need evaluating under ``rival``: the others are inconclusive
    whatever their values.
    """
    return [c for c in characteristics if not _differing(c, registration, rival)]


def agree(a, b):
    """Whether two evaluations of one characteristic agree within their uncertainty (E_n <= 1).

    Parameters
    ----------
    a, b : Evaluation
        ``measured`` (None if not measured) and ``expanded_uncertainty``.

    Returns
    -------
    bool
        True when neither was measured, or both were and
        ``|a - b| <= sqrt(U_a^2 + U_b^2)``.
    """
    if a.measured is None or b.measured is None:
        return a.measured is None and b.measured is None
    return abs(a.measured - b.measured) <= math.hypot(a.expanded_uncertainty, b.expanded_uncertainty)


def pose_words(registration):
    """"which of 2 poses 180.0 degrees apart" and the like, for a registration with competing poses."""
    angles = ", ".join(f"{c.angle:.1f}" for c in registration.competing)
    n = len(registration.competing) + 1
    return (f"which of 2 poses {angles} degrees apart" if n == 2
            else f"which of {n} poses ({angles} degrees from the best fitting)")


def _deciding(registration):
    ids = []
    for c in registration.competing:
        ids += [fid for fid in c.deciding if fid not in ids]
    return ids


def depends_on_words(registration):
    """The head of the reason of a characteristic that depends on which competing pose is right."""
    deciding = _deciding(registration)
    tell = (f" ({', '.join(deciding)}, which would tell, {'was' if len(deciding) == 1 else 'were'} not measured)"
            if deciding else "")
    return (f"depends on {pose_words(registration)} is right: the measured features are symmetric, "
            f"the CAD model is not{tell}")


def dependence(c, evaluation, registration, rival_evaluations):
    """What makes a characteristic depend on the pose, as :func:`reconcile` judges it, without decisions.

    For the plan, which predicts uncertainties and makes no decisions: the
    test is :func:`reconcile`'s but for the decision's (the value's
    agreement within E_n <= 1 stands for it).

    Parameters
    ----------
    c : Characteristic
    evaluation : Evaluation
        Under ``registration``.
    registration : Registration
        With ``competing`` poses.
    rival_evaluations : list
        One per competing pose: the characteristic's Evaluation under it,
        or None where it was not evaluated.

    Returns
    -------
    str or None
        None when the characteristic is the same under every pose; else
        what differs, in words.
    """
    differing = []
    for rival in registration.competing:
        differing += [fid for fid in _differing(c, registration, rival.registration) if fid not in differing]
    if differing:
        return f"{', '.join(differing)} {'is' if len(differing) == 1 else 'are'} matched to different measured edges in them"
    if all(o is not None and agree(o, evaluation) for o in rival_evaluations):
        return None
    return "its value differs beyond the uncertainty"


def reconcile(decisions, registration, rival_decisions):
    """The decisions under the best pose, made inconclusive where a competing pose would decide otherwise.

    Parameters
    ----------
    decisions : list of Decision
        Under ``registration`` (the best fitting pose), one per characteristic.
    registration : Registration
        With ``competing`` poses (each a ``registration``, an ``angle`` in
        degrees and the ``deciding`` CAD ids).
    rival_decisions : list of dict
        One per competing pose, in its order: characteristic id ->
        Decision under that pose, for (at least) the characteristics
        :func:`alike` keeps.

    Returns
    -------
    list of Decision
        Same order. A characteristic judged differently (module notes)
        becomes inconclusive: its evaluation keeps the best pose's value,
        ``details["ambiguity"]`` holds each pose's value, expanded
        uncertainty and decision (degrees for angles), and the reason says
        what it depends on.
    """
    if not registration.competing:
        return list(decisions)
    head = depends_on_words(registration)
    out = []
    for d in decisions:
        c = d.evaluation.characteristic
        differing, others = [], []
        for rival, table in zip(registration.competing, rival_decisions):
            differing += [fid for fid in _differing(c, registration, rival.registration) if fid not in differing]
            others.append(table.get(c.id))
        if not differing and all(o is not None and o.decision == d.decision and agree(o.evaluation, d.evaluation)
                                 for o in others):
            out.append(d)
            continue
        if differing:
            what = f"{', '.join(differing)} {'is' if len(differing) == 1 else 'are'} matched to different measured edges in them"
        elif any(o.decision != d.decision for o in others):
            what = "the decision differs: " + " vs ".join(x.decision for x in [d, *others])
        else:
            what = "its value differs beyond the uncertainty"
        ev = replace(d.evaluation, details={**d.evaluation.details, "ambiguity": _per_pose(c, [d, *others])})
        out.append(replace(d, evaluation=ev, decision=INCONCLUSIVE, reason=f"{head}; {what}"))
    return out


def _per_pose(c, decisions):
    """Each pose's value, expanded uncertainty and decision (None where it was not evaluated), report units."""
    conv = math.degrees if c.unit == "rad" else float

    def num(v):
        return None if v is None else round(conv(v), 12)

    return [{"measured": num(x.evaluation.measured), "expanded_uncertainty": num(x.evaluation.expanded_uncertainty),
             "decision": x.decision} if x is not None else None for x in decisions]
