import numpy as np
import pytest

from partinspect.simulate.rig import (
    BASELINE,
    FOCAL_LENGTH,
    FULL_SIZE,
    PIXEL_PITCH,
    WORKING_DISTANCE,
    default_rig,
)
from partinspect.poses import fixation_point
from partinspect.vision.calibration import camera_pose, project_points, read_calibration, undistort_points, write_calibration


def _border_round_trip(K, D, size, step):
    """Largest px error of the image border (every ``step`` px) undistorted and projected back: tiny
    unless the distortion model folds the image over somewhere."""
    W, H = size
    xs, ys = np.arange(0, W, step, dtype=float), np.arange(0, H, step, dtype=float)
    border = np.concatenate([np.stack([xs, np.zeros_like(xs)], 1), np.stack([xs, np.full_like(xs, H - 1)], 1),
                             np.stack([np.zeros_like(ys), ys], 1), np.stack([np.full_like(ys, W - 1), ys], 1)])
    xb = undistort_points(border, K, D)
    return np.abs(project_points(np.c_[xb, np.ones(len(xb))], K, D) - border).max()


def test_full_size_numbers():
    rig = default_rig()
    assert rig.image_size == (2448, 2048)
    f = FOCAL_LENGTH / PIXEL_PITCH
    assert f == pytest.approx(7246.4, abs=0.1)
    centre = np.array([(2448 - 1) / 2, (2048 - 1) / 2])
    offsets = []
    for K in (rig.K1, rig.K2):
        assert K[0, 0] == pytest.approx(f, rel=2e-3)
        assert K[0, 0] == K[1, 1] and K[0, 1] == 0  # square pixels, no skew
        off = np.linalg.norm(K[:2, 2] - centre)
        assert 1.0 < off < 30.0  # near, but not exactly at, the centre
        offsets.append(K[:2, 2] - centre)
    assert not np.allclose(offsets[0], offsets[1])
    assert rig.baseline == pytest.approx(BASELINE, abs=1e-9)
    np.testing.assert_allclose(rig.R @ rig.R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rig.R) == pytest.approx(1.0)
    # Converging optical axes: the angle between them is 2 atan(60 / 400).
    _, axis = camera_pose(rig, 1)
    angle = np.degrees(np.arccos(axis[2]))
    assert angle == pytest.approx(2 * np.degrees(np.arctan(BASELINE / 2 / WORKING_DISTANCE)), abs=0.1)
    assert rig.std == {}


def test_fixation_point_is_on_both_optical_axes():
    rig = default_rig()
    F = fixation_point(rig)
    expected = np.hypot(WORKING_DISTANCE, BASELINE / 2)
    assert F[2] == pytest.approx(expected, abs=0.5)
    assert np.hypot(F[0], F[1]) < 0.5  # on the left axis
    centre, axis = camera_pose(rig, 1)
    v = F - centre
    assert np.linalg.norm(v - (v @ axis) * axis) < 0.5  # on the right axis
    # It images near both principal points.
    for index, K, D in ((0, rig.K1, rig.D1), (1, rig.K2, rig.D2)):
        R, t = (None, None) if index == 0 else (rig.R, rig.T)
        uv = project_points(F[None], K, D, R, t)[0]
        assert np.linalg.norm(uv - K[:2, 2]) < 3.0


@pytest.mark.parametrize("size", [(816, 683), (1224, 1024), (612, 512)])
def test_smaller_images_keep_the_field_of_view(size):
    full, small = default_rig(), default_rig(size)
    w, h = size
    W, H = FULL_SIZE
    # The outer corners of the corner pixels look along the same rays.
    for K_full, K_small in ((full.K1, small.K1), (full.K2, small.K2)):
        a = undistort_points([[-0.5, -0.5], [W - 0.5, H - 0.5]], K_full, np.zeros(5))
        b = undistort_points([[-0.5, -0.5], [w - 0.5, h - 0.5]], K_small, np.zeros(5))
        # x exactly; y up to the rounding of the height (683 vs 2048 / 3)
        np.testing.assert_allclose(b[:, 0], a[:, 0], atol=1e-9)
        np.testing.assert_allclose(b[:, 1], a[:, 1], atol=2e-4)
    np.testing.assert_array_equal(full.R, small.R)
    np.testing.assert_array_equal(full.T, small.T)


def test_distortion_is_realistic():
    plain, rig = default_rig(), default_rig(distortion=True)
    assert not np.any(plain.D1) and not np.any(plain.D2)
    assert not np.allclose(rig.D1, rig.D2)
    W, H = FULL_SIZE
    corners = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]], float)
    for K, D in ((rig.K1, rig.D1), (rig.K2, rig.D2)):
        k1, k2, p1, p2, k3 = D
        assert k1 < 0  # barrel, as for most C-mount lenses
        xn = undistort_points(corners, K, D)
        ideal = xn * K[0, 0] + K[:2, 2]
        shift = np.linalg.norm(corners - ideal, axis=1)
        assert np.all((shift > 2.0) & (shift < 6.0)), shift  # a few pixels at the corners
        # Tangential part alone: small.
        tang = np.stack([2 * p1 * xn[:, 0] * xn[:, 1] + p2 * (3 * xn[:, 0] ** 2 + xn[:, 1] ** 2),
                         p1 * (xn[:, 0] ** 2 + 3 * xn[:, 1] ** 2) + 2 * p2 * xn[:, 0] * xn[:, 1]], axis=1)
        assert np.abs(tang * K[0, 0]).max() < 0.5
        assert _border_round_trip(K, D, FULL_SIZE, 1) < 1e-6  # the model does not fold the image over


def test_calibration_file_round_trip(tmp_path):
    rig = default_rig((816, 683), distortion=True)
    write_calibration(tmp_path / "calibration.yaml", rig)
    back = read_calibration(tmp_path / "calibration.yaml")
    assert back.image_size == rig.image_size
    for name in ("K1", "D1", "K2", "D2", "R", "T"):
        np.testing.assert_array_equal(np.ravel(getattr(back, name)), np.ravel(getattr(rig, name)))


def test_bad_size():
    with pytest.raises(ValueError):
        default_rig((0, 10))


# ------------------------------------------------------------------ random rigs

from hypothesis import given, settings
from hypothesis import strategies as st

from partinspect.cad.sightlines import in_view
from partinspect.simulate.rig import LENSES, SENSORS, random_rig


def _sphere_in_view(rig, centre, radius, n=400):
    """Whether points on a sphere about ``centre`` project inside both images."""
    rng = np.random.default_rng(0)
    d = rng.normal(size=(n, 3))
    X = centre + radius * d / np.linalg.norm(d, axis=1)[:, None]
    return all(in_view(project_points(X, *rig.camera(index)), rig.image_size).all() for index in (0, 1))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), field=st.floats(20.0, 300.0))
def test_random_rig_frames_the_part_in_both_images(seed, field):
    rig = random_rig(seed, field)
    F = fixation_point(rig)
    middle = camera_pose(rig, 1)[0] / 2  # of the baseline
    assert 2.5 * field - 1.0 <= np.linalg.norm(F - middle) <= 1201.0
    # A part of that size about the fixation point is seen whole by both cameras.
    assert _sphere_in_view(rig, F, field / 2)
    # Converging cameras 12-35 degrees apart, a proper rotation.
    _, axis = camera_pose(rig, 1)
    assert 11.0 < np.degrees(np.arccos(axis[2])) < 36.0
    np.testing.assert_allclose(rig.R @ rig.R.T, np.eye(3), atol=1e-12)
    assert ((rig.image_size, pytest.approx(rig.K1[0, 0], rel=0.02)) in
            [(size, lens / pitch) for size, pitch in SENSORS for lens in LENSES])


def test_random_rigs_differ_as_users_rigs_do():
    rigs = [random_rig(seed, 120.0) for seed in range(40)]
    # Seeded: the same seed gives the same rig.
    again = random_rig(7, 120.0)
    for name in ("K1", "D1", "K2", "D2", "R", "T"):
        np.testing.assert_array_equal(getattr(again, name), getattr(rigs[7], name))
    # Baselines at every angle about the view, horizontal and vertical ones among them: the
    # epipolar lines run in any direction in the image.
    angles = []
    for rig in rigs:
        centre, _ = camera_pose(rig, 1)
        angles.append(np.degrees(np.arctan2(centre[1], centre[0])) % 180.0)
    angles = np.array(angles)
    assert (np.minimum(angles, 180.0 - angles) < 20.0).any() and (np.abs(angles - 90.0) < 20.0).any()
    assert len({rig.image_size for rig in rigs}) >= 3
    baselines = [rig.baseline for rig in rigs]
    assert max(baselines) > 2.0 * min(baselines)
    # Distortion, different per lens and never folding the image over.
    for rig in rigs[:10]:
        assert not np.allclose(rig.D1, rig.D2)
        for K, D in ((rig.K1, rig.D1), (rig.K2, rig.D2)):
            assert _border_round_trip(K, D, rig.image_size, 7) < 1e-6


def test_random_rig_refuses_what_no_lens_frames():
    with pytest.raises(ValueError, match="> 0"):
        random_rig(0, 0.0)
    with pytest.raises(ValueError, match="no sensor and lens"):
        random_rig(0, 2000.0)
