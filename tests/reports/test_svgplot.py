"""partinspect.reports.svgplot: ticks, escaping, marks and layout of the SVG charts."""

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from partinspect.reports import svgplot as S

SVG = "{http://www.w3.org/2000/svg}"
FRAME = S.Frame(10.0, 20.0, 200.0, 100.0, xlim=(0.0, 10.0), ylim=(0.0, 5.0))


def _points(path):
    """The (x, y) pairs of a path's d attribute (M/L/H/V letters as separators)."""
    d = ET.fromstring(f'<svg xmlns="http://www.w3.org/2000/svg">{path}</svg>').find(SVG + "path").get("d")
    return np.array([[float(a), float(b)] for a, b in re.findall(r"(-?[0-9.]+),(-?[0-9.]+)", d)])


@pytest.mark.parametrize("lo, hi, nbins, symmetric, want", [
    (0.0, 84.0, 9, False, [0, 10, 20, 30, 40, 50, 60, 70, 80]),
    (0.0, 7624.0, 9, False, [0, 1000, 2000, 3000, 4000, 5000, 6000, 7000]),
    (-0.0906, 0.0906, 5, True, [-0.08, -0.04, 0.0, 0.04, 0.08]),
    (-0.02, 0.07, 5, True, [-0.06, -0.03, 0.0, 0.03, 0.06]),  # symmetric about zero
])
def test_nice_ticks(lo, hi, nbins, symmetric, want):
    steps = S.FINE_STEPS if symmetric else S.AUTO_STEPS
    ticks, step = S.nice_ticks(lo, hi, nbins, symmetric=symmetric, steps=steps)
    assert np.allclose(ticks, want, atol=1e-12)
    assert len(ticks) - 1 <= nbins + 1 and step / 10 ** np.floor(np.log10(step)) in np.round(steps, 6)


def test_nice_ticks_survive_degenerate_ranges():
    for lo, hi in ((3.0, 3.0), (0.0, 0.0), (np.nan, 1.0), (-np.inf, np.inf), (5.0, 1.0)):
        ticks, step = S.nice_ticks(lo, hi)
        assert len(ticks) >= 1 and np.all(np.isfinite(ticks)) and step > 0


def test_tick_labels_decimals_and_minus():
    assert S.tick_labels(np.array([-0.05, -0.025, 0.0, 0.025, 0.05]), 0.025) == [
        "\u22120.050", "\u22120.025", "0.000", "0.025", "0.050"]
    assert S.tick_labels(np.array([0.0, 1000.0, 2000.0]), 1000.0) == ["0", "1000", "2000"]
    assert S.tick_labels(np.array([-1e-17]), 0.1) == ["0.0"]  # no "-0.0"
    assert S.tick_labels(np.array([3 * 0.1]), 0.1) == ["0.3"]


def test_labels_are_escaped_into_well_formed_xml():
    nasty = 'a<b & "c">\x00\x1b\ud800 </svg><script>'
    svg = S.document(300, 200, [S.title(FRAME, nasty), S.text_box(FRAME, [nasty, "ok"]),
                                S.legend(FRAME, [(nasty, "#000", "line"), ("x", "#111", "patch")])], label=nasty)
    root = ET.fromstring(svg)
    clean = 'a<b & "c"> </svg><script>'  # XML-forbidden characters dropped, the rest kept as text
    assert root.get("aria-label") == clean
    texts = [e.text for e in root.iter() if e.tag in (SVG + "text", SVG + "tspan")]
    assert texts.count(clean) == 3 and "<script>" not in svg


def test_polyline_drops_non_finite_and_repeated_points():
    x = np.array([0.0, 1.0, np.nan, 2.0, 2.0001, 3.0, np.inf])
    y = np.array([0.0, 1.0, 1.0, 2.0, 2.0, np.nan, 1.0])
    pts = _points(S.polyline(FRAME, x, y, "#000"))
    # finite: (0,0) (1,1) (2,2) (2.0001,2); the last rounds onto (2,2) and is dropped
    assert np.allclose(pts, [[10, 120], [30, 100], [50, 80]])
    assert S.polyline(FRAME, [1.0, np.nan], [1.0, 1.0], "#000") == ""


def test_stairs_is_one_closed_step_path():
    counts, edges = np.array([1.0, 3.0, np.nan]), np.array([0.0, 2.0, 4.0, 6.0])
    filled = S.stairs(FRAME, counts, edges, fill="#abc", opacity=0.25)
    el = ET.fromstring(f'<svg xmlns="http://www.w3.org/2000/svg">{filled}</svg>').find(SVG + "path")
    assert el.get("d").endswith("Z") and el.get("fill-opacity") == "0.25"
    pts = _points(filled)
    assert len(pts) == 2 * len(counts) + 2
    assert np.allclose(pts[[0, -1], 1], 120) and np.allclose(pts[1:3, 1], 100) and np.allclose(pts[3:5, 1], 60)
    assert np.allclose(pts[5:7, 1], 120)  # a non-finite count is drawn at the baseline
    assert not S.stairs(FRAME, counts, edges, stroke="#000").count("Z")


def test_vrules_and_axes():
    rules = S.vrules(FRAME, [2.0, np.nan, 5.0], "#ccc")
    assert rules.count("M") == 2 and "M50,20V120" in rules and "M110,20V120" in rules
    ticks, step = S.nice_ticks(*FRAME.xlim, nbins=5)
    axis = S.axis_bottom(FRAME, ticks, S.tick_labels(ticks, step), "x, mm")
    root = ET.fromstring(f'<svg xmlns="http://www.w3.org/2000/svg">{axis}</svg>')
    assert [t.text for t in root.iter(SVG + "text")] == ["0", "2", "4", "6", "8", "10", "x, mm"]
    left = S.axis_left(FRAME, ticks[:3], ["0", "2", "4"], "y")
    assert 'transform="rotate(-90' in left


def test_grid_lays_out_rows_with_width_ratios():
    boxes = S.grid(6, 4, 720.0, 300.0, (10.0, 5.0, 15.0, 30.0), wspace=0.1, hspace=0.3)
    assert len(boxes) == 6
    assert boxes[0][:2] == (10.0, 15.0) and boxes[4][0] == 10.0 and boxes[4][1] > boxes[0][1] + boxes[0][3]
    assert abs(boxes[3][0] + boxes[3][2] - 715.0) < 1e-9 and abs(boxes[4][1] + boxes[4][3] - 270.0) < 1e-9
    a, b = S.grid(2, 2, 720.0, 216.0, (43.2, 7.2, 19.4, 32.4), wspace=0.22, width_ratios=(2.1, 1))
    assert abs(a[2] / b[2] - 2.1) < 1e-9 and abs(b[0] + b[2] - 712.8) < 1e-9


def test_same_data_same_bytes():
    x = np.linspace(0, 10, 50)
    make = lambda: S.document(300, 200, [S.polyline(FRAME, x, np.sin(x) + 2, "#000"), S.title(FRAME, "t")])
    assert make() == make()


def test_axes_leave_out_ticks_outside_the_frame():
    axis = S.axis_bottom(FRAME, np.array([-2.0, 0.0, 10.0, 12.0]), ["a", "b", "c", "d"])
    assert re.findall(r">([a-d])</text>", axis) == ["b", "c"]
    assert re.findall(r">([a-d])</text>", S.axis_left(FRAME, np.array([-1.0, 5.0, 6.0]), ["a", "b", "c"])) == ["b"]


def test_equal_limits_give_finite_coordinates():
    flat = S.Frame(0.0, 0.0, 100.0, 50.0, xlim=(2.0, 2.0), ylim=(0.0, 0.0))
    path = S.polyline(flat, [2.0, 3.0], [0.0, 0.0], "#000")
    assert "nan" not in path and "inf" not in path and np.all(np.isfinite(_points(path)))
