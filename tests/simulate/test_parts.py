"""Property-based tests (hypothesis) of the parametric part generator.

For any seed: the part is one valid solid within the rig's field of view;
it survives a STEP round trip through partinspect's own writer and loader
with the same feature inventory, every number of which is finite; the
inventory has every hole rim and slot end the generator placed; and a
random pose lies within ``inspect plan``'s search limits with the whole
part in both images. The issue-46 lug and flange have the sizes the issue
gives, and the flange maps onto itself under its bolt-circle turns (by
registration's own test) while the lug does not.
"""

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from partinspect.cad.features import inventory
from partinspect.cad.registration import cad_arrays, model_symmetry
from partinspect.cad.step import load_step
from partinspect.poses import bounds_of, default_pose, fixation_point
from partinspect.simulate.parts import (KINDS, MAX_LENGTH, flange, lug, random_part, random_pose, write_part)
from partinspect.vision.calibration import project_points, read_calibration

FEW = settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
RIG = read_calibration(Path(__file__).resolve().parents[2] / "examples" / "plate" / "images" / "calibration.yaml")

seeds = st.integers(0, 2**31 - 1)
kinds = st.sampled_from(KINDS)


def _found(expected, features, tol=1e-4):
    """The placed (centre, radius) pairs not among the inventory's features."""
    missing = []
    for c, r in expected:
        if not any(np.linalg.norm(np.asarray(f.center) - c) < tol and abs(f.radius - r) < tol for f in features):
            missing.append((c, r))
    return missing


def _finite(x):
    """Every number in a nested dict/list structure is finite (what a strict JSON writer needs)."""
    json.dumps(x, allow_nan=False)
    return True


@FEW
@given(seed=seeds, kind=kinds)
def test_generated_part_is_one_valid_solid_in_the_field_of_view(seed, kind):
    part = random_part(seed, kind)
    assert part.kind == kind
    assert part.shape.isValid()
    assert len(part.shape.Solids()) == 1
    assert part.shape.Volume() > 1000.0  # mm^3: a part, not a sliver
    b = bounds_of(part.shape)
    assert np.all(b[1] - b[0] <= MAX_LENGTH + 1e-6), b
    assert b[0, 2] == pytest.approx(0.0, abs=1e-6)  # it stands on z = 0
    assert part.features, "a part without features"
    # Same seed, same part.
    again = random_part(seed, kind)
    assert again.features == part.features
    assert again.shape.Volume() == pytest.approx(part.shape.Volume(), rel=1e-12)


@FEW
@given(seed=seeds, kind=kinds)
def test_step_round_trip_keeps_the_placed_holes_and_slots(seed, kind):
    part = random_part(seed, kind)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "part.step"
        write_part(part, path)
        loaded = load_step(path)
    assert loaded.isValid()
    inv = inventory(loaded)
    assert _finite(inv.to_dict())  # what `inspect features --json` prints
    assert inv.features
    direct = {f.id: f for f in inventory(part.shape).features}
    assert {f.id: f.kind for f in inv.features} == {i: f.kind for i, f in direct.items()}
    for f in inv.features:
        if f.kind != "line":
            np.testing.assert_allclose(f.center, direct[f.id].center, atol=1e-6)
            assert f.radius == pytest.approx(direct[f.id].radius, abs=1e-6)
    circles = [f for f in inv.features if f.kind == "circle"]
    arcs = [f for f in inv.features if f.kind == "arc"]
    for f in part.features:
        assert not _found(f.circles, circles), (f, _found(f.circles, circles))
        assert not _found(f.arcs, arcs), (f, _found(f.arcs, arcs))
    holes = [f for f in part.features if f.kind in ("through", "blind", "counterbore", "countersink")]
    # Every hole leaves two circles of its own diameter on its axis (entry or step, and exit or bottom).
    for h in holes:
        own = [f for f in circles if abs(2 * f.radius - h.diameter) < 1e-4
               and np.linalg.norm(np.cross(np.asarray(f.center) - h.center, h.normal)) < 1e-4]
        assert len(own) >= 2, h


@FEW
@given(seed=seeds, kind=kinds)
def test_random_pose_is_reachable_and_in_view(seed, kind):
    part = random_part(seed, kind)
    b = bounds_of(part.shape)  # before random_pose meshes the shape, which widens OCCT's box by some 1e-5 mm
    P, fp = random_pose(seed, part.shape, RIG)
    start = default_pose(b, RIG)
    # Within inspect plan's search: R = R_start Rx(tilt_x) Ry(tilt_y) Rz(rotation), |rotation| <= 180, |tilt| <= 30.
    rel = start[:3, :3].T @ P[:3, :3]
    tx, ty, rz = Rotation.from_matrix(rel).as_euler("XYZ", degrees=True)
    assert np.allclose([tx, ty, rz], [fp.tilt_x, fp.tilt_y, fp.rotation], atol=1e-6)
    assert abs(fp.tilt_x) <= 30 and abs(fp.tilt_y) <= 30 and abs(fp.rotation) <= 180
    # It pivots about the bounding-box centre, which stays at the rig's fixation point.
    centre = P[:3, :3] @ b.mean(axis=0) + P[:3, 3]
    np.testing.assert_allclose(centre, fixation_point(RIG), atol=1e-9)
    # The whole part in both images.
    X = np.array([v.toTuple() for v in part.shape.tessellate(0.5)[0]]) @ P[:3, :3].T + P[:3, 3]
    w, h = RIG.image_size
    for index in (0, 1):
        uv = project_points(X, *RIG.camera(index))
        assert np.all(np.isfinite(uv))
        assert uv[:, 0].min() > 0 and uv[:, 1].min() > 0 and uv[:, 0].max() < w and uv[:, 1].max() < h


def test_every_kind_is_drawn_by_default():
    assert {random_part(seed).kind for seed in range(len(KINDS))} == set(KINDS)


def test_issue_lug_has_the_issue_sizes():
    part = lug()
    b = bounds_of(part.shape)
    np.testing.assert_allclose(b[1] - b[0], [100.0, 56.0, 18.0], atol=1e-6)
    assert part.shape.isValid()
    holes = sorted(f.diameter for f in part.features if f.kind == "through")
    assert holes == [7.5, 7.5, 14.0]
    boss_hole = next(f for f in part.features if f.diameter == 14.0)
    assert boss_hole.center[0] > 100.0 - 44.0 and boss_hole.center[2] == pytest.approx(18.0)
    (slot,) = [f for f in part.features if f.kind == "slot"]
    assert (slot.length, slot.diameter) == (16.0, 8.0)
    assert slot.center[2] == pytest.approx(10.0)  # in the lower step
    inv = inventory(part.shape)
    # A turn of 180 deg about the vertical axis does not map the lug onto itself.
    c = 0.5 * (b[0] + b[1])
    S = np.eye(4)
    S[:3, :3] = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    S[:3, 3] = c - S[:3, :3] @ c
    assert model_symmetry(cad_arrays(inv), S) is None


@pytest.mark.parametrize("seed", [None, 3, 8])
def test_flange_maps_onto_itself_under_its_bolt_circle_turns(seed):
    part = flange() if seed is None else random_part(seed, "flange")
    bolts = [f for f in part.features if f.kind in ("through", "counterbore") and np.hypot(*f.center[:2]) > 1.0]
    n = len(bolts)
    assert n >= 3
    if seed is None:
        assert n == 6 and {f.diameter for f in bolts} == {9.0}
        assert {round(float(np.hypot(*f.center[:2])), 6) for f in bolts} == {35.0}
        b = bounds_of(part.shape)
        np.testing.assert_allclose(b[1] - b[0], [90.0, 90.0, 20.0], atol=1e-6)
    cad = cad_arrays(inventory(part.shape))
    for k, turn in ((1, True), (0.5, False)):
        S = np.eye(4)
        S[:3, :3] = Rotation.from_euler("z", k * 360.0 / n, degrees=True).as_matrix()
        words = model_symmetry(cad, S)
        if turn:
            assert words is not None and f"{360.0 / n:.1f} deg" in words
        else:
            assert words is None
    assert math.isclose(part.shape.Volume(), flange().shape.Volume()) == (seed is None)
