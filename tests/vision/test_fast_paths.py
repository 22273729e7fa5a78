"""The fast paths of the fits agree with the plain numpy forms they replace."""

import numpy as np

from partinspect.vision.fitting import (
    _line_tls,
    _pinv_sym,
    _solve_sym,
    ellipse_points,
    fit_ellipse,
)
from partinspect.vision.stereo import _along_edge_mean


def test_small_symmetric_solvers_match_numpy():
    rng = np.random.default_rng(0)
    for rank in (5, 4):
        A = rng.normal(size=(5, rank))
        S = A @ A.T  # rank-deficient for rank 4, as a circle's theta column
        b = S @ rng.normal(size=5)
        assert np.allclose(_pinv_sym(S, 1e-13), np.linalg.pinv(S, rcond=1e-13, hermitian=True), atol=1e-10)
        assert np.allclose(_solve_sym(S, b, 1e-14), np.linalg.lstsq(S, b, rcond=1e-14)[0], atol=1e-8)


def test_line_tls_closed_form_matches_svd():
    rng = np.random.default_rng(1)
    t = np.linspace(-50, 50, 200)
    xy = np.c_[3 + 0.8 * t, -2 + 0.6 * t] + rng.normal(0, 0.05, (200, 2))
    w = rng.uniform(0.5, 2.0, 200)
    n, c = _line_tls(xy, w)
    d = (xy - c) * np.sqrt(w)[:, None]
    ref = np.linalg.svd(d)[2][-1]
    assert abs(abs(n @ ref) - 1) < 1e-12


def test_ellipse_start_values_reach_the_same_minimum():
    rng = np.random.default_rng(2)
    phi = np.linspace(0.3, 2.5, 150)
    xy = ellipse_points([400, 300, 80, 50, 0.4], phi) + rng.normal(0, 0.05, (150, 2))
    cov = np.broadcast_to(0.0025 * np.eye(2), (150, 2, 2))
    a = fit_ellipse(xy, cov, corr_length=1.0)
    b = fit_ellipse(xy, cov, corr_length=1.0, start=a.params + [0.5, -0.3, 1.0, -0.5, 0.01])
    assert a.converged and b.converged
    u = np.sqrt(np.diag(a.cov))
    assert np.all(np.abs(a.params - b.params) < 1e-4 * u)
    assert np.allclose(a.cov, b.cov, rtol=1e-4, atol=0)


def test_along_edge_mean_matches_dense_form():
    rng = np.random.default_rng(3)
    phi = np.linspace(0, 4, 300)
    xy = np.c_[60 * np.cos(phi), 40 * np.sin(phi)]
    values = rng.normal(size=(300, 3))
    std = rng.uniform(0.01, 0.1, 300)
    d2 = ((xy[:, None, :] - xy[None, :, :]) ** 2).sum(-1)
    w = np.exp(-d2 / 8.0)
    w /= w.sum(axis=1, keepdims=True)
    rho = np.exp(-d2 / 4.0)
    a = w * std[None, :]
    var = ((a @ rho) * a).sum(axis=1)
    mean, sd = _along_edge_mean(xy, values, std, 2.0)
    assert np.allclose(mean, w @ values, rtol=0, atol=1e-12)
    assert np.allclose(sd, np.sqrt(var), rtol=1e-10)
