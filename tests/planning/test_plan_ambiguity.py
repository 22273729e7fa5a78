"""The plan says where the pose would be ambiguous, as the run would find it.

Issue 46's flange with a clocking hole underneath: from above, the cameras see a bolt circle of six
like holes, a hub and a bore, all symmetric under turns of 60 degrees; only the unseen hole would
tell which pose is right. ``inspect`` then keeps every tied pose and makes what depends on it
inconclusive (tests/test_ambiguous_pose.py). The plan predicts at a known pose, so it registered
with that pose as hint and never saw the tie: it called the bolt holes' characteristics decidable.
"""

import json
from pathlib import Path

import pytest

from partinspect.cli import main

RIG = Path(__file__).resolve().parents[2] / "examples" / "plate" / "images" / "calibration.yaml"
BOLTS = {f"circle-{k}" for k in (2, 4, 6, 14, 16, 20)}  # the bolt holes' top rims (as the run's test names them)


@pytest.fixture(scope="module")
def plans(tmp_path_factory):
    from partinspect.simulate.parts import flange, write_part

    d = tmp_path_factory.mktemp("plan-ambiguity")
    out = {}
    for name, part in (("clocked", flange(clocking=(5.0, 5.0))), ("symmetric", flange())):
        write_part(part, d / f"{name}.step")
        code = main(["plan", str(d / f"{name}.step"), "--rig", str(RIG), "--no-search", "-o", str(d / name), "-q"])
        out[name] = (code, json.loads((d / name / "plan.json").read_text()), (d / name / "plan.html").read_text())
    return out


def test_a_clocked_flange_plan_names_the_tie_and_what_depends_on_it(plans):
    code, plan, html = plans["clocked"]
    best = plan["best"]
    assert best["ambiguity"].startswith("6 poses (")
    assert "the measured features are symmetric, the CAD model is not" in best["ambiguity"]
    assert "pose ambiguous" in html and best["ambiguity"][:40] in html
    by_id = {c["id"]: c for c in best["characteristics"]}
    dependent = {cid for cid, c in by_id.items() if c["reason"] and c["reason"].startswith("depends on which of 6 poses")}
    # Every bolt hole's measured characteristic depends on the pose, and nothing else does.
    assert dependent == {cid for cid, c in by_id.items() if set(c["features"]) & BOLTS
                         and c["expanded_uncertainty"] is not None}
    assert len(dependent) == 12
    for cid in dependent:
        assert not by_id[cid]["decidable"]
        assert "matched to different measured edges" in by_id[cid]["reason"]
    # The disc's, hub's and bore's rims are the same edges under every pose: as decidable as without the tie.
    assert by_id["circle-9.diameter"]["decidable"] and by_id["circle-11.diameter"]["decidable"]
    assert code == 3 and not plan["all_decidable"]
    json.dumps(plan, allow_nan=False)


def test_a_symmetric_flange_plan_is_not_ambiguous(plans):
    """Where the CAD model itself maps onto itself under the turns, any of the poses is right."""
    code, plan, _ = plans["symmetric"]
    assert plan["best"]["ambiguity"] is None
    assert not [c for c in plan["best"]["characteristics"] if c["reason"] and c["reason"].startswith("depends on")]
