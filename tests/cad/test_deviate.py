import math

import numpy as np
import pytest

from partinspect.cad.deviate import DeviationError, deviate, parse_deviation
from partinspect.cad.features import inventory
from partinspect.cad.step import load_step, save_step
from partinspect.errors import InputError


@pytest.fixture(scope="module")
def plate(plate_path):
    shape = load_step(plate_path)
    return shape, inventory(shape)


@pytest.fixture(scope="module")
def bracket(bracket_path):
    shape = load_step(bracket_path)
    return shape, inventory(shape)


def _rims(inv, feature_id):
    """Ids of the circles on the same axis and radius as this one (both rims of a hole)."""
    f = inv[feature_id]
    out = []
    for g in inv.features:
        if g.kind == "line" or abs(g.radius - f.radius) > 1e-9:
            continue
        v = g.center - f.center
        if np.linalg.norm(v - (v @ f.normal) * f.normal) < 1e-9:
            out.append(g.id)
    return out


def _assert_only_these_changed(before, after, changed, radius=0.0, shift=(0.0, 0.0, 0.0)):
    """The named circles moved/resized exactly as asked; every other feature is as it was."""
    assert [f.id for f in after.features] == [f.id for f in before.features]
    for f in before.features:
        g = after[f.id]
        assert g.kind == f.kind
        if f.id in changed:
            np.testing.assert_allclose(g.center, f.center + np.asarray(shift), atol=1e-6)
            assert g.radius == pytest.approx(f.radius + radius, abs=1e-6)
            np.testing.assert_allclose(g.normal, f.normal, atol=1e-9)
        elif f.kind == "line":
            np.testing.assert_allclose(g.start, f.start, atol=1e-6)
            np.testing.assert_allclose(g.end, f.end, atol=1e-6)
        else:
            np.testing.assert_allclose(g.center, f.center, atol=1e-6)
            assert g.radius == pytest.approx(f.radius, abs=1e-6)
            if f.kind == "arc":
                assert (g.angle_start, g.angle_end) == pytest.approx((f.angle_start, f.angle_end), abs=1e-9)


def test_diameter_of_the_hole_in_the_step(plate):
    shape, inv = plate
    rims = _rims(inv, "circle-8")
    assert rims == ["circle-7", "circle-8"]
    out = deviate(shape, inv, [("circle-8", "diameter", 0.08)])
    _assert_only_these_changed(inv, inventory(out), rims, radius=0.04)
    depth = inv["circle-8"].center[2] - inv["circle-7"].center[2]
    r = inv["circle-8"].radius
    assert shape.Volume() - out.Volume() == pytest.approx(math.pi * ((r + 0.04) ** 2 - r**2) * depth, rel=1e-9)


def test_center_shift_moves_the_whole_hole(plate):
    shape, inv = plate
    rims = _rims(inv, "circle-4")
    assert len(rims) == 2
    out = deviate(shape, inv, [parse_deviation("circle-4.center=0.1,-0.05,0", inv)])
    _assert_only_these_changed(inv, inventory(out), rims, shift=(0.1, -0.05, 0.0))
    assert out.Volume() == pytest.approx(shape.Volume(), rel=1e-12)


def test_size_and_shift_of_one_hole_and_a_second_hole(plate):
    shape, inv = plate
    out = deviate(shape, inv, ["circle-2.radius=-0.03", "circle-1.y=0.07", "circle-10.diameter=-0.1"])
    after = inventory(out)
    assert [f.id for f in after.features] == [f.id for f in inv.features]
    for fid in ("circle-1", "circle-2"):
        np.testing.assert_allclose(after[fid].center, inv[fid].center + [0, 0.07, 0], atol=1e-6)
        assert after[fid].radius == pytest.approx(inv[fid].radius - 0.03, abs=1e-6)
    for fid in ("circle-9", "circle-10"):
        np.testing.assert_allclose(after[fid].center, inv[fid].center, atol=1e-6)
        assert after[fid].radius == pytest.approx(inv[fid].radius - 0.05, abs=1e-6)
    untouched = {"circle-1", "circle-2", "circle-9", "circle-10"}
    for f in inv.features:
        if f.id not in untouched:
            g = after[f.id]
            np.testing.assert_allclose(_vec(g), _vec(f), atol=1e-6, err_msg=f.id)


def _vec(f):
    return np.concatenate([np.ravel(v) for v in (f.start, f.end, f.center) if v is not None] + [[f.length]])


def test_wall_hole_of_the_bracket(bracket):
    shape, inv = bracket
    rims = _rims(inv, "circle-5")
    assert rims == ["circle-5", "circle-6"]
    out = deviate(shape, inv, [("circle-5", "x", 0.2), ("circle-6", "radius", -0.1)])
    after = inventory(out)
    _assert_only_these_changed(inv, after, rims, radius=-0.1, shift=(0.2, 0.0, 0.0))
    assert len(after.of_kind("arc")) == 4  # the slot is untouched


def test_original_shape_is_not_changed(plate):
    shape, inv = plate
    volume = shape.Volume()
    deviate(shape, inv, [("circle-6", "diameter", 0.2)])
    assert shape.Volume() == volume
    assert inventory(shape).to_dict() == inv.to_dict()


def test_deviated_part_survives_a_step_round_trip(tmp_path, plate):
    shape, inv = plate
    out = deviate(shape, inv, [("circle-3", "radius", 0.05)])
    path = tmp_path / "deviated.step"
    save_step(out, path)
    again = inventory(load_step(path))
    assert again["circle-3"].radius == pytest.approx(inv["circle-3"].radius + 0.05, abs=1e-9)


def test_boss_is_resized_and_moved():
    import cadquery as cq

    base = cq.Workplane("XY").box(40, 30, 5, centered=False)
    part = base.union(cq.Solid.makeCylinder(6, 8, cq.Vector(15, 12, 5))).cut(cq.Solid.makeCylinder(2, 5, cq.Vector(32, 20, 0))).val()
    inv = inventory(part)
    boss = [c.id for c in inv.of_kind("circle") if c.radius == pytest.approx(6)]
    assert len(boss) == 2
    assert all(inv[f].convex for c in boss for f in inv[c].faces if inv[f].surface == "cylinder")
    out = deviate(part, inv, [(boss[1], "diameter", 0.2), (boss[0], "center", np.array([0.05, -0.1, 0.0]))])
    _assert_only_these_changed(inv, inventory(out), boss, radius=0.1, shift=(0.05, -0.1, 0.0))
    assert out.Volume() - part.Volume() == pytest.approx(math.pi * (6.1**2 - 36) * 8, rel=1e-9)


def test_hole_with_a_split_wall(plate):
    import cadquery as cq
    from OCP.ShapeUpgrade import ShapeUpgrade_ShapeDivideClosed

    shape, _ = plate
    divide = ShapeUpgrade_ShapeDivideClosed(shape.wrapped)
    divide.SetNbSplitPoints(1)
    divide.Perform()
    split = cq.Shape.cast(divide.Result())
    inv = inventory(split)
    out = deviate(split, inv, [("circle-4", "radius", 0.02)])
    after = inventory(out)
    for fid in ("circle-3", "circle-4"):
        assert after[fid].radius == pytest.approx(inv[fid].radius + 0.02, abs=1e-6)
    assert after["circle-9"].radius == pytest.approx(inv["circle-9"].radius, abs=1e-12)


# --- what cannot be deviated ----------------------------------------------------


@pytest.mark.parametrize(
    "dev, message",
    [
        (("arc-1", "radius", 0.1), "partial cylinder"),
        (("line-3", "radius", 0.1), "is a line"),
        (("face-2", "radius", 0.1), "is a face"),
        (("circle-99", "radius", 0.1), "no feature 'circle-99'"),
        (("circle-3", "y", 0.1), "along the axis"),
        (("circle-1", "radius", -4.0), "would become <= 0"),
        (("circle-1", "volume", 1.0), "unknown parameter"),
    ],
)
def test_unsupported_deviations(bracket, dev, message):
    shape, inv = bracket
    with pytest.raises(DeviationError, match=message):
        deviate(shape, inv, [dev])


def test_two_size_changes_of_one_hole(plate):
    shape, inv = plate
    with pytest.raises(DeviationError, match="already changed"):
        deviate(shape, inv, [("circle-1", "radius", 0.1), ("circle-2", "diameter", 0.1)])


# --- parsing ------------------------------------------------------------------------


def test_parse_deviation_forms(plate):
    _, inv = plate
    assert parse_deviation("circle-3.diameter=0.08") == ("circle-3", "diameter", 0.08)
    assert parse_deviation("  circle-3 . radius = -1e-2 ") == ("circle-3", "radius", -0.01)
    fid, param, delta = parse_deviation("circle-2.center=0.1,0,-0.2", inv)
    assert (fid, param) == ("circle-2", "center")
    np.testing.assert_array_equal(delta, [0.1, 0.0, -0.2])
    assert parse_deviation("circle-2.Z=0.5") == ("circle-2", "z", 0.5)


@pytest.mark.parametrize(
    "text, message",
    [
        ("circle-3diameter=0.08", "expected FEATURE.PARAM=VALUE"),
        ("circle-3.diameter", "expected FEATURE.PARAM=VALUE"),
        ("circle-3.diamter=0.08", "unknown parameter 'diamter'"),
        ("circle-3.diameter=abc", "one number"),
        ("circle-3.diameter=0.1,0.2", "one number"),
        ("circle-3.center=0.1,0.2", "three numbers"),
        ("circle-3.radius=nan", "one number"),
        ("circle-3.radius=inf", "one number"),
    ],
)
def test_parse_deviation_errors(text, message):
    with pytest.raises(DeviationError, match=message) as info:
        parse_deviation(text)
    assert isinstance(info.value, InputError) and isinstance(info.value, ValueError)
    assert "\n" not in str(info.value) and text.strip() in str(info.value)


def test_parse_deviation_checks_ids_against_the_inventory(plate):
    _, inv = plate
    with pytest.raises(DeviationError, match="no feature 'circle-42'"):
        parse_deviation("circle-42.radius=0.1", inv)
    with pytest.raises(DeviationError, match="line-1 is a line"):
        parse_deviation("line-1.radius=0.1", inv)
    assert parse_deviation("circle-42.radius=0.1") == ("circle-42", "radius", 0.1)  # no inventory, no check


def test_fill_fallback_gives_the_same_hole(plate, monkeypatch):
    # Where OCCT's defeaturing fails, the hole is filled with its exact
    # cylinder instead; the result must be the same.
    import partinspect.cad.deviate as dev

    shape, inv = plate
    expected = inventory(deviate(shape, inv, [("circle-8", "diameter", 0.08)]))
    monkeypatch.setattr(dev, "_defeature", lambda shape, faces: None)
    got = inventory(deviate(shape, inv, [("circle-8", "diameter", 0.08)]))
    for f in expected.features:
        np.testing.assert_allclose(_vec(got[f.id]), _vec(f), atol=1e-9, err_msg=f.id)
