"""Several views: the fewest turns of the part that decide its characteristics."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from partinspect.cli import main
from partinspect.planning.views import fewest_views, fused_choice, view_candidates
from tests.planning.conftest import REPO, SIZE

PLATE = REPO / "examples" / "plate" / "part.step"


def _pose(decides, n=6, registration_error=None):
    chars = [SimpleNamespace(id=f"c{k}", decidable=k in decides, U=1.0 if k in decides else np.inf,
                             characteristic=SimpleNamespace(source="spec")) for k in range(n)]
    return SimpleNamespace(characteristics=chars, registration_error=registration_error,
                           score=lambda: (len(decides), len(decides), 0.0, 0.0))


def test_the_exact_cover_beats_the_greedy_one():
    # Greedy takes the largest (A) first and then needs both others; two views do it.
    A, B, C = _pose({0, 1, 2, 3}), _pose({0, 1, 4}), _pose({2, 3, 5})
    assert fewest_views([A, B, C], 3) == ((1, 2), True)
    # One view allowed: the one that decides the most, and it is said to be incomplete.
    assert fewest_views([A, B, C], 1) == ((0,), False)


def test_a_view_the_part_cannot_be_registered_in_decides_nothing():
    A = _pose({0, 1, 2, 3, 4, 5}, registration_error="alignment is ambiguous")
    B, C = _pose({0, 1, 2}), _pose({3, 4, 5})
    assert fewest_views([A, B, C], 3) == ((1, 2), True)


def test_views_are_chosen_by_what_they_decide_together():
    # c5 (a distance from a rim seen only by B to one seen only by C) is decided by B and C together;
    # A decides c0-c3 alone, which B and C decide together as well.
    A, B, C, D = _pose({0, 1, 2, 3}), _pose({0, 1, 4}), _pose({2, 3}), _pose({4})
    cands = [A, B, C, D]

    def together(views):
        have = {id(v) for v in views}
        return {5: None} if id(B) in have and id(C) in have else {}

    chosen, complete = fewest_views(cands, 3)
    assert complete and 5 not in {k for i in chosen for k in range(6) if cands[i].characteristics[k].decidable}
    # Alone, A and B (or B and D with C) are chosen; together, B and C decide all six, A is needless.
    assert fused_choice(cands, chosen, 3, together) == (1, 2)
    # One view allowed: nothing is added, and the lone view is kept.
    assert fused_choice(cands, (0,), 1, together) == (0,)
    # Nothing decided by any view alone: the best-ranked view first, then its partner.
    E, F = _pose(set()), _pose(set())
    assert fused_choice([E, F], (), 2, lambda views: {0: None} if len(views) == 2 else {}) == (0, 1)


def test_candidates_cover_a_full_turn_upright_and_upside_down():
    c = view_candidates(120.0)
    assert [(p.rotation, p.tilt_x) for p in c] == [(0.0, 0.0), (120.0, 0.0), (-120.0, 0.0),
                                                   (0.0, 180.0), (120.0, 180.0), (-120.0, 180.0)]


@pytest.fixture(scope="module")
def rig_file(tmp_path_factory):
    from partinspect.simulate.rig import default_rig
    from partinspect.vision.calibration import write_calibration

    path = tmp_path_factory.mktemp("rig") / "calibration.yaml"
    write_calibration(path, default_rig(SIZE))
    return path


def test_plate_views_decide_what_one_pose_leaves_out_of_view(rig_file, tmp_path, capsys):
    """The plate's bottom rims, out of view from above, are decided by the view with the part upside down;
    a distance from a bottom rim to a top rim, which no view sees whole, by the views together; the
    printed --views text renders each chosen view in the pose the plan predicted."""
    from partinspect.poses import parse_views, parse_pose, turned_pose

    spec = tmp_path / "part.tol.yaml"
    spec.write_text((PLATE.parent / "part.tol.yaml").read_text()
                    + "  - {between: [circle-1, circle-4], upper: 0.1, lower: -0.1}   # bottom rim to top rim\n")
    out = tmp_path / "plan"
    code = main(["plan", str(PLATE), "--rig", str(rig_file), "--views", "3", "--step", "180", "-o", str(out), "-q",
                 "--tolerances", str(spec)])
    data = json.loads((out / "plan.json").read_text())
    views = data["views"]
    assert len(views["candidates"]) == 4 and 1 <= len(views["chosen"]) <= 3
    start = {c["id"]: c for c in data["start"]["characteristics"]}
    hidden = [cid for cid, c in start.items() if not c["inspected"]]
    assert hidden, "the start pose sees every edge: nothing for the views to add"
    decided = {cid for v in views["chosen"] for cid in v["decides"]}
    assert set(hidden) <= decided | {u["id"] for u in views["undecided"]} | set(views["out_of_view"])
    assert any(v["fixture"][1] == 180.0 for v in views["chosen"])
    assert len(decided & set(hidden)) >= len(hidden) // 2
    assert code == (0 if not views["undecided"] else 3)
    # No candidate sees both rims, so no view decides the distance alone; the chosen views combined do.
    cross = "distance(circle-1,circle-4)"
    assert not start[cross]["inspected"] or not start[cross]["decidable"]
    together = {t["id"]: t for t in views["together"]}
    assert cross in together and len(together[cross]["views"]) >= 2
    assert 0 < together[cross]["expanded_uncertainty"] <= 0.25 * 0.2
    assert sum(cross in v["decides"] for v in views["chosen"]) >= 2
    # The render's convention (turns about X, then Y, then Z) reproduces each chosen fixture pose.
    from partinspect.cad.step import load_step
    from partinspect.planning.search import FixturePose, fixture_pose
    from partinspect.poses import bounds_of

    bounds = bounds_of(load_step(PLATE))
    start_pose = parse_pose(views["pose"], bounds, None)
    center = 0.5 * (bounds[0] + bounds[1])
    turns = parse_views(views["render_views"])
    assert len(turns) == len(views["chosen"])
    for turn, v in zip(turns, views["chosen"]):
        assert np.allclose(turned_pose(start_pose, turn, bounds),
                           fixture_pose(start_pose, center, FixturePose(*v["fixture"])), atol=1e-6)
    html = (out / "plan.html").read_text()
    assert 'id="views"' in html and views["render_views"] in html



def test_a_part_laid_on_its_side_renders_in_the_pose_the_plan_predicted():
    """--tilts 90: each candidate on its side, written as --views text, is the fixture pose itself."""
    from partinspect.planning.search import fixture_pose
    from partinspect.planning.views import turns_text, view_turns
    from partinspect.poses import parse_views, turned_pose

    c = view_candidates(90.0, tilts=(90.0, -90.0))
    assert len(c) == 8 and {p.tilt_x for p in c} == {90.0, -90.0}
    bounds = np.array([[0.0, 0.0, 0.0], [80.0, 60.0, 10.0]])
    center = bounds.mean(axis=0)
    start = np.eye(4)
    start[:3, 3] = [0.0, 0.0, 400.0]
    preds = [SimpleNamespace(angles=(p.rotation, p.tilt_x, p.tilt_y)) for p in c]
    for turn, p in zip(parse_views(turns_text(view_turns(preds))), c):
        assert np.allclose(turned_pose(start, turn, bounds), fixture_pose(start, center, p), atol=1e-6)
    assert main(["plan", str(PLATE), "--rig", "nowhere.yaml", "--views", "2", "--tilts", "0,ninety"]) == 2
