"""The stated calibration checked against a pair, and a drifted rig corrected (on the bundled plate's pair)."""

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from partinspect.vision.calibration import read_calibration
from partinspect.vision.epipolar_drift import check_calibration, matched_arcs, matched_edge_points, tangency_residuals
from partinspect.vision.images import read_pair
from partinspect.vision.matching import epipolar_geometry
from partinspect.vision.stereo import measure_stereo

IMAGES = Path(__file__).resolve().parents[2] / "examples" / "plate" / "images"


@pytest.fixture(scope="module")
def plate_stereo():
    """The exact rig and the stereo result of its pair (ideal pixels do not depend on K without distortion)."""
    calib = read_calibration(IMAGES)
    assert not np.any(calib.D1) and not np.any(calib.D2)
    left, right, _ = read_pair(IMAGES, calib)
    return calib, measure_stereo(left, right, calib)


@pytest.fixture(scope="module")
def plate(plate_stereo):
    """The exact rig and the matched arcs of its pair."""
    calib, stereo = plate_stereo
    return calib, matched_arcs(stereo)


def _shifted(calib, dy):
    K2 = calib.K2.copy()
    K2[1, 2] += dy
    return replace(calib, K2=K2)


def _rolled(calib, px_at_side):
    Q = cv2.Rodrigues(np.array([0.0, 0.0, px_at_side / (0.5 * calib.image_size[0])]))[0]
    return replace(calib, R=Q @ calib.R, T=Q @ np.ravel(calib.T))


def _left_over(check, pairs):
    r, _, _ = tangency_residuals(epipolar_geometry(check.calib), pairs)
    return float(np.sqrt(np.mean(r**2)))


def test_the_exact_rig_is_consistent_and_left_alone(plate):
    calib, pairs = plate
    check = check_calibration(calib, pairs)
    assert check.verdict == "consistent" and not check.corrected and check.calib is calib
    assert check.drift.n >= 6 and abs(check.drift.shift) < 3 * check.drift.u


@pytest.mark.parametrize("dy", [0.25, 1.0, -2.0])
def test_a_shift_across_the_epipolar_lines_is_measured_and_corrected(plate, dy):
    calib, pairs = plate
    check = check_calibration(_shifted(calib, dy), pairs)
    assert check.verdict == "drifted" and check.corrected
    assert abs(check.drift.shift - dy) < 0.02
    assert _left_over(check, pairs) < 0.05
    assert np.all(np.asarray(check.calib.std["extrinsics"])[:3] > 0)  # the correction's uncertainty is carried


def test_a_roll_of_the_right_camera_is_corrected_too(plate):
    """Points at the image's sides moved by 1 px across the epipolar lines, in opposite senses:
    the mean residual says little, the spread says it, and the second turn takes it out."""
    calib, pairs = plate
    stated = _rolled(calib, 1.0)
    r, _, _ = tangency_residuals(epipolar_geometry(stated), pairs)
    check = check_calibration(stated, pairs)
    assert check.verdict == "drifted" and check.corrected
    assert _left_over(check, pairs) < 0.25 * float(np.sqrt(np.mean(r**2)))


def _true_residual(true, stated):
    """Median over the plate's visible CAD edges of the true partners' epipolar residual under ``stated``, px."""
    import json

    from partinspect.cad.edge_sampling import sample_edge
    from partinspect.vision.calibration import project_points

    truth = json.loads((IMAGES.parent / "truth.json").read_text())
    geo, P = epipolar_geometry(stated), np.asarray(truth["part_to_camera"], float)
    out = []
    for f in truth["features"]:
        if f["visible_both"]:
            g = {k: (np.asarray(v, float) if isinstance(v, list) else v) for k, v in f["rendered"].items()}
            X = sample_edge(f["kind"], g)[0] @ P[:3, :3].T + P[:3, 3]
            x = project_points(X, true.K1, true.D1, np.eye(3), np.zeros(3))
            y = project_points(X, true.K2, true.D2, np.asarray(true.R, float), np.ravel(true.T))
            out.append(geo.band_right(y) - geo.band_left(x))
    return float(np.median(np.concatenate(out)))


@pytest.mark.parametrize("px", [1.0, 2.0])
def test_under_a_roll_the_residual_is_stated_at_the_parts_edges(plate_stereo, px):
    """A roll makes the residual a field across the image: the check states it at the part's edges
    (their median), not the tangencies' mean, with a u that covers the truth, and says how much it varies."""
    calib, stereo = plate_stereo
    stated = _rolled(calib, px)
    check = check_calibration(stated, matched_arcs(stereo), matched_edge_points(stereo))
    true = _true_residual(calib, stated)
    assert abs(check.drift.shift - true) < max(0.02, 2 * check.drift.u), (check.drift, true)
    assert check.drift.u < 0.05 * px
    # The field's slope is the roll's: the lines move px at the image's side edges, half its width away.
    assert check.drift.slope * np.sign(check.drift.slope) == pytest.approx(px / (0.5 * calib.image_size[0]), rel=0.25)
    assert check.drift.spread > 0.1 * px


def test_a_drift_beyond_correction_is_invalid(plate):
    calib, pairs = plate
    assert check_calibration(_shifted(calib, 4.0), pairs).verdict == "invalid"


BRACKET = IMAGES.parents[1] / "bracket" / "images"


def test_a_rims_disagreeing_tangents_do_not_hide_a_roll():
    """The bracket's wall hole reads its two tangents 0.2 px apart at any drift: that is the rim's own
    error, not the rig's, and must not swamp the roll the other rims show (0.5 px at the image's sides)."""
    from partinspect.simulate.calibration import drifted_rig, simulated_calibration

    calib = read_calibration(BRACKET)
    stated = simulated_calibration(calib, np.random.default_rng(0))
    rolled = replace(drifted_rig(stated, "roll", 0.5), std=stated.std, cov=stated.cov)
    left, right, _ = read_pair(BRACKET, rolled)
    pairs = matched_arcs(measure_stereo(left, right, rolled))
    _, variances, used = tangency_residuals(epipolar_geometry(rolled), pairs)
    assert len(used) >= 6 and variances.max() > 10 * np.median(variances)  # the odd rim carries its Type B
    check = check_calibration(rolled, pairs)
    assert check.corrected and abs(np.degrees(check.correction[2]) + np.degrees(0.5 / 1224)) < 0.01, check.correction


def test_a_precise_circle_is_paired_through_the_calibrations_own_epipolar_error():
    """Under a calibration as a board session states it (0.01-0.02 px of epipolar error), every circle the
    exact rig pairs is paired: one circle through a calibration its covariance allows."""
    from partinspect.simulate.calibration import simulated_calibration

    calib = read_calibration(IMAGES)
    left, right, _ = read_pair(IMAGES, calib)
    exact = sum(f.kind != "line" for f in measure_stereo(left, right, calib).features)
    stated = simulated_calibration(calib, np.random.default_rng(0))
    drawn = sum(f.kind != "line" for f in measure_stereo(left, right, stated).features)
    assert drawn == exact >= 7
