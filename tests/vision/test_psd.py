"""Ill-conditioned covariances propagate and draw alike (issue: the planner's crash on the plate)."""

from pathlib import Path

import numpy as np
import pytest

from partinspect.tolerances.form import _across, _across_sd, _circle_reference, circularity
from partinspect.vision.pointerrors import PointErrorModel
from partinspect.vision.psd import covariance_factor

# A far rim's 24 deg sliver (a 4 mm hole, 23 points) as `inspect plan` predicted it for
# the bundled plate: its right ellipse fit's covariance spans 1e-6 to 2e5 and is
# asymmetric by 1e-7 of its entries, as the sandwich product's rounding leaves it.
CASE = Path(__file__).resolve().parents[1] / "data" / "regressions" / "short_arc_point_errors.npz"


def _model(common_cov=None):
    d = np.load(CASE)
    comps = tuple((s, float(l)) for s, l in zip(d["comp_std"], d["comp_length"]))
    cov = d["common_cov"] if common_cov is None else common_cov
    return d["points"], PointErrorModel(d["arc_length"], d["normal_jacobian"], comps, d["common_jacobian"], cov,
                                        tuple(int(k) for k in d["systematic"]), float(d["outlier_z"]))


def test_factor_is_the_nearest_psd_matrix_and_exact_on_a_covariance():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((5, 5))
    C = A @ A.T
    L = covariance_factor(C)
    np.testing.assert_allclose(L @ L.T, C, rtol=1e-12, atol=1e-12)
    bad = np.diag([4.0, 1.0, -1e-3]) + np.triu(np.full((3, 3), 1e-4), 1)  # indefinite, asymmetric
    S = covariance_factor(bad) @ covariance_factor(bad).T
    np.testing.assert_allclose(S, S.T)
    assert np.linalg.eigvalsh(S).min() >= -1e-15
    np.testing.assert_allclose(np.diag(S)[:2], [4.0, 1.0], atol=1e-6)


@pytest.mark.parametrize("variant", ["stored", "lower", "upper"])
def test_short_arc_draws_match_its_covariances_whatever_the_rounding(variant):
    """The same covariance rounded another way (another processor's sums): the draws still
    scatter as the stated covariances say, no variance is negative, and the
    circularity's noise-only zone is simulated; before, the lower-triangle reading
    gave negative variances and the stored one draws twice the stated spread."""
    d = np.load(CASE)
    C = d["common_cov"]
    C = {"stored": C, "lower": np.tril(C) + np.tril(C, -1).T, "upper": np.triu(C) + np.triu(C, 1).T}[variant]
    P, model = _model(C)
    covs = model.covariances()
    assert np.linalg.eigvalsh(covs).min() > -1e-12
    ideal, axis = _circle_reference(P)
    sd = _across_sd(covs, ideal, axis)
    e = model.draw(np.random.default_rng(1), 4000)
    ratio = np.sqrt((_across(e, ideal, axis) ** 2).mean(0)) / sd
    assert np.all(np.abs(ratio - 1) < 0.08), ratio
    r = circularity(P, covs, np.random.default_rng(0), errors=model.draw, outlier_z=model.outlier_z)
    assert np.isfinite(r.value) and 0 < r.u < 0.02
