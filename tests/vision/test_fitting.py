import numpy as np
import pytest

from partinspect.vision.fitting import ellipse_points, fit_circle, fit_ellipse, fit_line
from tests.vision.synthetic import ellipse_draws, line_draws


def test_line_exact_and_gauge():
    t = np.linspace(-50, 50, 101)
    xy = np.column_stack([30 + 0.6 * t, 40 - 0.8 * t])  # direction (0.6, -0.8)
    f = fit_line(xy)
    A, B, C = f.params
    assert A * A + B * B == pytest.approx(1.0)
    assert C <= 0
    assert np.allclose(f.residuals, 0, atol=1e-9)
    assert abs(A * 30 + B * 40 + C) < 1e-9
    assert np.linalg.matrix_rank(fit_line(xy + np.random.default_rng(0).normal(0, 0.1, xy.shape)).cov) == 2


def test_line_on_edge_points_efficient_and_honest():
    errs, preds, kcr_ind, kcr_cor, resid_mean, _ = line_draws(40)
    rms = np.sqrt((errs ** 2).mean(axis=0))
    assert np.all(rms <= 1.25 * kcr_cor)
    ratio = preds.mean(axis=0) / errs.std(axis=0)
    assert np.all((ratio > 0.8) & (ratio < 1.2)), ratio
    assert abs(resid_mean.mean()) < 1e-3
    # Without the correlation the KCR bound is far too optimistic for edge points.
    assert np.all(kcr_ind < 0.75 * kcr_cor)


def test_ellipse_exact_points():
    P = np.array([120.0, 80.0, 50.0, 30.0, 0.7])
    xy = ellipse_points(P, np.linspace(0, 2 * np.pi, 60, endpoint=False))
    f = fit_ellipse(xy)
    assert f.converged
    assert np.allclose(f.params, P, atol=1e-6)


def test_ellipse_on_edge_points_efficient_and_honest():
    errs, preds, kcr_ind, kcr_cor, resid_mean, _, converged = ellipse_draws(30)
    assert converged
    rms = np.sqrt((errs ** 2).mean(axis=0))
    assert np.all(rms <= 1.25 * kcr_cor), rms / kcr_cor
    ratio = preds.mean(axis=0) / errs.std(axis=0)
    assert np.all((ratio > 0.8) & (ratio < 1.2)), ratio
    assert abs(resid_mean.mean()) < 2e-3


def test_ellipse_arc_and_ci():
    rng = np.random.default_rng(2)
    P = np.array([50.0, 60.0, 40.0, 25.0, -0.3])
    phi = np.linspace(0.2, 2.5, 120)
    xy = ellipse_points(P, phi)
    xy = xy + rng.normal(0, 0.05, xy.shape)
    f = fit_ellipse(xy, np.full(len(xy), 0.05 ** 2))
    assert f.converged
    assert np.all((f.ci95[:, 0] <= P) & (P <= f.ci95[:, 1]))
    assert 0.001 < f.consistency.p_value


def test_circle_theta_undetermined_and_fit_circle():
    xy = ellipse_points([50, 50, 20, 20, 0], np.linspace(0, 6, 50))
    f = fit_ellipse(xy)
    assert np.isinf(f.cov[4, 4])
    rng = np.random.default_rng(3)
    errs = []
    for _ in range(200):
        c = fit_circle(xy + rng.normal(0, 0.1, xy.shape), np.full(50, 0.01))
        errs.append(c.params - [50, 50, 20])
    assert np.std(errs, axis=0) == pytest.approx(np.sqrt(np.diag(c.cov)), rel=0.2)


def test_consistency_flags_wrong_model():
    t = np.linspace(0, 1, 200)
    xy = np.column_stack([100 * t, 5 * t * t])  # a parabola, not a line
    f = fit_line(xy, np.full(200, 0.05 ** 2))
    assert f.consistency.p_value < 1e-6
    assert f.consistency.noise_ratio > 3
