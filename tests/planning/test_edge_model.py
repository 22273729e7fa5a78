"""The edge-point noise model against the detector it predicts (partinspect.vision.edges)."""

from collections import defaultdict

import numpy as np
import pytest
from scipy.special import ndtr

from partinspect.planning.edge_model import DetectorModel, detector_parameters, edge_point_std, profile_width
from partinspect.vision.edges import edge_points


def _edge_image(angle, contrast, blur, size=72, offset=0.3):
    """A straight step edge through the image centre, blurred by blur and the pixel box."""
    y, x = np.mgrid[0:size, 0:size].astype(float)
    c = (size - 1) / 2 + offset
    d = (x - c) * np.cos(angle) + (y - c) * np.sin(angle)
    w = np.hypot(blur, np.sqrt(1 / 12))
    return 60.0 + contrast * ndtr(d / w), (np.cos(angle), np.sin(angle), -c * (np.cos(angle) + np.sin(angle)))


def test_formula_scales_and_default_value():
    s = edge_point_std(100.0, 2.0, 0.6, 1.0)
    assert s == pytest.approx(0.955 * np.sqrt(3 / 8) * 2.0 / 100.0 * profile_width(0.6, 1.0) ** 3, rel=1e-12)
    assert 0.019 < s < 0.024
    assert edge_point_std(50.0, 2.0) == pytest.approx(2 * s)
    assert edge_point_std(100.0, 4.0) == pytest.approx(2 * s)
    assert np.isinf(edge_point_std(0.0, 2.0))
    assert DetectorModel(noise=2.0).pixel_noise == pytest.approx(np.sqrt(4 + 1 / 12))


@pytest.mark.parametrize("deg", [3.0, 20.0, 38.0])
def test_close_to_the_detectors_own_first_order_std(deg):
    img, _ = _edge_image(np.deg2rad(deg), 80.0, 0.6)
    e = edge_points(img, 1.0, noise=2.0)
    inner = (np.abs(e.xy - 36).max(axis=1) < 26) & (e.strength > 5)
    ratio = np.median(e.normal_std[inner]) / edge_point_std(80.0, 2.0, 0.6, 1.0)
    assert 0.9 < ratio < 1.05, ratio


@pytest.mark.parametrize("deg, contrast", [(4.0, 120.0), (30.0, 50.0)])
def test_matches_the_scatter_of_detected_points(deg, contrast):
    """Each pixel's edge point over noise draws of an 8-bit image: the model's std."""
    angle = np.deg2rad(deg)
    img, (a, b, c) = _edge_image(angle, contrast, 0.6)
    rng = np.random.default_rng(3)
    noise = DetectorModel(noise=2.0).pixel_noise
    per = defaultdict(list)
    for _ in range(40):
        e = edge_points(np.clip(np.rint(img + 2.0 * rng.standard_normal(img.shape)), 0, 255), 1.0, noise=noise)
        r = e.xy @ np.array([a, b]) + c
        for k in np.flatnonzero((np.abs(e.xy - 36).max(axis=1) < 26) & (np.abs(r) < 1.0)):
            per[tuple(e.pixel[k])].append(r[k])
    var = [np.var(v, ddof=1) for v in per.values() if len(v) >= 30]
    assert len(var) > 30
    ratio = np.sqrt(np.mean(var)) / edge_point_std(contrast, noise, 0.6, 1.0)
    assert 0.9 < ratio < 1.12, ratio


def test_one_point_per_pixel_of_the_dominant_axis():
    t = np.linspace(0.0, 100.0, 2001)
    ang = np.deg2rad(30.0)
    uv = np.c_[t * np.cos(ang), t * np.sin(ang)]
    tp = detector_parameters(t, uv)
    assert len(tp) == int(100 * np.cos(ang))
    assert np.allclose(np.diff(tp), 1 / np.cos(ang), rtol=0.01)


def test_a_piece_thrown_off_by_the_distortion_polynomial_gets_no_points():
    """Far outside the image the distortion polynomial throws a projected
    edge millions of px away (NIST ctc_02's plan asked for 186 million
    samples of one arc, 23 GB, and was killed); only the part near the
    image counts."""
    from partinspect.planning.edge_model import near_image

    t = np.linspace(0.0, 300.0, 3001)
    uv = np.c_[t + 50.0, np.full_like(t, 40.0)]
    wild = (t > 100.0) & (t < 200.0)
    uv[wild, 0] = 1e8 * (t[wild] - 100.0)
    valid = near_image(uv, (400, 300))
    assert not valid[wild].any() and valid[~wild].all()
    tp = detector_parameters(t, uv, valid=valid)
    assert len(tp) == 200 and not ((tp > 100.0) & (tp < 200.0)).any()
    assert np.abs(np.diff(uv[:, 0])).sum() > 1e9  # the points it would have been asked for
    assert not near_image(np.array([[np.nan, 0.0], [-401.0, 0.0], [0.0, 601.0]]), (400, 300)).any()


@pytest.mark.parametrize("deg", [3.0, 20.0, 44.0])
def test_stated_std_pattern_states_what_the_detector_states(deg):
    """Per point, the uncertainty the detector gives a noise-free edge at the
    point's direction and sub-pixel phase, and a scatter factor of the size
    the noisy magnitudes give it."""
    from partinspect.planning.edge_model import stated_std_pattern
    from tests.vision.synthetic import HalfPlane, render_optics

    th = np.deg2rad(deg)
    hp = HalfPlane(-np.sin(th), np.cos(th), -(-np.sin(th) * 60.3 + np.cos(th) * 60.2))
    model = DetectorModel()
    e = edge_points(render_optics([(hp, 140.0)], 120, 120, 60.0, model.blur), 1.0, noise=model.pixel_noise)
    inner = (np.abs(e.xy - 60).max(axis=1) < 40) & (np.abs(hp.distance(e.xy)) < 1)
    xy, n = e.xy[inner], e.normal[inner]
    order = np.argsort(xy @ np.array([np.cos(th), np.sin(th)]))
    std, pattern = stated_std_pattern(xy[order], n[order], np.full(len(xy), 80.0), model)
    np.testing.assert_allclose(std, e.normal_std[inner][order], rtol=0.03)
    # Near 45 deg the detector states more than the direction-free formula.
    ratio = np.median(std) / edge_point_std(80.0, model.pixel_noise, model.blur, model.sigma)
    assert (ratio > 1.025) if deg == 44.0 else (0.97 < ratio < 1.02), ratio
    assert 0.02 < np.std(np.log(pattern)) < 0.08
    np.testing.assert_array_equal(pattern, stated_std_pattern(xy[order], n[order], np.full(len(xy), 80.0), model)[1])
