"""Parallelism between measured edges: a line's tilt against a parallel datum line."""

import math

import numpy as np
import pytest

from partinspect.cad.registration import register
from partinspect.errors import InputError
from partinspect.simulate.measured import measure_features
from partinspect.tolerances.evaluate import evaluate
from partinspect.tolerances.geometry import line_tilt
from partinspect.tolerances.resolve import characteristics_for
from partinspect.tolerances.spec import parse_spec


def test_tilt_of_a_line_against_a_parallel_one():
    b = ([0, 0, 0], [100, 0, 0])
    # 0.1 mm higher at the far end over 100 mm: atan(0.1 / 100), either orientation of a
    assert line_tilt([0, 0, 10], [100, 0, 10.1], *b) == pytest.approx(math.atan(0.001))
    assert line_tilt([100, 0, 10.1], [0, 0, 10], *b) == pytest.approx(math.atan(0.001))
    assert line_tilt([0, 0, 10], [100, 0, 10], *b) == 0.0
    # towards a direction: only the tilt along it counts; one sideways is second order
    assert line_tilt([0, 5, 0], [100, 5, 0.1], *b, towards=[0, 0, 1]) == pytest.approx(math.atan(0.001))
    assert abs(line_tilt([0, 5, 0], [100, 5.1, 0], *b, towards=[0, 0, 1])) < 1e-12
    with pytest.raises(ValueError, match="one line"):
        line_tilt([10, 0, 0], [20, 0, 0], *b)
    with pytest.raises(ValueError, match="along the lines"):
        line_tilt([0, 0, 10], [100, 0, 10], *b, towards=[1, 0, 0])


def _chars(inv, text):
    return {c.id: c for c in characteristics_for(parse_spec(text, "part.tol.yaml"), inv, "part.tol.yaml")}


def test_an_angle_between_parallel_lines_is_a_parallelism(plate):
    inv = plate[0]
    c = _chars(inv, "angles:\n  - {between: [line-8, line-5], upper: 0.05, lower: -0.05, towards: [0, 1, 0]}\n")[
        "angle(line-8,line-5)"]
    assert c.type == "parallelism" and c.nominal == 0 and c.unit == "rad" and c.towards == (0.0, 1.0, 0.0)
    assert c.upper_limit == pytest.approx(math.radians(0.05))
    assert c.to_dict()["towards"] == [0.0, 1.0, 0.0]
    with pytest.raises(InputError, match="towards is for an angle between parallel lines"):
        _chars(inv, "angles:\n  - {between: [line-5, line-1], upper: 1, lower: -1, towards: [0, 0, 1]}\n")
    with pytest.raises(InputError, match="the direction runs along the lines"):
        _chars(inv, "angles:\n  - {between: [line-8, line-5], upper: 1, lower: -1, towards: [1, 0, 0]}\n")


def test_measured_parallelism_is_consistent_with_its_uncertainty(plate):
    inv, T, ids = plate
    # towards the offset between them, and (by default) in the plane they span: the same quantity here
    pair = [_chars(inv, "angles:\n  - {between: [line-8, line-5], upper: 0.5, lower: -0.5, towards: [0, 1, 0]}\n")[
        "angle(line-8,line-5)"], _chars(inv, "angles:\n  - {between: [line-8, line-5], upper: 0.5, lower: -0.5}\n")[
        "angle(line-8,line-5)"]]
    rng = np.random.default_rng(11)
    z, u = [], []
    for draw in range(40):
        m = measure_features(inv, T, ids, rng, n_points=0)
        reg = register(m.circles, m.lines, inv, pose_hint=T)
        ev = evaluate(pair, reg, inv, seed=draw)
        z.append([e.measured / e.standard_uncertainty for e in ev])  # the truth is 0
        u.append([e.standard_uncertainty for e in ev])
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.6) & (rms < 1.4)), rms
    assert np.all(np.array(u) > 0)
    assert np.allclose(np.array(z)[:, 0] * np.array(u)[:, 0], np.array(z)[:, 1] * np.array(u)[:, 1], atol=1e-6)


def test_a_tilted_line_reads_its_tilt(plate):
    from dataclasses import replace

    inv, T, ids = plate
    (c,) = [x for x in _chars(inv, "angles:\n  - {between: [line-8, line-5], upper: 0.5, lower: -0.5, "
                                   "towards: [0, 0, 1]}\n").values() if x.type == "parallelism"]
    m = measure_features(inv, T, ids, np.random.default_rng(12), n_points=0)
    datums = [x for x in ids if x != "line-8"]
    (before,) = evaluate([c], register(m.circles, m.lines, inv, pose_hint=T, datums=datums), inv)
    # line-8 turned 5 mrad towards the part's z about its midpoint
    i = m.line_ids.index("line-8")
    rec = m.lines[i]
    z_rig = T[:3, :3] @ np.array([0.0, 0.0, 1.0])
    d = rec.direction + math.tan(0.005) * (z_rig - (z_rig @ rec.direction) * rec.direction) / np.linalg.norm(
        z_rig - (z_rig @ rec.direction) * rec.direction)
    d /= np.linalg.norm(d)
    mid = 0.5 * (rec.start + rec.end)
    half = 0.5 * float(np.linalg.norm(rec.end - rec.start))
    lines = list(m.lines)
    lines[i] = replace(rec, direction=d, point=mid, start=mid - half * d, end=mid + half * d)
    (after,) = evaluate([c], register(m.circles, lines, inv, pose_hint=T, datums=datums), inv)
    # the sign follows line-5's orientation: the tilt's size is what changed, by the 5 mrad
    assert abs(abs(after.measured - before.measured) - 0.005) < 2e-5
    assert after.standard_uncertainty == pytest.approx(before.standard_uncertainty, rel=0.05)
