"""The Type B level a fit's residuals show, on residuals drawn with a known level."""

import numpy as np
import pytest

from partinspect.vision.bias_evidence import bias_evidence, correlation_matrix
from partinspect.vision.fit3d import View

N, RADIUS = 200, 60.0


def _views():
    t = np.linspace(0.0, 2 * np.pi, N, endpoint=False)
    xy = RADIUS * np.c_[np.cos(t), np.sin(t)] + 200.0
    view = View(xy, np.full(N, 0.01), np.eye(3, 4), 1.0, np.full(N, 0.02), 0.2 * RADIUS)
    return [view, view], t


def _draws(k, n_draws, seed):
    """Weighted residuals of a 2-D circle fit (centre and radius taken up) to errors with Type B level k."""
    views, t = _views()
    v = views[0]
    Rn = correlation_matrix(v.xy, v.corr_length).toarray()
    Rb = correlation_matrix(v.xy, v.bias_corr_length).toarray()
    S = 0.01 ** 2 * Rn + (k * 0.02) ** 2 * Rb
    L = np.linalg.cholesky(S + 1e-14 * np.eye(N))
    tot = v.total_sigma
    J1 = -np.c_[np.cos(t), np.sin(t), np.ones(N)] / tot[:, None]
    J = np.block([[J1, np.zeros((N, 3))], [np.zeros((N, 3)), J1]])
    Q, _ = np.linalg.qr(J)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_draws):
        e = np.concatenate([L @ rng.standard_normal(N), L @ rng.standard_normal(N)]) / np.r_[tot, tot]
        r = e - Q @ (Q.T @ e)
        out.append(bias_evidence(views, r, J))
    return np.array(out)


@pytest.mark.parametrize("k", [0.0, 1.0])
def test_level_is_recovered(k):
    est = _draws(k, 30, seed=int(10 * k))
    k2, se = est[:, 0], est[:, 1]
    # Unbiased: the mean of 30 estimates within 4 of its standard errors
    # (the spread grows with the systematic part itself, so it is taken
    # from the draws).
    assert abs(k2.mean() - k * k) < 4 * k2.std() / np.sqrt(len(k2)) + 0.01
    if k == 0.0:
        # The stated standard error is the spread under noise alone.
        assert se.mean() == pytest.approx(k2.std(), rel=0.35)


def test_no_systematic_part_gives_none():
    views, _ = _views()
    plain = [View(v.xy, v.sigma, v.P, v.corr_length) for v in views]
    assert bias_evidence(plain, np.zeros(2 * N), np.ones((2 * N, 1))) is None


def test_type_b_scale_is_floored_when_the_residuals_show_less_than_the_noise(monkeypatch):
    # k2 far below zero (residuals smaller than the stated noise predicts) once
    # made the bound negative and the scale NaN, which reached the centre's
    # covariance and stopped the run in an eigen-decomposition.
    from partinspect.vision import rim_errors

    views, _ = _views()
    monkeypatch.setattr(rim_errors, "circle_residuals_at", lambda views, fit: (np.zeros(2 * N), np.zeros((2 * N, 6))))
    monkeypatch.setattr(rim_errors, "bias_evidence", lambda views, r, J: (-0.5, 0.01))
    scale = rim_errors.type_b_scale(views, None)
    assert np.isfinite(scale)
    assert scale == pytest.approx(rim_errors.RIM_DETECTOR_ERROR / 0.02)
