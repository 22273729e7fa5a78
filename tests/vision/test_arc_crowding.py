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


def _arc_scene(offsets):
    """Two CAD rims' images (concentric circles r 40 and 60 px) and measured arcs off rim "A" by ``offsets`` (px, (left, right))."""
    from types import SimpleNamespace

    t = np.linspace(0, 2 * np.pi, 1600)
    ring = lambda r: np.c_[100 + r * np.cos(t), 100 + r * np.sin(t)]  # noqa: E731
    images = {"A": (ring(40), ring(40)), "B": (ring(60), ring(60))}
    s = np.linspace(0.2, 2.4, 60)  # a 35 % arc
    arc = lambda r: SimpleNamespace(uv=np.c_[100 + r * np.cos(s), 100 + r * np.sin(s)])  # noqa: E731
    left = [arc(40 + dl) for dl, _ in offsets]
    right = [arc(40 + dr) for _, dr in offsets]
    feats = tuple(SimpleNamespace(kind="arc", left=k, right=k) for k in range(len(offsets)))
    stereo = SimpleNamespace(features=feats, left=SimpleNamespace(features=left), right=SimpleNamespace(features=right))
    return stereo, images


def test_an_unmatched_arc_along_a_free_rims_image_is_taken_as_that_rim():
    from partinspect.vision.guided import MAX_DISTANCE, rims_along

    # 0.6 px off (as a crowded rim's ends push it) in both images: rim A's.
    stereo, images = _arc_scene([(0.6, -0.6)])
    assert rims_along(stereo, [0], {"A", "B"}, images) == {0: "A"}
    # A already has its measured feature: nothing to take.
    assert rims_along(stereo, [0], {"B"}, images) == {}
    # Farther off than a point may lie from its edge's image, in one image only: not A's.
    stereo, images = _arc_scene([(0.3, MAX_DISTANCE + 0.5)])
    assert rims_along(stereo, [0], {"A", "B"}, images) == {}
    # Nearer B than A in the right image: not one rim's in both.
    stereo, images = _arc_scene([(0.3, 12.0)])
    assert rims_along(stereo, [0], {"A", "B"}, images) == {}
    # Two arcs along A: the nearer one takes it.
    stereo, images = _arc_scene([(1.2, 1.2), (0.2, -0.3)])
    assert rims_along(stereo, [0, 1], {"A", "B"}, images) == {1: "A"}
