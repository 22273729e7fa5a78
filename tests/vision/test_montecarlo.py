"""Monte Carlo (JCGM 101) against first-order covariances of the 3D features."""

from dataclasses import replace

import numpy as np

from partinspect.vision.montecarlo import correlated_normal_errors, monte_carlo
from tests.vision.test_stereo import measured
from partinspect.vision.stereo import measure_stereo
from tests.vision import stereo_scenes as S


def test_correlated_errors_have_the_model_correlation():
    xy = np.c_[np.arange(40.0), np.zeros(40)]
    z = correlated_normal_errors(xy, 1.0, 20000, np.random.default_rng(0))
    c = np.corrcoef(z[:, 10], z[:, 11])[0, 1]
    assert abs(c - np.exp(-1 / 4)) < 0.03 and abs(z.std() - 1) < 0.02


def _pick(res):
    circle = max((k for k, f in enumerate(res.features) if f.kind == "circle"),
                 key=lambda k: len(res.features[k].correspondences))
    line = max((k for k, f in enumerate(res.features) if f.kind == "line"),
               key=lambda k: len(res.features[k].correspondences))
    return [circle, line]


def _ratio(m, res, calibration=False):
    """Monte Carlo over first-order standard deviations of the parts the Monte Carlo draws.

    A circle's ``param_cov`` also holds the Type B component for the
    remaining edge displacement at hole rims (``param_cov_systematic``),
    which no draw of image noise or calibration reproduces.
    """
    f = res.features[m.feature]
    fo = f.param_cov_image + (f.param_cov_calibration if calibration else 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.diag(m.cov_mc) / np.diag(fo))


def test_first_order_agrees_with_monte_carlo_image_noise():
    rig, res = measured(0)
    mc = monte_carlo(res, rig, _pick(res), draws=150, seed=1)
    for m in mc:
        # Positions (centre or point, across the line) and radius: standard deviations within 15 %.
        idx = [0, 1, 2, 6] if m.kind == "circle" else [0, 1, 2]
        ratio = _ratio(m, res)[idx]
        ratio = ratio[np.isfinite(ratio)]
        assert np.all(np.abs(ratio - 1) < 0.15), (m.kind, _ratio(m, res))


def test_first_order_agrees_with_monte_carlo_with_calibration():
    # A calibration's full covariance, as a board session states it: correlated parameters,
    # so both the principal directions of the first order and the draws are tried.
    from partinspect.simulate.calibration import simulated_calibration
    from partinspect.vision.calibration import validate_calibration

    rig, _ = measured(0)
    cal = validate_calibration(replace(rig, std={}, cov=simulated_calibration(rig, np.random.default_rng(3)).cov))
    _, _, L, R = S.render("plate", 2.0, 0)
    res = measure_stereo(L, R, cal)
    mc = monte_carlo(res, cal, _pick(res), draws=100, seed=2)
    for m in mc:
        idx = [0, 1, 2, 6] if m.kind == "circle" else [0, 1, 2]
        ratio = _ratio(m, res, calibration=True)
        assert np.all(np.abs(ratio[idx] - 1) < 0.2), (m.kind, ratio)
