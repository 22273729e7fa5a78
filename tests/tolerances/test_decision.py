"""ISO 14253-1 decisions at and around the zone boundaries, and the verdict."""

import pytest

from partinspect.tolerances.decision import FAIL, INCONCLUSIVE, PASS, decide, decide_all, exit_code, verdict
from partinspect.tolerances.evaluate import Evaluation
from partinspect.tolerances.resolve import Characteristic

SIZE = Characteristic("circle-1.diameter", "diameter", ("circle-1",), 10.0, 9.5, 10.5, "spec")
FORM = Characteristic("line-1.straightness", "straightness", ("line-1",), 0.0, None, 1.0, "spec")


def ev(c, y, U):
    return Evaluation(c, y, y - c.nominal, U / 2, U)


# binary-exact numbers so the boundaries are hit exactly
@pytest.mark.parametrize(
    "y, U, expected",
    [
        (10.0, 0.25, PASS),
        (10.25, 0.25, PASS),  # y + U == USL: inside (limits belong to the zone)
        (10.25 + 2**-20, 0.25, INCONCLUSIVE),
        (10.5, 0.25, INCONCLUSIVE),  # on the limit
        (10.75, 0.25, INCONCLUSIVE),  # y - U == USL: touches, not entirely outside
        (10.75 + 2**-20, 0.25, FAIL),
        (9.75, 0.25, PASS),  # y - U == LSL
        (9.75 - 2**-20, 0.25, INCONCLUSIVE),
        (9.25, 0.25, INCONCLUSIVE),
        (9.25 - 2**-20, 0.25, FAIL),
        (10.0, 0.0, PASS),
        (10.5, 0.0, PASS),
        (10.0, 0.75, INCONCLUSIVE),  # U wider than half the zone: conformity never provable
    ],
)
def test_iso14253_two_sided(y, U, expected):
    assert decide(ev(SIZE, y, U), "iso14253").decision == expected


@pytest.mark.parametrize(
    "y, U, expected",
    [
        (0.0, 0.25, PASS),
        (-0.25, 0.25, PASS),  # a noise-corrected form below zero: no lower limit
        (0.75, 0.25, PASS),
        (0.75 + 2**-20, 0.25, INCONCLUSIVE),
        (1.25, 0.25, INCONCLUSIVE),
        (1.25 + 2**-20, 0.25, FAIL),
    ],
)
def test_iso14253_upper_only(y, U, expected):
    assert decide(ev(FORM, y, U), "iso14253").decision == expected


@pytest.mark.parametrize("y, expected", [(10.5, PASS), (10.5 + 2**-20, FAIL), (9.5, PASS), (9.5 - 2**-20, FAIL), (10.4, PASS)])
def test_simple_rule_ignores_uncertainty(y, expected):
    assert decide(ev(SIZE, y, 5.0), "simple").decision == expected


def test_unmeasured_is_inconclusive_with_reason():
    e = Evaluation(SIZE, None, None, None, None, reason="circle-1 not measured")
    for rule in ("iso14253", "simple"):
        d = decide(e, rule)
        assert d.decision == INCONCLUSIVE and "circle-1 not measured" in d.reason


def test_unknown_rule():
    with pytest.raises(ValueError):
        decide(ev(SIZE, 10.0, 0.1), "guess")


def test_verdict_and_exit_codes():
    p, i, f = ev(SIZE, 10.0, 0.1), ev(SIZE, 10.5, 0.1), ev(SIZE, 11.0, 0.1)
    assert verdict(decide_all([p, p])) == PASS and exit_code(decide_all([p, p])) == 0
    assert verdict(decide_all([p, i])) == INCONCLUSIVE and exit_code(decide_all([p, i])) == 3
    assert verdict(decide_all([p, i, f])) == FAIL and exit_code(decide_all([i, f])) == 1
    assert verdict([]) == INCONCLUSIVE
    assert exit_code("pass") == 0
    assert decide(p).to_dict()["decision"] == PASS
