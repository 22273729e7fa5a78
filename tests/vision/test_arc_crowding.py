"""Which edges may crowd a rim: not those that meet it at its ends, not smooth ones."""

from pathlib import Path

import numpy as np

from partinspect.vision.guided import _Crowd
from partinspect.vision.posed import meeting

ROOT = Path(__file__).resolve().parents[2]


def test_the_bracket_slot_ends_meet_the_slot_sides_and_a_whole_circle_meets_nothing():
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step

    inv = inventory(load_step(ROOT / "examples" / "bracket" / "part.step"))
    by_id = {f.id: f for f in inv.features}
    arc = by_id["arc-2"]
    met = meeting(arc, inv.features)
    assert met and all(by_id[i].start is not None for i in met)
    ends = np.array([arc.start, arc.end])
    for i in met:
        g = by_id[i]
        assert np.linalg.norm(ends[:, None] - np.array([g.start, g.end])[None], axis=2).min() < 1e-3
    # Every other edge keeps its distance from the arc's ends.
    others = [g for g in inv.features if g.start is not None and g.id not in met and g.id != arc.id]
    assert all(np.linalg.norm(ends[:, None] - np.array([g.start, g.end])[None], axis=2).min() >= 1e-3
               for g in others)
    circle = next(f for f in inv.features if f.kind == "circle" and f.start is None)
    assert meeting(circle, inv.features) == set()


def test_an_ignored_edge_does_not_crowd():
    own = np.c_[np.linspace(0, 50, 101), np.zeros(101)]
    beside = own + [0.0, 2.0]
    images = {"rim": (own, own), "side": (beside, beside)}
    crowd = _Crowd(images, 0)
    uv = own[::10]
    assert not crowd.clear_of_others(uv, "rim", 3.0).any()
    assert crowd.clear_of_others(uv, "rim", 3.0, ("side",)).all()
    assert crowd.clear_of_others(uv, "rim", 1.5).all()
