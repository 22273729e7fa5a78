"""The calibration's error in triangulated points: it bends a rim, and the form's Monte Carlo must draw it."""

from dataclasses import replace

import numpy as np
import pytest

from partinspect.tolerances.form import circularity
from partinspect.vision.calibration import validate_calibration
from partinspect.vision.calibration_points import curve_tangents, point_responses, reread
from partinspect.vision.calibration_uncertainty import perturbed_calibration, uncertainty_directions
from partinspect.vision.correspondences import correspond
from partinspect.vision.matching import epipolar_geometry
from partinspect.vision.pointerrors import PointErrorModel
from tests.vision.test_matching import P1, P2, RIG, circle, feature

# Standard uncertainties of (fx, fy, cx, cy, k1..k3, p1, p2) per camera, then
# (rotation vector, rad; T, mm): a rig whose epipolar lines a draw moves by
# about a tenth of a pixel, as a board session's calibration does.
STD = np.r_[0.1, 0.1, 0.1, 0.1, 3e-4, 0, 0, 0, 0, 0.1, 0.1, 0.1, 0.1, 3e-4, 0, 0, 0, 0,
            3e-5, 3e-5, 3e-5, 0.01, 0.01, 0.01]
CALIB = validate_calibration(replace(RIG, std={}, cov=np.diag(STD**2)))
CENTER, NORMAL, RADIUS = [15.0, 5.0, 395.0], [0.2, -0.5, -0.8], 5.0


def drawn(seed):
    """A stated calibration: the true rig moved by one draw of its covariance, and that draw's deviates."""
    dirs = uncertainty_directions(CALIB)
    z = np.random.default_rng(seed).standard_normal(len(dirs))
    shift = {}
    for zj, d in zip(z, dirs):
        for k, v in d.items():
            shift[k] = shift.get(k, 0.0) + zj * v
    return perturbed_calibration(CALIB, shift), z


@pytest.fixture(scope="module")
def rim():
    X = circle(CENTER, NORMAL, RADIUS, n=300)
    return feature("arc", X, P1), feature("arc", X, P2)


def test_reread_and_tangents():
    xy = np.array([[100.0, 80.0], [600.0, 500.0], [1100.0, 950.0]])
    assert np.allclose(reread(xy, RIG.K1, RIG.D1)(RIG.K1, RIG.D1), xy, atol=1e-9)
    K = np.array(RIG.K1, float)
    K[0, 2] += 2.0
    # No distortion: the recorded pixels are the ideal ones whatever K is.
    assert np.allclose(reread(xy, RIG.K1, RIG.D1)(K, RIG.D1), xy, atol=1e-9)
    D = np.r_[0.05, 0.0, 0.0, 0.0, 0.0]
    moved = reread(xy, RIG.K1, RIG.D1)(RIG.K1, D)
    assert np.linalg.norm(moved[2] - xy[2]) > 1.0  # far from the centre a k1 moves points by pixels
    ell = np.array([600.0, 500.0, 40.0, 20.0, 0.3])
    ph = np.array([0.1, 1.7, 4.0])
    c, s = np.cos(ell[4]), np.sin(ell[4])
    p = ell[:2] + np.c_[ell[2] * np.cos(ph), ell[3] * np.sin(ph)] @ np.array([[c, s], [-s, c]])
    d = np.c_[-ell[2] * np.sin(ph), ell[3] * np.cos(ph)] @ np.array([[c, s], [-s, c]])
    t = curve_tangents(ell, p)
    assert np.allclose(np.abs(np.einsum("ni,ni->n", t, d / np.linalg.norm(d, axis=1)[:, None])), 1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_responses_predict_the_points_a_drawn_calibration_triangulates(rim, seed):
    """The first-order responses, times the draw's deviates, are where the drawn calibration puts the points."""
    fl, fr = rim
    stated, z = drawn(seed)
    true = correspond(fl, fr, epipolar_geometry(RIG))
    seen = correspond(fl, fr, epipolar_geometry(stated))
    G = point_responses(seen, stated)
    assert G.shape == (len(seen), 3, len(z))
    _, i0, i1 = np.intersect1d(true.left_index, seen.left_index, return_indices=True)
    moved = seen.points[i1] - true.points[i0]
    miss = moved - G[i1] @ z  # the stated rig is the true one moved by z along the directions
    assert np.sqrt(np.mean(moved**2)) > 0.02  # mm: the calibration's error is there
    assert np.sqrt(np.mean(miss**2)) < 0.05 * np.sqrt(np.mean(moved**2))
    assert point_responses(seen, RIG).shape == (len(seen), 3, 0)  # no stated uncertainty, nothing drawn


def test_circularity_carries_the_bend_of_a_drawn_calibration(rim):
    """A perfect rim triangulated through a drawn calibration reads out of round; with the
    calibration's part drawn, its true circularity (0) lies within +-2u; without, far outside."""
    fl, fr = rim
    stated, _ = drawn(0)
    seen = correspond(fl, fr, epipolar_geometry(stated))
    n = len(seen)
    # The points' own noise: 0.02 px across the edge, independent.
    model = PointErrorModel(np.arange(n, dtype=float), np.einsum("nij,nj->ni", seen.jac_left, fl.ideal.normal[seen.left_index]),
                            ((np.full(n, 0.02), 0.0),), calibration=point_responses(seen, stated))
    covs = model.covariances()
    without = circularity(seen.points, covs, np.random.default_rng(0), errors=model.draw)
    carried = circularity(seen.points, covs, np.random.default_rng(0), errors=model.draw, shared=model.draw_calibration)
    assert without.raw == carried.raw
    assert abs(without.value) > 5 * without.u
    assert abs(carried.value) < 2 * carried.u
    assert carried.u > 5 * without.u
    assert PointErrorModel(model.arc_length, model.normal_jacobian, model.components).draw_calibration(
        np.random.default_rng(0), 3) is None
