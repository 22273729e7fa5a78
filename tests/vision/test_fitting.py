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


def test_stacked_ellipse_fits_follow_each_fit_alone():
    # fit_ellipses runs several fits in lockstep (padded arrays, their own
    # damping each): every fit must take the path it takes alone, down to
    # its iteration count, including one that does not converge.
    from partinspect.vision.fitting import EllipseJob, fit_ellipses

    rng = np.random.default_rng(5)
    jobs = []
    for k, (m, span, cov_kind) in enumerate([(12, 1.2, "full"), (40, 2.5, "full"), (90, 6.3, "normal"),
                                             (25, 0.9, "none"), (300, 6.0, "full"), (14, 0.5, "full")]):
        P = np.array([100.0 + 10 * k, 80.0, 45.0 + 5 * k, 30.0, 0.3 * k - 0.5])
        xy = ellipse_points(P, np.linspace(0.1, 0.1 + span, m)) + rng.normal(0, 0.03, (m, 2))
        s2 = rng.uniform(0.5, 1.5, m) * 0.03 ** 2
        cov = {"full": s2[:, None, None] * np.array([[1.0, 0.2], [0.2, 0.8]]), "normal": s2, "none": None}[cov_kind]
        jobs.append(EllipseJob(xy, cov, 1.0))
    alone = [fit_ellipse(j.xy, j.cov, corr_length=j.corr_length, max_iter=10) for j in jobs]
    # Twice over: more than eight fits take the stacked solve, fewer the
    # per-fit one.
    together = fit_ellipses(jobs + jobs, max_iter=10)
    assert not all(f.converged for f in alone)  # the stop at max_iter is exercised
    for a, b in zip(alone + alone, together):
        assert (a.converged, a.iterations) == (b.converged, b.iterations)
        if a.converged:
            assert np.allclose(a.params, b.params, rtol=0, atol=1e-7)
            assert np.allclose(a.cov, b.cov, rtol=1e-6, atol=0)
            assert a.consistency.p_value == pytest.approx(b.consistency.p_value, rel=1e-9)
    # need_converged drops the unconverged fits only.
    kept = fit_ellipses(jobs, max_iter=10, need_converged=True)
    assert [f is not None for f in kept] == [f.converged for f in alone]
    # With blur (the segment refits), as fit_ellipse with blur alone.
    blurred = [EllipseJob(j.xy, j.cov, 1.0, 1.2, a.params) for j, a in zip(jobs, alone) if a.converged]
    for job, b in zip(blurred, fit_ellipses(blurred)):
        a = fit_ellipse(job.xy, job.cov, corr_length=1.0, blur=1.2, start=job.start)
        assert a.iterations == b.iterations and np.allclose(a.params, b.params, rtol=0, atol=1e-7)
        assert np.allclose(a.residuals, b.residuals, rtol=0, atol=1e-7)


def test_ellipse_fit_is_the_least_squares_minimum():
    # The Gauss-Newton steps of _lm_ellipses use the normal equations in a
    # rearranged form; the minimum they reach must be that of a generic
    # solver on the full problem (parameters and one phase per point).
    from scipy.optimize import least_squares

    rng = np.random.default_rng(6)
    P = np.array([200.0, 150.0, 60.0, 35.0, 0.4])
    phi = np.linspace(-0.5, 2.0, 50)
    xy = ellipse_points(P, phi) + rng.normal(0, 0.05, (50, 2))
    cov = rng.uniform(0.5, 2.0, 50)[:, None, None] * np.array([[0.0025, 0.0005], [0.0005, 0.0016]])
    f = fit_ellipse(xy, cov)
    assert f.converged
    # Weights as the fit's at its minimum (inverse variance along the normal).
    w = 1.0 / f.point_std ** 2

    def resid(x):
        d = xy - ellipse_points(x[:5], x[5:])
        return (d * np.sqrt(w)[:, None]).ravel()

    ref = least_squares(resid, np.r_[f.params + [0.3, -0.2, 0.5, -0.3, 0.01], f.phases], xtol=1e-15, ftol=1e-15,
                        gtol=1e-15)
    assert np.allclose(ref.x[:5], f.params, rtol=0, atol=1e-6)


def test_band_and_information_matrices_match_the_loop_over_offsets():
    from partinspect.vision.fitting import information_matrices, trace_r2

    rng = np.random.default_rng(7)
    for n, closed, cl in [(2, False, 1.0), (7, True, 1.0), (40, False, 1.0), (40, True, 3.0), (200, False, 0.5),
                          (30, False, None)]:
        t = np.linspace(0, 2 * np.pi if closed else 2.0, n, endpoint=not closed)
        xy = np.c_[20 * np.cos(t), 15 * np.sin(t)]
        ref = []
        for k in range(1, n // 2 + 1 if cl else 1):
            d2 = ((np.roll(xy, -k, axis=0) - xy) ** 2).sum(axis=1)
            rho = np.exp(-d2 / (4 * cl * cl)) * (0.5 if k == n - k else 1.0)
            if rho.max() < 1e-4:
                break
            ref.append((k, rho))
        h, s = rng.normal(size=(n, 3)), rng.uniform(0.5, 1.0, n)
        hw = h / s[:, None]
        M = hw.T @ hw
        for k, rho in ref:
            C = (hw * rho[:, None]).T @ np.roll(hw, -k, axis=0)
            M += C + C.T
        S2, M2, trR2 = information_matrices(h, s, xy, cl)
        assert np.allclose(M2, M, rtol=1e-12, atol=1e-12 * np.abs(M).max())
        assert trR2 == pytest.approx(n + 2 * sum(float(r @ r) for _, r in ref), rel=1e-13)
        assert trace_r2(xy, cl) == trR2
