"""A stated calibration made as a board session makes it: off the true rig by what it states, and no more."""

import json
from dataclasses import replace

import numpy as np

from partinspect.cli import main
from partinspect.poses import fixation_point
from partinspect.simulate.calibration import simulated_calibration
from partinspect.simulate.rig import default_rig
from partinspect.vision.calibration import project_points, read_calibration, undistort_points
from partinspect.vision.matching import epipolar_geometry


def _epipolar_residuals(true, stated, rng):
    """Band offset differences of true correspondences of points about the working distance, under ``stated``, px."""
    X = fixation_point(true) + rng.uniform(-40.0, 40.0, (300, 3))
    ideal = []
    for i, (K, D) in enumerate(((stated.K1, stated.D1), (stated.K2, stated.D2))):
        xn = undistort_points(project_points(X, *true.camera(i)), K, D)
        ideal.append(xn @ K[:2, :2].T + K[:2, 2])
    g = epipolar_geometry(stated)
    return g.band_right(ideal[1]) - g.band_left(ideal[0])


def test_its_errors_are_what_it_states_and_its_epipolar_geometry_stays_close():
    rig = default_rig()
    z = []
    for seed in range(5):
        c = simulated_calibration(rig, np.random.default_rng(seed))
        for K, Kt, std in ((c.K1, rig.K1, c.std["intrinsics1"]), (c.K2, rig.K2, c.std["intrinsics2"])):
            err = np.array([K[0, 0] - Kt[0, 0], K[1, 1] - Kt[1, 1], K[0, 2] - Kt[0, 2], K[1, 2] - Kt[1, 2]])
            z.extend(err / std[:4])
        # Focal lengths and principal points off by pixels, yet the epipolar geometry within a tenth of one:
        # a calibration's errors are correlated, which independent draws per parameter would not be.
        assert np.median(np.abs(_epipolar_residuals(rig, c, np.random.default_rng(9)))) < 0.1
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.4 < rms < 2.0, rms


def _parameters(c):
    """A calibration's parameters in its covariance's order."""
    import cv2

    K = lambda K: K[[0, 1, 0, 1], [0, 1, 2, 2]]  # noqa: E731
    return np.concatenate([K(c.K1), c.D1, K(c.K2), c.D2, cv2.Rodrigues(c.R)[0].ravel(), c.T])


def test_its_stated_covariance_describes_its_errors_and_its_epipolar_geometry():
    from partinspect.vision.calibration_uncertainty import perturbed_calibration, uncertainty_directions

    rig = default_rig()
    m2, ratio, ratio_independent = [], [], []
    for seed in range(4):
        c = simulated_calibration(rig, np.random.default_rng(seed))
        e = _parameters(c) - _parameters(rig)
        m2.append(e @ np.linalg.solve(c.cov, e))
        # The spread of the epipolar residual the stated uncertainty predicts, against the residual found.
        found = _epipolar_residuals(rig, c, np.random.default_rng(9))
        for cal, out in ((c, ratio), (replace(c, cov=None), ratio_independent)):
            base = _epipolar_residuals(c, c, np.random.default_rng(9))
            var = sum((_epipolar_residuals(c, perturbed_calibration(cal, d), np.random.default_rng(9)) - base) ** 2
                      for d in uncertainty_directions(cal))
            out.append(np.sqrt(np.mean(found**2) / np.mean(var)))
    # 24 parameters: the squared Mahalanobis distance of the errors averages 24 (chi-square, 4 draws: 13-38 at 99 %).
    assert 13 < np.mean(m2) < 38, m2
    # With the covariance the epipolar residual is stated at its size; taken as independent it is overstated
    # by two orders of magnitude.
    assert 0.4 < np.median(ratio) < 2.5, ratio
    assert max(ratio_independent) < 0.02, ratio_independent


def _render(tmp_path, repo, *options):
    """The plate rendered at 612 x 512 with ``options``: (stated calibration, truth)."""
    out = tmp_path / "render"
    assert main(["render", str(repo / "examples" / "plate" / "part.step"), str(out), "--size", "612x512",
                 *options, "-q"]) == 0
    return read_calibration(out / "images"), json.loads((out / "truth.json").read_text())


def test_render_writes_the_calibrated_rig_and_keeps_the_true_one(tmp_path, repo):
    stated, truth = _render(tmp_path, repo, "--calib-error", "4")
    note = truth["calibration_error"]
    true_K1 = np.array(note["true_rig"]["K1"])
    assert note["seed"] == 4 and stated.std["intrinsics1"][0] > 0 and stated.cov.shape == (24, 24)
    assert abs(stated.K1[0, 0] - true_K1[0, 0]) > 1e-3 and abs(stated.K1[0, 0] - true_K1[0, 0]) < 6 * stated.std["intrinsics1"][0]


def test_a_drifted_rig_is_rendered_and_the_run_finds_the_drift(tmp_path, repo):
    from partinspect.pipeline import run_inspection

    stated, truth = _render(tmp_path, repo, "--drift", "shift=1.5")
    note = truth["drift"]
    assert note["kind"] == "shift" and note["px"] == 1.5
    assert np.array(note["rig_after_drift"]["K2"])[1, 2] == stated.K2[1, 2] + 1.5
    check = run_inspection(repo / "examples" / "plate" / "part.step", tmp_path / "render" / "images",
                           tmp_path / "out").report[
        "calibration_check"]
    assert check["verdict"] == "drifted" and abs(abs(check["epipolar_residual_px"]) - 1.5) < 0.2, check


def test_a_bad_drift_is_one_clear_error(tmp_path, repo, capsys):
    code = main(["render", str(repo / "examples" / "plate" / "part.step"), str(tmp_path / "r"), "--drift", "tilt=1"])
    assert code == 2 and "--drift: expected shift=PX or roll=PX" in capsys.readouterr().err
