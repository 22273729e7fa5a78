"""Conformity decisions per ISO 14253-1:2017, and the overall verdict.

Rules (``ResolvedSpec.decision_rule``):

``iso14253``
    The measurement result is ``y +- U``. Conformity is proved (*pass*) when
    the whole interval ``[y - U, y + U]`` lies inside the specification zone
    ``[LSL, USL]`` (limits included: the conformance zone is
    ``[LSL + U, USL - U]``); nonconformity is proved (*fail*) when the whole
    interval lies outside it (``y - U > USL`` or ``y + U < LSL``); anything
    else -- the interval straddling a limit, touching it included -- is
    *inconclusive*. Geometrical tolerances (form, position, profile) have an
    upper limit only (``LSL`` None).
``simple``
    Shared risk: the measured value alone decides, ``LSL <= y <= USL``
    passes, anything else fails.

A characteristic that could not be measured is inconclusive under either
rule, with the reason.

The verdict of the part is *fail* if any characteristic fails, else
*inconclusive* if any is inconclusive or none was measured, else *pass*;
exit codes 0 (pass), 1 (fail), 3 (inconclusive), as DESIGN.md specifies.

References
----------
.. [1] ISO 14253-1:2017, GPS -- Inspection by measurement of workpieces and
       measuring equipment -- Part 1: Decision rules for verifying
       conformity or nonconformity with specifications, clauses 5 to 7.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["PASS", "FAIL", "INCONCLUSIVE", "RULES", "EXIT_CODES", "Decision", "decide", "decide_all", "verdict", "exit_code"]

PASS, FAIL, INCONCLUSIVE = "pass", "fail", "inconclusive"
RULES = ("iso14253", "simple")
EXIT_CODES = {PASS: 0, FAIL: 1, INCONCLUSIVE: 3}


@dataclass(frozen=True)
class Decision:
    """The decision on one characteristic.

    Attributes
    ----------
    evaluation : Evaluation
    decision : {"pass", "fail", "inconclusive"}
    rule : {"iso14253", "simple"}
    reason : str
        Why, in words, for the report.
    """

    evaluation: object
    decision: str
    rule: str
    reason: str

    @property
    def id(self):
        return self.evaluation.id

    def to_dict(self):
        d = self.evaluation.to_dict()
        d["decision"] = self.decision
        d["decision_rule"] = self.rule
        d["decision_reason"] = self.reason
        return d


def decide(evaluation, rule="iso14253"):
    """Decide one characteristic.

    Parameters
    ----------
    evaluation : Evaluation
        ``measured``, ``expanded_uncertainty`` and the characteristic's
        ``lower_limit`` / ``upper_limit`` (either may be None: no limit).
    rule : {"iso14253", "simple"}

    Returns
    -------
    Decision
    """
    if rule not in RULES:
        raise ValueError(f"unknown decision rule {rule!r}; expected one of {', '.join(RULES)}")
    c = evaluation.characteristic
    if evaluation.measured is None:
        return Decision(evaluation, INCONCLUSIVE, rule, f"not measured: {evaluation.reason or 'no result'}")
    y = float(evaluation.measured)
    lo, up = c.lower_limit, c.upper_limit
    if rule == "simple":
        ok = (lo is None or y >= lo) and (up is None or y <= up)
        return Decision(evaluation, PASS if ok else FAIL, rule, "measured value within the limits" if ok else "measured value outside the limits")
    U = float(evaluation.expanded_uncertainty)
    if U < 0:
        raise ValueError(f"{c.id}: negative expanded uncertainty {U}")
    if (up is not None and y - U > up) or (lo is not None and y + U < lo):
        return Decision(evaluation, FAIL, rule, "measured value +- U entirely outside the specification zone")
    if (lo is None or y - U >= lo) and (up is None or y + U <= up):
        return Decision(evaluation, PASS, rule, "measured value +- U entirely inside the specification zone")
    return Decision(evaluation, INCONCLUSIVE, rule, "measured value +- U straddles a specification limit")


def decide_all(evaluations, rule="iso14253"):
    """:func:`decide` for each evaluation, in order."""
    return [decide(e, rule) for e in evaluations]


def verdict(decisions):
    """The part's verdict: "fail" if any fails, else "inconclusive" if any is (or none exists), else "pass"."""
    ds = [d.decision for d in decisions]
    if FAIL in ds:
        return FAIL
    if not ds or INCONCLUSIVE in ds:
        return INCONCLUSIVE
    return PASS


def exit_code(decisions_or_verdict):
    """Process exit code: 0 pass, 1 fail, 3 inconclusive."""
    v = decisions_or_verdict if isinstance(decisions_or_verdict, str) else verdict(decisions_or_verdict)
    return EXIT_CODES[v]
