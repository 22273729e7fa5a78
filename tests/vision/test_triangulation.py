import cv2
import numpy as np
import pytest
from scipy.stats import chi2

from partinspect.vision.triangulation import correct_matches, fundamental_matrix, triangulate, triangulation_covariance

K1 = np.array([[7246.4, 0, 1224.5], [0, 7246.4, 1023.5], [0, 0, 1]])
K2 = np.array([[7251.0, 0, 1219.0], [0, 7251.0, 1030.0], [0, 0, 1]])
R = cv2.Rodrigues(np.array([0.002, -np.radians(17.1), 0.001]))[0]
T = -R @ np.array([120.0, 0.5, 1.0])


def project(X, K, R=np.eye(3), T=np.zeros(3)):
    x = (X @ R.T + T) @ K.T
    return x[:, :2] / x[:, 2:]


def scene(n, seed):
    rng = np.random.default_rng(seed)
    X = rng.uniform([-40, -35, 360], [40, 35, 440], (n, 3))
    return rng, X, project(X, K1), project(X, K2, R, T)


def test_noiseless_points_are_recovered_exactly():
    _, X, x1, x2 = scene(500, 0)
    assert np.abs(triangulate(x1, x2, K1, K2, R, T) - X).max() < 1e-9


def test_correction_matches_hartley_sturm():
    rng, X, x1, x2 = scene(300, 1)
    n1, n2 = x1 + rng.normal(0, 0.5, x1.shape), x2 + rng.normal(0, 0.5, x2.shape)
    F = fundamental_matrix(K1, K2, R, T)
    y1, y2 = correct_matches(n1, n2, F)
    r1, r2 = cv2.correctMatches(F, n1.reshape(1, -1, 2), n2.reshape(1, -1, 2))
    assert np.abs(y1 - r1.reshape(-1, 2)).max() < 1e-6
    assert np.abs(y2 - r2.reshape(-1, 2)).max() < 1e-6
    residual = np.einsum("ni,ij,nj->n", np.c_[y2, np.ones(len(y2))], F, np.c_[y1, np.ones(len(y1))])
    assert np.abs(residual).max() < 1e-12


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_covariance_is_honest(seed):
    """The true point lies in the 95 % ellipsoid 95 % of the time; Mahalanobis RMS matches."""
    rng, X, x1, x2 = scene(4000, seed)
    # Optimal triangulation is the ML estimate for isotropic image noise: test what it claims.
    iso = np.broadcast_to(np.eye(2) * 0.04, (len(X), 2, 2))
    noise1 = rng.normal(0, 0.2, x1.shape)
    noise2 = rng.normal(0, 0.2, x2.shape)
    Xh = triangulate(x1 + noise1, x2 + noise2, K1, K2, R, T)
    C = triangulation_covariance(Xh, iso, iso, K1, K2, R, T)
    e = Xh - X
    m = np.einsum("ni,nij,nj->n", e, np.linalg.inv(C), e)
    assert 0.93 <= np.mean(m < chi2.ppf(0.95, 3)) <= 0.97
    assert 0.9 <= np.sqrt(m.mean() / 3) <= 1.1
    # Depth is the worst-determined direction, as the paper observes.
    assert e[:, 2].std() > 2.5 * max(e[:, 0].std(), e[:, 1].std())
    assert np.allclose(C, np.transpose(C, (0, 2, 1))) and (np.linalg.eigvalsh(C) > 0).all()
