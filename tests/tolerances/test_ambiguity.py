"""Characteristics judged across competing poses: only what does not depend on which is right."""

from types import SimpleNamespace

from partinspect.tolerances.ambiguity import agree, alike, assigned, reconcile
from partinspect.tolerances.decision import decide
from partinspect.tolerances.evaluate import measured_result, unmeasured_result


def _char(cid, features, nominal=8.0, lower=7.9, upper=8.1, unit="mm"):
    return SimpleNamespace(id=cid, features=tuple(features), nominal=nominal, lower_limit=lower, upper_limit=upper,
                           unit=unit, to_dict=lambda: {"id": cid})


# Two poses 180 degrees apart about the plate's centre: the central bore (circle-7) is the same
# measured circle 0 in both, the two side holes (circle-2, circle-10) swap measured circles 1 and 2.
BEST = SimpleNamespace(assignment={"circle": {0: "circle-7", 1: "circle-2", 2: "circle-10"}, "line": {0: "line-3"}})
TURNED = SimpleNamespace(assignment={"circle": {0: "circle-7", 1: "circle-10", 2: "circle-2"}, "line": {0: "line-3"}})
REG = SimpleNamespace(assignment=BEST.assignment,
                      competing=(SimpleNamespace(registration=TURNED, angle=180.0, deciding=("circle-3", "circle-4")),))

BORE = _char("circle-7.diameter", ["circle-7"], 10.0, 9.8, 10.2)
HOLE = _char("circle-2.diameter", ["circle-2"])
BETWEEN = _char("distance(circle-2,circle-10)", ["circle-2", "circle-10"], 56.0, 55.9, 56.1)
POSITION = _char("circle-7.position", ["circle-7"], 0.0, None, 0.3)
EDGE = _char("line-3.straightness", ["line-3"], 0.0, None, 0.05)


def _decided(c, value, U):
    return decide(measured_result(c, value, U / 2, 2.0, "test"))


def test_assignment_per_cad_feature():
    assert assigned(BEST, "circle-2") == {("circle", 1)} and assigned(TURNED, "circle-2") == {("circle", 2)}
    assert assigned(BEST, "circle-3") == frozenset()
    # Only what each pose matches alike needs evaluating under the other.
    assert alike([BORE, HOLE, BETWEEN, POSITION, EDGE], BEST, TURNED) == [BORE, POSITION, EDGE]


def test_agreement_within_the_expanded_uncertainties():
    a = measured_result(POSITION, 0.058, 0.05, 2.0, "")  # U 0.10
    assert agree(a, measured_result(POSITION, 0.12, 0.05, 2.0, ""))  # 0.062 <= sqrt(2) 0.10
    assert not agree(a, measured_result(POSITION, 0.21, 0.05, 2.0, ""))  # 0.152 > 0.141
    assert not agree(a, unmeasured_result(POSITION, "not seen"))
    assert agree(unmeasured_result(POSITION, "not seen"), unmeasured_result(POSITION, "hidden"))


def test_only_what_depends_on_the_pose_is_inconclusive():
    best = [_decided(BORE, 10.01, 0.03), _decided(HOLE, 8.01, 0.04), _decided(BETWEEN, 56.01, 0.07),
            _decided(POSITION, 0.058, 0.10), _decided(EDGE, 0.01, 0.02)]
    assert [d.decision for d in best] == ["pass"] * 5
    # Under the turned pose: the bore and the edge the same; the bore's position moved within
    # its uncertainty for one run, beyond it (with another decision) for another.
    turned = {d.id: d for d in [_decided(BORE, 10.01, 0.03), _decided(EDGE, 0.01, 0.02),
                                _decided(POSITION, 0.09, 0.10)]}
    out = reconcile(best, REG, [turned])
    assert [d.decision for d in out] == ["pass", "inconclusive", "inconclusive", "pass", "pass"]
    assert out[0] is best[0] and out[3] is best[3]
    hole, between = out[1], out[2]
    assert hole.reason.startswith("depends on which of 2 poses 180.0 degrees apart is right: the measured features "
                                  "are symmetric, the CAD model is not (circle-3, circle-4, which would tell, were "
                                  "not measured); circle-2 is matched to different measured edges in them")
    assert between.reason.endswith("circle-2, circle-10 are matched to different measured edges in them")
    # The best pose's value is kept, the other pose's (not evaluated: it depends anyway) beside it.
    assert hole.evaluation.measured == 8.01
    assert hole.evaluation.details["ambiguity"] == [
        {"measured": 8.01, "expanded_uncertainty": 0.04, "decision": "pass"}, None]

    moved = {**turned, POSITION.id: _decided(POSITION, 0.45, 0.10)}
    out = reconcile(best, REG, [moved])
    assert out[3].decision == "inconclusive" and out[3].reason.endswith("the decision differs: pass vs fail")
    far = {**turned, POSITION.id: _decided(POSITION, 0.19, 0.02)}  # 0.132 > sqrt(0.10^2 + 0.02^2)
    out = reconcile(best, REG, [far])
    assert out[3].decision == "inconclusive" and out[3].reason.endswith("its value differs beyond the uncertainty")
    assert [p["measured"] for p in out[3].evaluation.details["ambiguity"]] == [0.058, 0.19]


def test_an_unambiguous_registration_changes_nothing():
    best = [_decided(HOLE, 8.01, 0.04)]
    assert reconcile(best, SimpleNamespace(assignment=BEST.assignment, competing=()), []) == best
