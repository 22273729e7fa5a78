"""The sub-pixel phase ripple of line points: read from the residuals, removed, its error carried."""

import numpy as np
import pytest

from partinspect.vision.pixel_phase import HARMONICS, RIPPLE_P, line_phase, phase_ripple, sampling_phase
from partinspect.vision.stereo import measure_images
from tests.vision.synthetic import rectangle, render

K = np.array([[1000.0, 0.0, 160.0], [0.0, 1000.0, 120.0], [0.0, 0.0, 1.0]])
D = np.zeros(5)


def _line_points(n=300, slope=0.2, corr_length=1.0, sigma=0.01, seed=0):
    """Points along y = 50 + slope x found along the y axis, with noise correlated as the edge filter's."""
    rng = np.random.default_rng(seed)
    x = np.arange(n, dtype=float)
    y = 50.3 + slope * x
    phase = y - np.round(y)
    # Noise correlated as exp(-d^2 / (4 l^2)): white noise smoothed by a Gaussian of std l.
    from scipy.ndimage import gaussian_filter1d
    w = gaussian_filter1d(rng.standard_normal(n + 40), corr_length * np.hypot(1, slope))[20:-20]
    noise = sigma * w / w.std()
    normal = np.array([-slope, 1.0]) / np.hypot(1, slope)
    return np.column_stack([x, y]), normal, phase, noise


def test_sampling_phase_is_the_offset_along_the_search_axis():
    pixel = np.array([[10, 20], [10, 20]])          # (row, column)
    uv = np.array([[20.3, 10.0], [20.0, 9.6]])      # found along x, then along y
    assert sampling_phase(uv, pixel) == pytest.approx([0.3, -0.4])


def test_a_ripple_locked_to_the_phase_is_read_with_its_uncertainty():
    """Over 60 noise draws the first harmonic's error / u has RMS near 1, and the ripple is found every time."""
    z, found = [], 0
    for seed in range(60):
        xy, normal, phase, noise = _line_points(seed=seed)
        r = 0.012 * np.sin(2 * np.pi * phase) + noise
        rip = phase_ripple(xy, normal, r - r.mean(), np.full(len(r), 0.01), phase, 1.0)
        z.append((rip.coefficients[0] - 0.012) / np.sqrt(rip.covariance[0, 0]))
        found += rip.significant
    assert found == 60
    assert 0.7 < np.sqrt(np.mean(np.square(z))) < 1.3


def test_noise_alone_is_left_as_it_is():
    """Without a ripple the test rejects at about its level: no clean line is 'corrected'."""
    p = []
    for seed in range(200):
        xy, normal, phase, noise = _line_points(seed=1000 + seed)
        p.append(phase_ripple(xy, normal, noise - noise.mean(), np.full(len(noise), 0.01), phase, 1.0).p_value)
    assert np.mean(np.asarray(p) < RIPPLE_P) < 0.04


def test_a_real_bend_of_the_edge_is_not_taken_for_a_ripple():
    """A bow of the part (not locked to the pixel grid) stays in the points: what is removed is a fraction of it."""
    xy, normal, phase, noise = _line_points(seed=7)
    s = (xy[:, 0] - xy[:, 0].mean()) / np.ptp(xy[:, 0])
    bow = 0.03 * (1 - 4 * s * s)
    r = bow - bow.mean() + noise
    rip = phase_ripple(xy, normal, r, np.full(len(r), 0.01), phase, 1.0)
    assert np.ptp(rip.displacement) < 0.2 * np.ptp(bow)


def test_degenerate_lines_give_no_ripple():
    xy, normal, phase, noise = _line_points(n=5)
    assert phase_ripple(xy, normal, noise, np.full(5, 0.01), phase, 1.0) is None
    xy, normal, _, noise = _line_points()
    constant = np.full(len(xy), 0.25)   # a phase that never moves cannot be told from the line's offset
    assert phase_ripple(xy, normal, noise, np.full(len(xy), 0.01), constant, 1.0) is None


def test_a_sharp_lens_pixel_locking_is_removed_from_the_lines():
    """Exact optics (blur 0.3 px, pixel integration, not the project's renderer), edges 11 degrees off the axis.

    There the log-parabola's vertex locks to the pixels by about 0.01 px RMS;
    the corrected points lie on the true edge within a third of that, and each
    corrected line carries its correction's error factor.
    """
    poly = rectangle(160.3, 120.2, 220, 150, 0.2)
    img = render([(poly, 200.0)], 240, 320, background=40.0, blur=0.3, noise=0.5, seed=1)
    res = measure_images(img, K, D)
    lines = [f for f in res.features if f.kind == "line" and len(f.index) > 80]
    assert len(lines) == 4
    for f in lines:
        before = poly.distance(res.edges.xy[f.index])
        after = poly.distance(f.uv)
        assert f.phase_factor is not None and f.phase_factor.shape == (len(f.index), len(HARMONICS))
        assert np.std(before) > 0.008
        assert np.std(after) < 0.4 * np.std(before)
        # The correction's error is small beside the points' own noise.
        assert np.sqrt(np.mean(np.sum(f.phase_factor ** 2, axis=1))) < 0.3 * np.median(f.fit.point_std)


def test_near_45_degrees_each_search_axis_has_its_own_ripple():
    """Points found along x and along y, their ripples of opposite sign (the normal's components): both are read."""
    xy, normal, phase, noise = _line_points(n=400, slope=0.97, seed=3)
    axis = (np.arange(len(xy)) // 7) % 2          # the search axis changes in runs along the edge
    truth = np.where(axis == 0, 0.012, -0.012) * np.sin(2 * np.pi * phase)
    r = truth + noise
    one = phase_ripple(xy, normal, r - r.mean(), np.full(len(r), 0.01), phase, 1.0)
    two = phase_ripple(xy, normal, r - r.mean(), np.full(len(r), 0.01), phase, 1.0, axis)
    assert two.coefficients[[0, 2]] == pytest.approx([0.012, -0.012], abs=4 * np.sqrt(two.covariance[0, 0]))
    assert np.std(r - two.displacement) < 0.8 * np.std(r - one.displacement)


def test_line_phase_is_where_the_fitted_line_crosses_the_search_axis():
    """A point found 0.1 px off a 45-degree line along x: the line crosses that axis 0.1 * sqrt(2) px away."""
    normal = np.array([1.0, -1.0]) / np.sqrt(2.0)
    pixel = np.array([[10, 20], [11, 20]])                  # (row, column)
    uv = np.array([[20.3, 10.0], [20.0, 11.2]])             # found along x, then along y
    residuals = np.array([0.1, -0.1])
    assert line_phase(uv, pixel, residuals, normal) == pytest.approx([0.3 - 0.1 * np.sqrt(2), 0.2 - 0.1 * np.sqrt(2)])


@pytest.mark.parametrize("angle", [0.0, np.pi / 4])
def test_noise_on_a_line_whose_phase_stands_still_is_not_taken_for_a_ripple(angle):
    """Along an image axis or at 45 degrees an edge crosses every pixel at one phase, so no ripple can show.

    Harmonics of each point's own phase (the edge's plus the point's noise)
    would regress the residuals on their own noise and remove it: the points'
    scatter about the true edge stays what the detector left.
    """
    poly = rectangle(160.3, 120.2, 150, 110, angle)
    img = render([(poly, 200.0)], 240, 320, background=40.0, blur=1.0, noise=2.0, seed=2)
    res = measure_images(img, K, D)
    lines = [f for f in res.features if f.kind == "line" and len(f.index) > 40]
    assert len(lines) == 4
    for f in lines:
        assert f.phase_factor is None
        assert np.std(poly.distance(f.uv)) == pytest.approx(np.std(poly.distance(res.edges.xy[f.index])), rel=1e-6)
