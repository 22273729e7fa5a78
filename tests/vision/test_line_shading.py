"""A line's Type B for the shading beside it (issue 39): one offset per image, carried into the 3D line's covariance.

A 3D edge seen by a toed-in rig, its face in the left image shaded as a
curved face near grazing incidence (grey rising as the square root of the
distance from the edge), in the right image uniform: the left image's
points lie off the true edge's image, all alike, which the 3D line's fit
cannot see in its residuals.
"""

import numpy as np
import pytest
from scipy.special import chdtri

from partinspect.vision.stereo import measure_stereo
from tests.vision.synthetic import render_profile, toed_in_rig

SIZE = (320, 240)
POINT = np.array([0.3, 0.0, 300.0])
DIRECTION = np.array([0.15, 1.0, 0.1]) / np.linalg.norm([0.15, 1.0, 0.1])
DARK, FACE = 40.0, 200.0


def _step(u):
    return np.where(u < 0, DARK, FACE)


def _grazing(u):
    """A face whose grey falls towards the edge as on a surface seen near grazing incidence: 160 at it, 200 at 8 px."""
    return np.where(u < 0, DARK, 160.0 + (FACE - 160.0) * np.sqrt(np.clip(u, 0, 8) / 8))


def _image(calib, i, profile, seed):
    K, _, R, t = calib.camera(i)
    x = (np.array([POINT - 20 * DIRECTION, POINT + 20 * DIRECTION]) @ R.T + t) @ K.T
    a, b = x[:, :2] / x[:, 2:]
    d = (b - a) / np.linalg.norm(b - a)
    img = render_profile(profile, a, (-d[1], d[0]), SIZE)
    return np.clip(np.rint(img + np.random.default_rng(seed).normal(0.0, 2.0, img.shape)), 0, 255)


def _line_error(left_profile, seed=0):
    """The measured line's error across it (mm) and its squared Mahalanobis distance there (2 dof)."""
    calib = toed_in_rig(SIZE)
    res = measure_stereo(_image(calib, 0, left_profile, seed), _image(calib, 1, _step, seed + 100), calib,
                         parallel=False)
    lines = [f for f in res.features if f.kind == "line"]
    assert len(lines) == 1
    f = lines[0]
    across = np.linalg.svd(np.eye(3) - np.outer(f.direction, f.direction))[0][:, :2]
    e = across.T @ (POINT - f.point)
    return f, float(np.linalg.norm(e)), float(e @ np.linalg.solve(across.T @ f.covariance @ across, e))


def test_a_line_beside_a_grazing_face_states_the_offset_its_shading_gives_it():
    f, err, m2 = _line_error(_grazing)
    # the shading moves the line far beyond its image noise (about 1 um of it): 32 um
    assert err > 0.02
    # within chance of its stated covariance (chi-square, 2 dof, 99.9 %); without the
    # shading's Type B, 1800
    assert m2 < chdtri(2, 1e-3)
    # and that is the shading's Type B, in the systematic part
    assert np.trace(f.param_cov_systematic) > 10 * np.trace(f.param_cov_image)


def test_a_line_between_faces_of_uniform_grey_keeps_none():
    f, err, m2 = _line_error(_step)
    assert err < 0.003
    assert not np.any(f.param_cov_systematic)
    assert m2 < chdtri(2, 1e-3)


def test_the_line_offset_is_read_from_the_median_bound():
    from partinspect.vision.stereo import LINE_BOUND_READING, line_type_b

    # the few points near an end that read another edge do not set it
    bound = np.r_[np.full(40, 0.05), np.full(5, 2.0)]
    assert line_type_b(bound) == pytest.approx(LINE_BOUND_READING * 0.05)
    assert line_type_b(np.zeros(30)) == 0.0
    assert line_type_b(None) == 0.0
    # the rims' correction (1.4 times the first-order shift) and what it leaves (0.75 times the bound)
    assert LINE_BOUND_READING == pytest.approx(np.hypot(1.4, 0.75))


def _band(flank, depth=62.0):
    """A flat face, then a band ``depth`` below it: its flank from ``flank`` px to its floor at 3.7 px, back up by 6 px.

    A fillet's band seen near grazing incidence beside a narrow face; with
    the flank within 2 px the shading reading 3-4 px off the edge misses it.
    """
    return lambda u: np.where(u < 0, DARK, FACE - depth * np.clip(np.minimum((u - flank) / (3.7 - flank),
                                                                            (6.0 - u) / 2.3), 0, 1))


@pytest.mark.parametrize("flank", [1.5, 2.0])
def test_a_line_beside_a_narrow_band_states_the_offset_the_band_gives_it(flank):
    # seed 1: with the band, seed 0 finds no line to match (the right image's uniform face does)
    f, err, m2 = _line_error(_band(flank), seed=1)
    # the band moves the line 40-50 um, 50 times its image noise
    assert err > 0.03
    # within chance at 95 % (2 dof); the shading reading alone left 7.7 (flank 1.5 px)
    # and 2.3 (2.0 px): it reads the band's floor, past its flank
    assert m2 < chdtri(2, 0.05)
    assert np.trace(f.param_cov_systematic) > 10 * np.trace(f.param_cov_image)


def _one_image(profile, seed, noise=2.0):
    """One image of a straight edge with ``profile`` across it; its edge points near the line, and their offsets."""
    from partinspect.vision.edges import edge_points
    from tests.vision.synthetic import render_profile

    normal, point = np.array([np.cos(0.05), np.sin(0.05)]), np.array([40.3, 40.0])
    img = render_profile(profile, point, normal, (90, 80))
    img = np.clip(np.rint(img + np.random.default_rng(seed).normal(0.0, noise, img.shape)), 0, 255)
    ep = edge_points(img, 1.0, noise=noise)
    offset = (ep.xy - point) @ normal
    near = (np.abs(offset) < 1.0) & (ep.xy[:, 1] > 10) & (ep.xy[:, 1] < 70)
    return img, ep.xy[near], ep.normal[near], offset[near]


@pytest.mark.parametrize("flank", [1.0, 1.5, 2.0, 2.5])
def test_the_band_reading_gives_most_of_the_displacement_a_band_causes(flank):
    from partinspect.vision.line_profile import line_band_shift

    img, xy, normal, offset = _one_image(_band(flank), seed=1)
    found = np.median(offset)
    # the band pulls the edge towards it: -0.07 to -0.17 px
    assert found < -0.05
    shift = line_band_shift(img, xy, normal)
    # same sign, 70-100 % of it (the model's band is two blurred steps, the
    # rendered one two linear flanks)
    assert 0.7 < shift / found < 1.0


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_band_reading_is_zero_beside_uniform_faces(seed):
    from partinspect.vision.line_profile import line_band_shift

    img, xy, normal, offset = _one_image(_step, seed)
    assert len(xy) > 50
    assert line_band_shift(img, xy, normal) == 0.0


def test_the_band_model_moves_the_detector_towards_a_dark_band_and_not_without_one():
    from partinspect.vision.line_profile import band_displacement

    # no band: the maximum stays on the step
    assert abs(band_displacement(160.0, 0.0, 2.0, 0.7, 0.7, 2.0)) < 1e-3
    # a dark band on the bright side pulls the gradient's maximum away from it (to negative offsets) ...
    near = band_displacement(160.0, -60.0, 1.5, 0.7, 0.7, 2.0)
    far = band_displacement(160.0, -60.0, 3.0, 0.7, 0.7, 2.0)
    assert near < far < 0
    # ... and a bright one towards it; mirrored, the same amount
    assert band_displacement(160.0, 60.0, 1.5, 0.7, 0.7, 2.0) > 0
    assert band_displacement(-160.0, -60.0, -1.5, 0.7, 0.7, 2.0) == pytest.approx(-near, abs=0.01)


@pytest.mark.parametrize("q, lin", [((0.2, 0.8, 2.1, 0.9, 1.7), (40.0, 160.0, -60.0)),
                                    ((-0.1, 0.6, -1.5, 1.3, 3.0), (200.0, -150.0, 30.0))])
def test_the_band_models_derivatives_are_its_central_differences(q, lin):
    from partinspect.vision.line_profile import _design, _model_jacobian, _projected_jacobian, _projected_residuals

    t, q, lin = np.arange(-6.0, 6.01, 0.25), np.array(q), np.array(lin)
    grey = _design(t, *q) @ lin + 5.0 * np.sin(3.0 * t)  # a misfit, so the projection's second term counts
    dq = 1e-6 * np.eye(5)
    model = np.stack([(_design(t, *(q + e)) - _design(t, *(q - e))) @ lin / 2e-6 for e in dq], axis=1)
    assert _model_jacobian(t, q, lin) == pytest.approx(model, abs=1e-6 * np.abs(model).max())
    R = _projected_residuals(t, grey, np.vstack([q + dq, q - dq]))
    projected = ((R[:5] - R[5:]) / 2e-6).T
    assert _projected_jacobian(t, grey, q) == pytest.approx(projected, abs=1e-6 * np.abs(projected).max())
