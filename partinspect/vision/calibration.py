"""Stereo calibration: file I/O, validation, projection and undistortion.

The rig frame is the left camera's OpenCV frame (x right, y down, z forward).
The right camera sees ``X_right = R @ X_left + T`` (OpenCV's stereoCalibrate
convention), lengths in millimetres.

The distortion model is OpenCV's, with up to 12 coefficients
``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4]]])``: rational radial,
tangential and thin-prism terms. The 14-coefficient tilted-sensor model is
accepted only with zero tilt.

References
----------
.. [1] Bradski, G. The OpenCV Library, "Camera Calibration and 3D
       Reconstruction" (calib3d module documentation): the camera and
       distortion model implemented here.
.. [2] Brown, D. C. (1966). Decentering distortion of lenses.
       Photogrammetric Engineering 32(3), 444-462.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from partinspect.errors import InputError

__all__ = [
    "StereoCalibration",
    "read_calibration",
    "write_calibration",
    "validate_calibration",
    "check_image_size",
    "distort_normalized",
    "distortion_jacobian",
    "undistort_points",
    "project_points",
    "camera_pose",
]

_DIST_LENGTHS = (4, 5, 8, 12, 14)
# Std-dev vectors follow OpenCV's calibrateCameraExtended order:
# fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, taux, tauy.
_STD_KEYS = {
    "std_intrinsics1": "intrinsics1",
    "std_intrinsics2": "intrinsics2",
    "std_extrinsics": "extrinsics",
}


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """A calibrated stereo pair.

    Attributes
    ----------
    image_size : tuple of int or None
        ``(width, height)`` in pixels; None when the file did not say (OpenCV
        stereo_calib's intrinsics.yml), in which case the images give it.
    K1, K2 : ndarray, shape (3, 3)
        Camera matrices of the left and right camera, pixels.
    D1, D2 : ndarray, shape (n,)
        OpenCV distortion vectors, n in {4, 5, 8, 12, 14}.
    R : ndarray, shape (3, 3)
        Rotation from the left to the right camera frame.
    T : ndarray, shape (3,)
        Translation, mm: ``X_right = R @ X_left + T``.
    std : dict of str to ndarray
        Optional standard uncertainties of the parameters:
        ``"intrinsics1"``, ``"intrinsics2"`` in OpenCV's
        calibrateCameraExtended order (fx, fy, cx, cy, then the distortion
        coefficients), ``"extrinsics"`` as (rx, ry, rz, tx, ty, tz): the
        rotation vector of R in radians, then T in mm.
    cov : ndarray, shape (n, n) or None
        Optional covariance of all those parameters together, in the order
        intrinsics1, intrinsics2, extrinsics (n = 14 + len(D1) + len(D2)):
        a calibration's errors are correlated (a focal length's error comes
        with a matching translation's), and the epipolar geometry, which
        stereo matching depends on, is far better known than independent
        per-parameter uncertainties suggest. When given, ``std`` is the
        square root of its diagonal.
    """

    image_size: tuple[int, int] | None
    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    std: dict = field(default_factory=dict)
    cov: np.ndarray | None = None

    def camera(self, index):
        """Return ``(K, D, R, t)`` of camera 0 (left) or 1 (right).

        ``R, t`` map rig-frame points into that camera's frame.
        """
        if index == 0:
            return self.K1, self.D1, np.eye(3), np.zeros(3)
        if index == 1:
            return self.K2, self.D2, self.R, self.T
        raise ValueError(f"camera index must be 0 or 1, got {index}")

    @property
    def baseline(self):
        """Distance between the two projection centres, mm."""
        return float(np.linalg.norm(self.T))

    def same_rig(self, other):
        """Whether ``other`` states the same rig: every parameter and uncertainty equal.

        Views measured with the same calibration share its error; a rig
        recalibrated between views, or corrected for drift by one view's
        check, does not.
        """
        def same(x, y):
            if isinstance(x, dict) or isinstance(y, dict):
                return isinstance(x, dict) and isinstance(y, dict) and x.keys() == y.keys() and all(
                    same(x[k], y[k]) for k in x)
            if x is None or y is None:
                return x is None and y is None
            return np.array_equal(np.asarray(x), np.asarray(y))

        return all(same(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))


# ---------------------------------------------------------------- the model


def _dist12(D):
    """Pad a distortion vector to 12 coefficients; refuse a tilted sensor."""
    D = np.asarray(D, dtype=float).ravel()
    if D.size == 14:
        if np.any(D[12:] != 0):
            raise ValueError("the tilted-sensor distortion model (tauX, tauY != 0) is not supported")
        D = D[:12]
    out = np.zeros(12)
    out[: D.size] = D
    return out


def distort_normalized(xn, D):
    """Apply OpenCV's lens distortion to normalised image coordinates.

    Parameters
    ----------
    xn : ndarray, shape (N, 2)
        Undistorted normalised coordinates ``(X/Z, Y/Z)`` in a camera frame.
    D : array_like, shape (n,)
        OpenCV distortion vector.

    Returns
    -------
    xd : ndarray, shape (N, 2)
        Distorted normalised coordinates (multiply by K to get pixels).
    """
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = _dist12(D)
    x, y = xn[:, 0], xn[:, 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xy2 = 2 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * xy2 + s3 * r2 + s4 * r4
    return np.stack([xd, yd], axis=1)


def distortion_jacobian(xn, D):
    """Jacobian of :func:`distort_normalized` with respect to its input.

    Parameters
    ----------
    xn : ndarray, shape (N, 2)
        Undistorted normalised coordinates.
    D : array_like
        OpenCV distortion vector.

    Returns
    -------
    J : ndarray, shape (N, 2, 2)
        ``J[i] = d xd / d xn`` at point i.
    """
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = _dist12(D)
    x, y = xn[:, 0], xn[:, 1]
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    dradial = (dnum * den - num * dden) / (den * den)  # d radial / d r2
    px = s1 + 2 * s2 * r2  # d (prism x) / d r2
    py = s3 + 2 * s4 * r2
    J = np.empty((xn.shape[0], 2, 2))
    J[:, 0, 0] = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x + 2 * x * px
    J[:, 0, 1] = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y + 2 * y * px
    J[:, 1, 0] = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y + 2 * x * py
    J[:, 1, 1] = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x + 2 * y * py
    return J


def undistort_points(uv, K, D, *, tol=1e-12, max_iter=50):
    """Map distorted pixel coordinates to undistorted normalised coordinates.

    Newton's method on the distortion model, started at the distorted point,
    iterated until every point reprojects onto its input; unlike OpenCV's
    fixed-point ``undistortPoints`` this converges quadratically and checks
    that it did.

    Parameters
    ----------
    uv : array_like, shape (N, 2)
        Pixel coordinates in the distorted image (OpenCV convention: the
        centre of the top-left pixel is (0, 0)).
    K : ndarray, shape (3, 3)
        Camera matrix.
    D : array_like
        OpenCV distortion vector.
    tol : float
        Convergence threshold on the normalised reprojection residual
        (1e-12 is about 1e-8 px for f = 7000 px).
    max_iter : int
        Iteration limit.

    Returns
    -------
    xn : ndarray, shape (N, 2)
        Undistorted normalised coordinates ``(X/Z, Y/Z)``.

    Raises
    ------
    ValueError
        If some point does not converge (a distortion model that folds over
        inside the image).
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    K = np.asarray(K, dtype=float)
    fx, skew, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    yd = (uv[:, 1] - cy) / fy
    xd = (uv[:, 0] - cx - skew * yd) / fx
    target = np.stack([xd, yd], axis=1)
    D12 = _dist12(D)
    if not np.any(D12):
        return target
    x = target.copy()
    active = np.arange(len(x))
    for _ in range(max_iter):
        xa = x[active]
        r = distort_normalized(xa, D12) - target[active]
        done = np.abs(r).max(axis=1) <= tol
        if done.all():
            return x
        active, xa, r = active[~done], xa[~done], r[~done]
        J = distortion_jacobian(xa, D12)
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        dx = (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det
        dy = (J[:, 0, 0] * r[:, 1] - J[:, 1, 0] * r[:, 0]) / det
        x[active, 0] = xa[:, 0] - dx
        x[active, 1] = xa[:, 1] - dy
    raise ValueError(
        f"undistortion did not converge for {len(active)} point(s), e.g. pixel "
        f"{uv[active[0]].tolist()}: the distortion model folds over there"
    )


def project_points(X, K, D, R=None, t=None):
    """Project 3D points into a camera, with lens distortion.

    Parameters
    ----------
    X : array_like, shape (N, 3)
        Points in mm, in the frame from which ``R, t`` map into the camera
        (the rig frame for :meth:`StereoCalibration.camera`).
    K : ndarray, shape (3, 3)
        Camera matrix.
    D : array_like
        OpenCV distortion vector.
    R : ndarray, shape (3, 3), optional
        Rotation into the camera frame; identity if omitted.
    t : array_like, shape (3,), optional
        Translation into the camera frame, mm; zero if omitted.

    Returns
    -------
    uv : ndarray, shape (N, 2)
        Pixel coordinates in the distorted image. Points at or behind the
        camera (Z <= 0) give NaN.
    """
    X = np.asarray(X, dtype=float).reshape(-1, 3)
    Xc = X if R is None else X @ np.asarray(R, dtype=float).T
    if t is not None:
        Xc = Xc + np.asarray(t, dtype=float).ravel()
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = Xc[:, :2] / z[:, None]
    xn[z <= 0] = np.nan
    xd = distort_normalized(xn, D)
    K = np.asarray(K, dtype=float)
    u = K[0, 0] * xd[:, 0] + K[0, 1] * xd[:, 1] + K[0, 2]
    v = K[1, 1] * xd[:, 1] + K[1, 2]
    return np.stack([u, v], axis=1)


def camera_pose(calib, index):
    """Position (mm) and viewing direction of camera ``index`` in the rig frame.

    Returns
    -------
    center : ndarray, shape (3,)
    axis : ndarray, shape (3,)
        Unit vector of the camera's optical axis (+z).
    """
    _, _, R, t = calib.camera(index)
    return -R.T @ t, R.T @ np.array([0.0, 0.0, 1.0])


# ------------------------------------------------------------- validation


def _fail(path, problem):
    raise InputError(path, problem)


def _as_matrix(path, name, value, shape):
    a = np.asarray(value, dtype=float)
    if a.shape != shape:
        if a.size == int(np.prod(shape)) and (a.ndim == 1 or 1 in a.shape):
            a = a.reshape(shape)
        else:
            got = "x".join(str(s) for s in a.shape) or "a scalar"
            want = "x".join(str(s) for s in shape)
            _fail(path, f"{name} must be {want}, got {got}")
    if not np.all(np.isfinite(a)):
        _fail(path, f"{name} contains NaN or infinite values")
    return a


def _check_K(path, name, K):
    K = _as_matrix(path, name, K, (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        _fail(path, f"{name} has a non-positive focal length (fx={K[0, 0]:g}, fy={K[1, 1]:g})")
    if not (K[1, 0] == 0 and K[2, 0] == 0 and K[2, 1] == 0 and K[2, 2] == 1):
        _fail(path, f"{name} is not a camera matrix: its last row must be [0, 0, 1] and K[1,0] zero")
    return K


def _check_D(path, name, D):
    D = np.asarray(D, dtype=float).ravel()
    if D.size not in _DIST_LENGTHS:
        _fail(path, f"{name} must have 4, 5, 8, 12 or 14 coefficients, got {D.size}")
    if not np.all(np.isfinite(D)):
        _fail(path, f"{name} contains NaN or infinite values")
    if D.size == 14 and np.any(D[12:] != 0):
        _fail(path, f"{name}: the tilted-sensor model (tauX, tauY) is not supported")
    return D


def _check_R(path, R):
    R = np.asarray(R, dtype=float)
    if R.size == 3:
        import cv2

        R = _as_matrix(path, "R", R, (3, 1))
        R = cv2.Rodrigues(R)[0]
    R = _as_matrix(path, "R", R, (3, 3))
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > 1e-6:
        _fail(path, f"R is not a rotation: R^T R differs from the identity by {err:.2g}")
    if np.linalg.det(R) < 0:
        _fail(path, "R is a reflection (determinant -1), not a rotation")
    return R


def validate_calibration(calib, path=None):
    """Check a calibration and return a normalised copy.

    Parameters
    ----------
    calib : StereoCalibration
        Possibly with list or wrongly shaped entries.
    path : str or Path, optional
        The file it came from, named in error messages.

    Returns
    -------
    StereoCalibration
        With float arrays of the documented shapes.

    Raises
    ------
    InputError
        On wrong shapes, NaN or infinite values, non-positive focal lengths,
        a non-rotation R, a zero baseline, or bad standard deviations.
    """
    size = calib.image_size
    if size is not None:
        w, h = size
        if int(w) != w or int(h) != h or w <= 0 or h <= 0:
            _fail(path, f"image size must be two positive integers, got {w} x {h}")
        size = (int(w), int(h))
    K1 = _check_K(path, "K1", calib.K1)
    K2 = _check_K(path, "K2", calib.K2)
    D1 = _check_D(path, "D1", calib.D1)
    D2 = _check_D(path, "D2", calib.D2)
    R = _check_R(path, calib.R)
    T = _as_matrix(path, "T", calib.T, (3,))
    if np.linalg.norm(T) <= 0:
        _fail(path, "T is zero: the two cameras cannot be at the same place")
    std = {}
    lengths = {"intrinsics1": 4 + D1.size, "intrinsics2": 4 + D2.size, "extrinsics": 6}
    for key, value in (calib.std or {}).items():
        if key not in lengths:
            _fail(path, f"unknown standard-deviation entry {key!r}")
        a = np.asarray(value, dtype=float).ravel()
        n = lengths[key]
        if key.startswith("intrinsics") and a.size == 18:
            a = a[:n]  # calibrateCameraExtended always returns 18 entries
        if a.size != n:
            _fail(path, f"std_{key} must have {n} entries, got {a.size}")
        if not np.all(np.isfinite(a)) or np.any(a < 0):
            _fail(path, f"std_{key} must be finite and non-negative")
        std[key] = a
    cov = None if calib.cov is None else _check_cov(path, calib.cov, lengths, std)
    if cov is not None:
        std = _std_of(cov, lengths)
    return StereoCalibration(size, K1, D1, K2, D2, R, T, std, cov)


COV_TOLERANCE = 1e-3
"""Relative: how far a stated covariance may be from symmetric and
positive semi-definite (rounding in a written file), and its diagonal from
the stated standard deviations."""


def _std_of(cov, lengths):
    """The standard deviations on a covariance's diagonal, split by parameter group."""
    s, out, at = np.sqrt(np.clip(np.diag(cov), 0.0, None)), {}, 0
    for key, n in lengths.items():
        out[key] = s[at : at + n]
        at += n
    return out


def _check_cov(path, cov, lengths, std):
    """A stated covariance checked: its size, finite, symmetric, positive semi-definite, agreeing with std."""
    n = sum(lengths.values())
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (n, n):
        got = "x".join(str(k) for k in cov.shape) or "a scalar"
        _fail(path, f"covariance must be {n}x{n} (intrinsics1, intrinsics2, extrinsics in order), got {got}")
    if not np.all(np.isfinite(cov)):
        _fail(path, "covariance contains NaN or infinite values")
    if np.any(np.diag(cov) < 0):
        _fail(path, "covariance has a negative variance on its diagonal")
    # A parameter held fixed in the calibration has variance 0 and no covariance.
    d = np.sqrt(np.diag(cov))
    free = d > 0
    if np.any(cov[~free] != 0):
        _fail(path, "covariance has a parameter with zero variance but non-zero covariance")
    corr = cov[np.ix_(free, free)] / np.outer(d[free], d[free])
    if np.abs(corr - corr.T).max(initial=0.0) > COV_TOLERANCE:
        _fail(path, "covariance is not symmetric")
    low = float(np.linalg.eigvalsh(0.5 * (corr + corr.T)).min(initial=0.0)) if free.any() else 0.0
    if low < -COV_TOLERANCE:
        _fail(path, f"covariance is not positive semi-definite (its correlation matrix has eigenvalue {low:.3g})")
    for key, s in _std_of(cov, lengths).items():
        if key in std and np.any(np.abs(std[key] - s) > COV_TOLERANCE * s):
            _fail(path, f"std_{key} disagrees with the square root of the covariance's diagonal")
    return 0.5 * (cov + cov.T)


def check_image_size(calib, size, path):
    """Raise InputError when an image's ``(width, height)`` differs from the calibration's."""
    if calib.image_size is not None and tuple(size) != tuple(calib.image_size):
        _fail(
            path,
            f"image is {size[0]}x{size[1]} pixels but the calibration is for "
            f"{calib.image_size[0]}x{calib.image_size[1]}",
        )


# -------------------------------------------------------------------- I/O


def _open_storage(path):
    import cv2

    path = Path(path)
    if not path.is_file():
        _fail(path, "file not found" if not path.exists() else "not a regular file")
    if path.stat().st_size == 0:
        _fail(path, "file is empty")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):
        # OpenCV's parser messages are multi-line C++ traces; the user needs the gist.
        _fail(path, "not a readable OpenCV FileStorage (YAML/XML) file: syntax error")
    if not fs.isOpened():
        _fail(path, "not a readable OpenCV FileStorage (YAML/XML) file")
    return fs


def _matrix_header_ok(node):
    """True when an ``!!opencv-matrix`` node has rows, cols, dt and data, once each, consistent.

    Checked before ``FileNode.mat()``: OpenCV 5.0's ``mat()`` on a header
    with a duplicated or missing field corrupts the heap and a later read
    aborts the process.
    """
    if not node.isMap():
        return False
    keys = list(node.keys())
    if sorted(keys) != ["cols", "data", "dt", "rows"]:
        return False
    rows, cols, dt, data = (node.getNode(k) for k in ("rows", "cols", "dt", "data"))
    if not (rows.isInt() and cols.isInt() and dt.isString() and data.isSeq()):
        return False
    channels = int(dt.string()[:-1]) if len(dt.string()) > 1 and dt.string()[:-1].isdigit() else 1
    return rows.real() >= 0 and cols.real() >= 0 and data.size() == int(rows.real()) * int(cols.real()) * channels


def _read_node(fs, path, name, required=True):
    import cv2

    # OpenCV reports malformed structure (a top level that is not a map, a
    # matrix with duplicated or missing fields, text among its numbers) as
    # C++ assertion traces; the user gets one line naming the entry.
    try:
        if not fs.root().isMap():
            _fail(path, "the file's top level is not a map of named entries (image_width, K1, ...)")
        node = fs.getNode(name)
        empty = node.empty()
    except (cv2.error, SystemError, UnicodeDecodeError):
        _fail(path, f"cannot read entry {name!r}: the file's structure is malformed")
    if empty:
        if required:
            _fail(path, f"missing entry {name!r}")
        return None
    try:
        if node.isInt() or node.isReal():
            return node.real()
        mat = node.mat() if _matrix_header_ok(node) else None
    except (cv2.error, SystemError, UnicodeDecodeError):  # e.g. a field name that is not UTF-8
        mat = None
    if mat is None or not isinstance(mat, np.ndarray):
        _fail(path, f"entry {name!r} is not a number or an OpenCV matrix")
    return mat


def _read_yaml(path):
    fs = _open_storage(path)
    try:
        w = _read_node(fs, path, "image_width")
        h = _read_node(fs, path, "image_height")
        raw = {k: _read_node(fs, path, k) for k in ("K1", "D1", "K2", "D2", "R", "T")}
        std = {}
        for key, name in _STD_KEYS.items():
            value = _read_node(fs, path, key, required=False)
            if value is not None:
                std[name] = value
        cov = _read_node(fs, path, "covariance", required=False)
    finally:
        fs.release()
    calib = StereoCalibration((w, h), raw["K1"], raw["D1"], raw["K2"], raw["D2"], raw["R"], raw["T"], std, cov)
    return validate_calibration(calib, path)


def _read_stereo_calib_pair(intrinsics, extrinsics):
    fs = _open_storage(intrinsics)
    try:
        raw = {k: _read_node(fs, intrinsics, k) for k in ("M1", "D1", "M2", "D2")}
    finally:
        fs.release()
    fs = _open_storage(extrinsics)
    try:
        R = _read_node(fs, extrinsics, "R")
        T = _read_node(fs, extrinsics, "T")
    finally:
        fs.release()
    # Validate intrinsics and extrinsics separately so the message names the right file.
    probe = StereoCalibration(None, raw["M1"], raw["D1"], raw["M2"], raw["D2"], np.eye(3), [1.0, 0, 0])
    probe = validate_calibration(probe, intrinsics)
    ext = validate_calibration(StereoCalibration(None, probe.K1, probe.D1, probe.K2, probe.D2, R, T), extrinsics)
    return ext


def read_calibration(path):
    """Read a stereo calibration.

    Parameters
    ----------
    path : str or Path
        Either a ``calibration.yaml`` file (DESIGN.md's format: an OpenCV
        FileStorage with ``image_width``, ``image_height``, ``K1``, ``D1``,
        ``K2``, ``D2``, ``R``, ``T`` and optional ``std_intrinsics1``,
        ``std_intrinsics2``, ``std_extrinsics`` and ``covariance``), or a folder holding
        ``calibration.yaml`` or OpenCV stereo_calib's ``intrinsics.yml``
        (``M1``, ``D1``, ``M2``, ``D2``) plus ``extrinsics.yml`` (``R``,
        ``T``; their length unit is whatever square size the calibration
        used, which must be mm here).

    Returns
    -------
    StereoCalibration
        Validated; ``image_size`` is None for the stereo_calib pair.

    Raises
    ------
    InputError
        Naming the file and the problem.
    """
    path = Path(path)
    if path.is_dir():
        for name in ("calibration.yaml", "calibration.yml"):
            if (path / name).exists():
                return _read_yaml(path / name)
        intr, extr = path / "intrinsics.yml", path / "extrinsics.yml"
        if intr.exists() or extr.exists():
            if not intr.exists():
                _fail(intr, "file not found (extrinsics.yml needs its intrinsics.yml)")
            if not extr.exists():
                _fail(extr, "file not found (intrinsics.yml needs its extrinsics.yml)")
            return _read_stereo_calib_pair(intr, extr)
        _fail(path, "no calibration.yaml (nor intrinsics.yml + extrinsics.yml) in this folder")
    return _read_yaml(path)


def write_calibration(path, calib):
    """Write DESIGN.md's calibration.yaml atomically.

    The file appears complete or not at all: it is written to a temporary
    file in the same folder and renamed over ``path``.

    Parameters
    ----------
    path : str or Path
        Destination, normally ``.../calibration.yaml``.
    calib : StereoCalibration
        Must have an image size.
    """
    import cv2

    calib = validate_calibration(calib, path)
    if calib.image_size is None:
        raise ValueError("a calibration.yaml needs the image size")
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=path.suffix or ".yaml", dir=path.parent)
    os.close(fd)
    try:
        fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", int(calib.image_size[0]))
        fs.write("image_height", int(calib.image_size[1]))
        for name in ("K1", "D1", "K2", "D2", "R"):
            a = np.asarray(getattr(calib, name), dtype=np.float64)
            fs.write(name, a.reshape(1, -1) if a.ndim == 1 else a)
        fs.write("T", np.asarray(calib.T, dtype=np.float64).reshape(3, 1))
        for key, name in _STD_KEYS.items():
            if name in calib.std:
                fs.write(key, np.asarray(calib.std[name], dtype=np.float64).reshape(1, -1))
        if calib.cov is not None:
            fs.write("covariance", np.asarray(calib.cov, dtype=np.float64))
        fs.release()
        os.chmod(tmp, 0o644)  # mkstemp makes it private; a calibration is meant to be shared
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
