import numpy as np
import pytest
from scipy import ndimage

from partinspect.vision.edges import (
    edge_error_correlation, edge_points, gaussian_derivative_kernels, gradient, gradient_noise_std)
from tests.vision.synthetic import Disc, HalfPlane, render, render_clean


def _draws(shape, H, W, contrast=80.0, noise=2.0, seeds=range(4), margin=10):
    clean = render_clean([(shape, 60.0 + contrast)], H, W, background=60.0)
    blurred = ndimage.gaussian_filter(clean, 0.6, mode="nearest")
    err, std = [], []
    for seed in seeds:
        ep = edge_points(render([], H, W, blur=0, noise=noise, seed=seed, clean=blurred), 1.0)
        d = shape.distance(ep.xy)
        ok = ((ep.xy[:, 0] > margin) & (ep.xy[:, 0] < W - margin) & (ep.xy[:, 1] > margin)
              & (ep.xy[:, 1] < H - margin))
        assert np.all(np.abs(d[ok]) < 0.5), "spurious edge points"
        err.append(d[ok])
        std.append(ep.normal_std[ok])
    return np.concatenate(err), np.concatenate(std)


def test_kernels_unit_gain():
    g, d = gaussian_derivative_kernels(1.3)
    k = np.arange(len(d)) - len(d) // 2
    assert g.sum() == pytest.approx(1.0)
    assert (k * d).sum() == pytest.approx(1.0)
    ramp = np.tile(np.arange(40.0) * 2.5, (30, 1))
    gx, gy = gradient(ramp, 1.3)
    assert np.allclose(gx[10:-10, 10:-10], 2.5, atol=1e-4)
    assert np.allclose(gy[10:-10, 10:-10], 0.0, atol=1e-4)


def test_gradient_noise_std_matches_simulation_and_formula():
    rng = np.random.default_rng(0)
    gx, gy = gradient(rng.normal(0, 3.0, (400, 400)), 1.0)
    emp = np.concatenate([gx[20:-20, 20:-20].ravel(), gy[20:-20, 20:-20].ravel()]).std()
    assert gradient_noise_std(3.0, 1.0) == pytest.approx(emp, rel=0.03)
    assert gradient_noise_std(3.0, 2.0) == pytest.approx(3.0 / (2 * np.sqrt(2 * np.pi) * 4.0), rel=0.01)


@pytest.mark.parametrize("angle", [0.0, 0.2, 0.55, np.pi / 4])
def test_straight_edge_accuracy_and_predicted_std(angle):
    A, B = np.cos(angle), np.sin(angle)
    err, std = _draws(HalfPlane(A, B, -(A * 60.3 + B * 50.2)), 100, 120, contrast=60.0)
    assert np.sqrt(np.mean(err ** 2)) <= 0.05
    assert abs(err.mean()) < 0.01
    ratio = np.sqrt(np.mean(std ** 2)) / err.std()
    assert 0.8 <= ratio <= 1.2


def test_circular_edge_accuracy_and_predicted_std():
    err, std = _draws(Disc(100.3, 100.7, 60), 200, 200, contrast=60.0, seeds=range(3))
    assert np.sqrt(np.mean(err ** 2)) <= 0.05
    ratio = np.sqrt(np.mean(std ** 2)) / err.std()
    assert 0.8 <= ratio <= 1.2


def test_edge_error_correlation_along_vertical_edge():
    err = []
    hp = HalfPlane(1.0, 0.0, -60.3)
    clean = ndimage.gaussian_filter(render_clean([(hp, 160.0)], 120, 120, 60.0), 0.6, mode="nearest")
    for seed in range(6):
        ep = edge_points(render([], 120, 120, blur=0, noise=2.0, seed=seed, clean=clean), 1.0, noise=2.0)
        o = np.argsort(ep.xy[:, 1])
        xy = ep.xy[o]
        xy = xy[(xy[:, 1] > 10) & (xy[:, 1] < 110)]
        assert np.all(np.diff(xy[:, 1]) == 1.0)
        err.append(hp.distance(xy))
    e = np.array(err)
    e = e - e.mean()
    rho1 = (e[:, 1:] * e[:, :-1]).mean() / (e * e).mean()
    assert rho1 == pytest.approx(float(edge_error_correlation(1.0, 1.0)), abs=0.08)


def test_output_shapes_and_no_noise_points():
    rng = np.random.default_rng(1)
    img = np.clip(np.rint(100 + rng.normal(0, 2.0, (150, 150))), 0, 255).astype(np.uint8)
    ep = edge_points(img)
    assert len(ep) == 0  # thresholds from the noise: pure noise has no edges
    img = render([(Disc(70, 70, 30), 180.0)], 140, 140, noise=2.0, seed=2)
    ep = edge_points(img)
    n = len(ep)
    assert n > 150
    assert ep.xy.shape == (n, 2) and ep.cov.shape == (n, 2, 2) and ep.pixel.shape == (n, 2)
    assert np.allclose(np.linalg.norm(ep.normal, axis=1), 1.0)
    assert np.all(np.linalg.eigvalsh(ep.cov) > 0)
    assert len(np.unique(ep.pixel[:, 0] * 1000 + ep.pixel[:, 1])) == n
    # Gradient points from dark (outside) to bright (inside the disc).
    assert np.all(((np.array([70, 70]) - ep.xy) * ep.normal).sum(axis=1) > 0)
