"""Why an edge was not measured names the condition: here, saturation (a highlight or over-exposure)."""

import json
import shutil

import cv2
import numpy as np
import pytest

from partinspect.diagnosis import saturated_along, saturation_level


def test_saturation_level_is_the_sensors_top():
    img8 = np.full((10, 10), 100, np.uint8)
    assert saturation_level(img8, 8) == 255
    img12 = np.full((100, 100), 1000, np.uint16)
    img12[:5] = 4095  # a 12-bit sensor's clipped pixels in a 16-bit file
    assert saturation_level(img12, 16) == 4095
    img12[:5] = 3000
    img12[0, 0] = 3001  # one bright pixel is no pile-up
    assert saturation_level(img12, 16) == 65535


def test_saturated_along_counts_points_with_clipped_pixels_nearby():
    img = np.zeros((50, 50), np.uint8)
    img[:, 30:] = 255
    uv = np.column_stack([np.linspace(5, 45, 41), np.full(41, 20.0)])  # a horizontal edge across the image
    frac = saturated_along(img, uv, 255)
    assert abs(frac - 19 / 41) < 0.03  # x >= 27 lies within 3 px of the clipped half
    assert saturated_along(img, uv + [0, 1000], 255) == 0.0  # outside the image: nothing counts


def test_a_rim_under_a_highlight_says_so(repo, tmp_path):
    """The plate's 12 mm hole clipped to 255 around its rim in the left image: not measured, and the reason says why."""
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.cad.edge_sampling import feature_geometry, sample_edge
    from partinspect.pipeline import run_inspection
    from partinspect.vision.calibration import project_points, read_calibration

    src = repo / "examples" / "plate"
    images = tmp_path / "images"
    shutil.copytree(src / "images", images)
    truth = json.loads((src / "truth.json").read_text())
    pose = np.asarray(truth["part_to_camera"], float)
    calib = read_calibration(images)
    inv = inventory(load_step(src / "part.step"))
    rim = max((f for f in inv.of_kind("circle") if abs(f.radius - 6.0) < 1e-6), key=lambda f: f.center[2])
    pts, _ = sample_edge(rim.kind, feature_geometry(rim))
    uv = project_points(pts @ pose[:3, :3].T + pose[:3, 3], calib.K1, calib.D1, np.eye(3), np.zeros(3))
    left = cv2.imread(str(images / "left.png"), cv2.IMREAD_UNCHANGED)
    mask = np.zeros(left.shape, np.uint8)
    cv2.polylines(mask, [np.rint(uv).astype(np.int32)], True, 1, thickness=13)
    left[mask > 0] = 255
    cv2.imwrite(str(images / "left.png"), left)

    report = run_inspection(src / "part.step", images, tmp_path / "out").report
    entry = next(f for f in report["features"] if f["id"] == rim.id)
    assert entry["measured"] is None
    assert "saturated (grey level 255)" in entry["reason"] and "left image" in entry["reason"]
    others = [f for f in report["features"] if f["measured"] is None and f["id"] != rim.id]
    assert not any("saturated" in f["reason"] for f in others)


def test_a_hole_moved_beyond_the_match_gate_is_said_to_be_displaced():
    """The plate's 8 mm hole measured 0.8 mm from its place (beyond the 0.5 mm match gate): left unassigned by the
    registration, and the reason names the displacement, not a missing grey-level step or edge."""
    from partinspect.cad.registration import register
    from partinspect.diagnosis import displaced_circle
    from partinspect.simulate.measured import measure_features
    from tests.tolerances.conftest import plate as plate_fixture

    inv, T, ids = plate_fixture.__wrapped__()
    m = measure_features(inv, T, ids, np.random.default_rng(3), n_points=0, shifts={"circle-2": np.array([0.8, 0, 0])})
    reg = register(m.circles, m.lines, inv, datums=[x for x in ids if x.startswith("line")], pose_hint=T)
    parts = reg.features_in_part_frame()
    assert "circle-2" not in {p.cad_id for p in parts}
    unassigned = [p for p in parts if p.cad_id is None and p.kind == "circle"]
    why = displaced_circle(inv["circle-2"], unassigned)
    assert why is not None and why.startswith("measured, but 0.8") and "0.5 mm" in why and "displaced" in why
    # the other rims are not taken for it: none of them is this hole moved
    assert all(displaced_circle(inv[f], unassigned) is None for f in ids if f.startswith("circle") and f != "circle-2")
    # a reach shorter than the offset claims nothing
    assert displaced_circle(inv["circle-2"], unassigned, reach=0.7) is None


@pytest.mark.slow
def test_a_moved_hole_in_a_render_is_reported_displaced(repo, tmp_path):
    """End to end on a small render: the 8 mm hole moved 0.8 mm is "measured, but 0.80 mm from its nominal place",
    not "no edge found along it" (its edge is looked for at the nominal place, where there is none)."""
    from partinspect.cli import main
    from partinspect.pipeline import run_inspection

    step = repo / "examples" / "plate" / "part.step"
    render = tmp_path / "render"
    assert main(["render", str(step), str(render), "--size", "816x683", "-q", "--deviate", "circle-2.center=0.8,0,0"]) == 0
    report = run_inspection(step, render / "images", tmp_path / "out").report
    entry = next(f for f in report["features"] if f["id"] == "circle-2")
    assert entry["measured"] is None and entry["reason"].startswith("measured, but 0.8"), entry["reason"]
    size = next(c for c in report["characteristics"] if c["id"] == "circle-2.diameter")
    assert size["decision"] == "inconclusive" and "from its nominal place" in size["reason"]


def test_a_feature_measured_then_taken_out_says_so_before_its_visibility():
    """Issue 38, NIST ftc_09 circle-59: a rim a third in sight (below the fraction that counts as in view) was
    measured and matched, then taken out as crowded in one image: its reason says that, not "not visible"."""
    from types import SimpleNamespace as NS

    from partinspect.cad.visibility import FeatureVisibility
    from partinspect.diagnosis import unmeasured_reason

    vis = FeatureVisibility((1.0, 1.0), (0.31, 0.37), (0.31, 0.37))
    assert not vis.in_view
    stereo = NS(withdrawn=(("circle-59", "in the left image 26 of its 26 points lie within 7.6 px of circle-61's "
                                         "image"),))
    why = unmeasured_reason(NS(id="circle-59"), vis, None, None, stereo, {})
    assert why.startswith("measured, then taken out: in the left image 26 of its 26") and "circle-61" in why
    assert unmeasured_reason(NS(id="circle-57"), vis, None, None, stereo, {}).startswith("not visible: hidden")
