import cv2
import numpy as np
import pytest

from partinspect.errors import InputError
from partinspect.vision.calibration import (
    StereoCalibration,
    check_image_size,
    distort_normalized,
    distortion_jacobian,
    project_points,
    read_calibration,
    undistort_points,
    write_calibration,
)

W, H = 2448, 2048
K = np.array([[7246.4, 0.0, 1231.7], [0.0, 7246.4, 1017.2], [0.0, 0.0, 1.0]])
# Realistic (strong) lens models of each OpenCV length.
MODELS = {
    4: [-0.21, 0.35, 0.0008, -0.0006],
    5: [-0.21, 0.35, 0.0008, -0.0006, -1.1],
    8: [-0.21, 0.35, 0.0008, -0.0006, -1.1, 0.02, 0.05, -0.3],
    12: [-0.21, 0.35, 0.0008, -0.0006, -1.1, 0.02, 0.05, -0.3, 0.001, -0.002, 0.0015, 0.0005],
}


def make_calib(**over):
    rvec = np.array([0.004, -0.30, 0.002])
    args = dict(
        image_size=(W, H),
        K1=K,
        D1=np.array(MODELS[5]),
        K2=K * [[1.001], [1.001], [1]],
        D2=np.array(MODELS[8]),
        R=cv2.Rodrigues(rvec)[0],
        T=np.array([-118.5, 0.8, 18.2]),
        std={"intrinsics1": np.arange(1, 10) * 0.01, "extrinsics": [1e-4, 2e-4, 1e-4, 0.02, 0.03, 0.05]},
    )
    args.update(over)
    return StereoCalibration(**args)


def full_grid(n=101):
    u, v = np.meshgrid(np.linspace(0, W - 1, n), np.linspace(0, H - 1, n))
    return np.stack([u.ravel(), v.ravel()], axis=1)


@pytest.mark.parametrize("n", sorted(MODELS))
def test_projection_matches_opencv(n):
    rng = np.random.default_rng(n)
    X = rng.uniform([-80, -60, 300], [80, 60, 500], (500, 3))
    rvec, t = np.array([0.02, -0.31, 0.01]), np.array([-118.0, 1.0, 20.0])
    ours = project_points(X, K, MODELS[n], cv2.Rodrigues(rvec)[0], t)
    ref = cv2.projectPoints(X, rvec, t, K, np.array(MODELS[n]))[0].reshape(-1, 2)
    assert np.abs(ours - ref).max() < 1e-8


@pytest.mark.parametrize("n", sorted(MODELS))
def test_undistort_round_trip_whole_image(n):
    uv = full_grid()
    xn = undistort_points(uv, K, MODELS[n])
    back = project_points(np.c_[xn, np.ones(len(xn))], K, MODELS[n])
    assert np.abs(back - uv).max() < 1e-6


def test_undistort_without_distortion_is_pinhole():
    uv = full_grid(11)
    xn = undistort_points(uv, K, np.zeros(5))
    assert np.allclose(xn[:, 0], (uv[:, 0] - K[0, 2]) / K[0, 0])
    assert np.allclose(xn[:, 1], (uv[:, 1] - K[1, 2]) / K[1, 1])


def test_undistort_agrees_with_opencv_where_opencv_converges():
    uv = full_grid(21)
    ours = undistort_points(uv, K, MODELS[5])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-14)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, np.array(MODELS[5]), criteria=criteria).reshape(-1, 2)
    assert np.abs(ours - ref).max() * K[0, 0] < 1e-4


def test_distortion_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    xn = rng.uniform(-0.18, 0.18, (50, 2))
    J = distortion_jacobian(xn, MODELS[12])
    h = 1e-7
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        fd = (distort_normalized(xn + e, MODELS[12]) - distort_normalized(xn - e, MODELS[12])) / (2 * h)
        assert np.abs(J[:, :, j] - fd).max() < 1e-7


def test_points_behind_camera_give_nan():
    uv = project_points([[0, 0, -10.0], [0, 0, 100.0]], K, MODELS[4])
    assert np.isnan(uv[0]).all() and np.isfinite(uv[1]).all()


def test_write_read_round_trip_is_lossless(tmp_path):
    calib = make_calib()
    path = tmp_path / "calibration.yaml"
    write_calibration(path, calib)
    back = read_calibration(path)
    assert back.image_size == (W, H)
    for name in ("K1", "D1", "K2", "D2", "R", "T"):
        np.testing.assert_array_equal(getattr(back, name), np.asarray(getattr(calib, name), dtype=float))
    np.testing.assert_array_equal(back.std["extrinsics"], calib.std["extrinsics"])
    assert set(back.std) == {"intrinsics1", "extrinsics"}
    # The folder form finds the same file; nothing but the target was left behind.
    assert read_calibration(tmp_path).baseline == pytest.approx(np.linalg.norm(calib.T))
    assert [p.name for p in tmp_path.iterdir()] == ["calibration.yaml"]


def _covariance(n, seed=0):
    """A positive-definite covariance of n parameters with strong correlations and mixed scales."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n)) + 3 * np.outer(rng.normal(size=n), rng.normal(size=n))
    s = 10.0 ** rng.uniform(-5, 0, n)
    return (A @ A.T / n) * np.outer(s, s)


def test_covariance_round_trip_sets_the_standard_uncertainties(tmp_path):
    cov = _covariance(9 + 12 + 6)  # D1 has 5 coefficients, D2 8
    write_calibration(tmp_path / "calibration.yaml", make_calib(std={}, cov=cov))
    back = read_calibration(tmp_path / "calibration.yaml")
    np.testing.assert_array_equal(back.cov, cov)
    np.testing.assert_allclose(back.std["intrinsics2"], np.sqrt(np.diag(cov))[9:21])
    np.testing.assert_allclose(back.std["extrinsics"], np.sqrt(np.diag(cov))[21:])


def test_reads_opencv_stereo_calib_pair(tmp_path):
    calib = make_calib()
    fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("M1", calib.K1), ("D1", calib.D1.reshape(1, -1)), ("M2", calib.K2), ("D2", calib.D2.reshape(1, -1))):
        fs.write(key, value)
    fs.release()
    fs = cv2.FileStorage(str(tmp_path / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("R", calib.R)
    fs.write("T", calib.T.reshape(3, 1))
    fs.write("R1", np.eye(3))
    fs.release()
    back = read_calibration(tmp_path)
    assert back.image_size is None
    np.testing.assert_allclose(back.K2, calib.K2)
    np.testing.assert_allclose(back.T, calib.T)
    (tmp_path / "extrinsics.yml").unlink()
    with pytest.raises(InputError, match="extrinsics.yml: file not found"):
        read_calibration(tmp_path)


def test_rotation_vector_is_accepted(tmp_path):
    rvec = np.array([0.01, -0.2, 0.03])
    calib = make_calib(R=rvec)
    write_calibration(tmp_path / "c.yaml", calib)
    np.testing.assert_allclose(read_calibration(tmp_path / "c.yaml").R, cv2.Rodrigues(rvec)[0], atol=1e-15)


BAD = {
    "NaN in K1": (dict(K1=np.where(np.eye(3) == 1, np.nan, K)), "K1 contains NaN"),
    "wrong shape": (dict(K2=np.eye(2)), "K2 must be 3x3, got 2x2"),
    "negative focal": (dict(K1=K * [[-1], [1], [1]]), "non-positive focal length"),
    "not a rotation": (dict(R=np.eye(3) * 1.01), "R is not a rotation"),
    "reflection": (dict(R=np.diag([1.0, 1.0, -1.0])), "reflection"),
    "zero baseline": (dict(T=np.zeros(3)), "T is zero"),
    "bad distortion": (dict(D1=np.zeros(6)), "D1 must have 4, 5, 8, 12 or 14"),
    "negative std": (dict(std={"extrinsics": [-1, 0, 0, 0, 0, 0]}), "non-negative"),
    "bad size": (dict(image_size=(0, 10)), "image size"),
    "covariance size": (dict(cov=np.eye(24)), "covariance must be 27x27"),
    "covariance not positive": (dict(std={}, cov=np.diag(np.r_[1.0, -1.0, np.ones(25)])), "negative variance"),
    "covariance indefinite": (dict(std={}, cov=np.eye(27) + 0.9 * (np.eye(27, k=1) + np.eye(27, k=-1))),
                              "not positive semi-definite"),
    "covariance asymmetric": (dict(std={}, cov=np.eye(27) + 0.5 * np.eye(27, k=1)), "not symmetric"),
    "covariance against std": (dict(std={"extrinsics": np.ones(6)}, cov=4 * np.eye(27)), "std_extrinsics disagrees"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_calibration_is_one_clear_error(tmp_path, case):
    over, message = BAD[case]
    path = tmp_path / "calibration.yaml"
    # Write it by hand: write_calibration refuses bad calibrations too.
    calib = make_calib(**over)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", int(calib.image_size[0]))
    fs.write("image_height", int(calib.image_size[1]))
    for name in ("K1", "D1", "K2", "D2", "R", "T"):
        fs.write(name, np.atleast_2d(np.asarray(getattr(calib, name), dtype=float)))
    for k, v in calib.std.items():
        fs.write("std_" + k, np.atleast_2d(np.asarray(v, dtype=float)))
    if calib.cov is not None:
        fs.write("covariance", np.asarray(calib.cov, dtype=float))
    fs.release()
    with pytest.raises(InputError) as err:
        read_calibration(path)
    assert str(err.value).startswith(str(path) + ": ")
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_unreadable_files(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        read_calibration(tmp_path / "nope.yaml")
    (tmp_path / "empty.yaml").write_text("")
    with pytest.raises(InputError, match="empty"):
        read_calibration(tmp_path / "empty.yaml")
    (tmp_path / "junk.yaml").write_text("%YAML:1.0\nK1: [unclosed\n  : : :")
    with pytest.raises(InputError, match="junk.yaml"):
        read_calibration(tmp_path / "junk.yaml")
    (tmp_path / "sub").mkdir()
    with pytest.raises(InputError, match="no calibration.yaml"):
        read_calibration(tmp_path / "sub")


def test_real_single_camera_file_is_rejected_clearly(test_data):
    # OpenCV's sample left_intrinsics.yml is a single-camera file, not a stereo calibration.
    path = test_data / "opencv-stereo-chessboard" / "left_intrinsics.yml"
    with pytest.raises(InputError, match="missing entry 'image_width'|missing entry 'K1'"):
        read_calibration(path)


def test_image_size_check():
    calib = make_calib()
    check_image_size(calib, (W, H), "left.png")
    with pytest.raises(InputError, match="left.png: image is 640x480 pixels but the calibration is for 2448x2048"):
        check_image_size(calib, (640, 480), "left.png")
