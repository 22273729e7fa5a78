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


def _rolled_and_levelled(calib, pairs, px):
    """Rolled by ``px`` at the image's sides, the right principal point moved so that the rims' mean residual is
    about zero: as on the bracket's renders, where a roll about the rims' middle leaves the mean unmoved."""
    rolled = _rolled(calib, px)
    return _shifted(rolled, -check_calibration(rolled, pairs).drift.shift)


def test_a_roll_three_tangencies_ask_for_is_fitted_and_corrected(plate):
    """Two rims, 3 tangencies (fewer than MIN_ROLL_TANGENCIES), rolled 1 px: about a constant they scatter
    far beyond their variances (Birge ratio 16). Before, no slope was fitted, the mean read zero and the check
    said "consistent", the roll left in every result; now the scatter asks for the slope, and the roll is
    fitted and taken out."""
    from partinspect.vision.epipolar_drift import SCATTER_P, drift_axes

    calib, pairs = plate
    two = [pairs[0], pairs[3]]
    stated = _rolled_and_levelled(calib, two, 1.0)
    check = check_calibration(stated, two)
    assert check.drift.n == 3 and check.corrected
    roll = float(check.correction @ drift_axes(stated)[1]) * check.half_width
    assert roll == pytest.approx(-1.0, abs=0.15), roll  # px at the image's sides
    assert check.verdict == "drifted" and check.scatter_p > SCATTER_P and check.roll_type_b == 0.0
    assert _left_over(check, two) < 0.02


def test_a_roll_too_few_tangencies_fit_is_carried_not_called_consistent(plate):
    """Two rims, 2 tangencies: no slope can be fitted and their difference scatters beyond its variance
    (Birge ratio 22). The scatter is carried as a roll of the right camera, its size (1 px at the image's
    sides) read from the scatter itself, where before the check said "consistent" and carried nothing."""
    from partinspect.vision.calibration_uncertainty import full_covariance
    from partinspect.vision.epipolar_drift import SCATTER_P, drift_axes

    calib, pairs = plate
    two = [pairs[1], pairs[3]]
    stated = _rolled_and_levelled(calib, two, 1.0)
    check = check_calibration(stated, two)
    assert check.drift.n == 2 and check.scatter_p < SCATTER_P and abs(check.drift.shift) < check.drift.u
    assert check.verdict == "drifted"
    axis = drift_axes(stated)[1]
    carried = np.sqrt(axis @ full_covariance(check.calib)[-6:-3, -6:-3] @ axis) * check.half_width
    assert 0.7 < carried < 1.5, carried  # px at the sides: the roll's, where the stated calibration states none
    assert check.roll_type_b * check.half_width == pytest.approx(carried, rel=0.05)


def test_the_same_rims_under_the_exact_rig_carry_nothing(plate):
    calib, pairs = plate
    for two in ([pairs[0], pairs[3]], [pairs[1], pairs[6]]):
        check = check_calibration(calib, two)
        assert check.verdict == "consistent" and check.roll_type_b == 0.0 and check.calib is calib


def test_a_scatter_beyond_what_a_run_carries_is_invalid_with_one_line(plate):
    calib, pairs = plate
    two = [pairs[1], pairs[3]]
    check = check_calibration(_rolled_and_levelled(calib, two, 4.0), two)
    assert check.verdict == "invalid" and check.roll_type_b * check.half_width > 3.0
    line = check.refusal()
    assert "\n" not in line and "recalibrate" in line and "roll of" in line


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
    odd = [used.index((2, 0)), used.index((2, 1))]  # the wall hole's two tangencies
    # The odd rim carries its own error, far beyond the fits' noise a well-seen rim's tangency has.
    assert len(used) >= 6 and variances[odd].max() > 10 * variances.min()
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


def test_a_tangent_carries_the_uncorrected_shading_beside_it_not_elsewhere():
    """The tangents are read from the points as found, before the shading correction: a tangent's Type B is
    the whole displacement that correction would remove where it touches the line (``BACKGROUND_CORRECTION``
    times the bound, a rectangular half-width), and shading elsewhere on the rim does not reach it."""
    from types import SimpleNamespace

    from partinspect.vision.epipolar_drift import _ellipse_points, _shading_variance
    from partinspect.vision.rim_errors import BACKGROUND_CORRECTION, EDGE_BIAS_FLOOR

    params = np.array([400.0, 300.0, 25.0, 17.0, 0.3])
    t = np.linspace(0.0, 2 * np.pi, 200, endpoint=False)
    xy = _ellipse_points(params, t)
    bound = np.where(np.abs(np.angle(np.exp(1j * (t - 1.0)))) < 0.2, 0.12, 0.0)  # shaded about phase 1 only
    f = SimpleNamespace(fit=SimpleNamespace(params=params), ideal=SimpleNamespace(xy=xy), background_bound=bound)
    shaded = _shading_variance(f, 1.0)
    assert np.isclose(shaded, (BACKGROUND_CORRECTION * 0.12) ** 2 / 3 + EDGE_BIAS_FLOOR**2)
    assert np.isclose(_shading_variance(f, 1.0 + np.pi), EDGE_BIAS_FLOOR**2)
    assert np.isclose(_shading_variance(SimpleNamespace(fit=f.fit, ideal=f.ideal), 1.0), EDGE_BIAS_FLOOR**2)
