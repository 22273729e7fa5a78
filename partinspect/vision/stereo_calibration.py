"""Stereo calibration from board image pairs, with standard uncertainties.

The chain is Zhang's [1]_: detect a planar board of known geometry in every
left/right image pair, calibrate each camera on its own views
(``cv2.calibrateCameraExtended``), then the rig
(``cv2.stereoCalibrateExtended``), reject outlier views and repeat. Standard
uncertainties (GUM, JCGM 100 [4]_): of the intrinsics, the diagonal of
``sigma^2 (J^T J)^-1`` that ``calibrateCameraExtended`` returns; of the
extrinsics (rotation vector of R, and T), first-order back-propagation of
the image noise through the stereo least-squares problem [2]_, *including*
the uncertainty of the intrinsics it was solved with, and the covariance
of all of them together (a sandwich covariance, :func:`parameter_covariance`).

The intrinsics are held fixed in the stereo step (``CALIB_FIX_INTRINSIC``,
as the OpenCV documentation [3]_ recommends for cameras well calibrated on
their own): every intrinsic written to calibration.yaml is then the
estimate whose standard uncertainty is reported, and one camera's poorly
seen corners cannot leak into the other's lens model through R and T. The
price, a slightly less efficient R and T, is paid for honestly in their
covariance.

Frames and units: the rig frame is the left camera's OpenCV frame;
``X_right = R @ X_left + T``; lengths in the board's unit (mm when the square
size is given in mm); pixel coordinates with the centre of the top-left pixel
at (0, 0).

References
----------
.. [1] Zhang, Z. (2000). A flexible new technique for camera calibration.
       IEEE Trans. PAMI 22(11), 1330-1334.
.. [2] Hartley, R., Zisserman, A. (2004). Multiple View Geometry in Computer
       Vision, 2nd ed., Cambridge University Press: section 5.2 (covariance
       of the estimated parameters by back-propagation) and 9.2 (the
       fundamental matrix of a calibrated pair).
.. [3] OpenCV calib3d documentation: ``calibrateCameraExtended``,
       ``stereoCalibrateExtended``, ``findChessboardCorners``,
       ``cornerSubPix``, ``projectPoints``, ``composeRT``; and the
       ``samples/cpp/stereo_calib.cpp`` procedure.
.. [4] JCGM 100:2008, Evaluation of measurement data - Guide to the
       expression of uncertainty in measurement (GUM).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from partinspect.errors import InputError
from partinspect.vision.calibration import StereoCalibration, undistort_points, validate_calibration

__all__ = [
    "Board",
    "View",
    "StereoCalibrationResult",
    "find_pairs",
    "read_grey",
    "detect_chessboard",
    "detect_charuco",
    "detect_board",
    "calibrate_camera",
    "calibrate_pair",
    "camera_jacobian",
    "parameter_covariance",
    "epipolar_distances",
    "calibrate_stereo",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
MIN_VIEWS = 3
OUTLIER_FACTOR = 3.0
# A ChArUco view needs enough corners for a homography with redundancy.
MIN_CHARUCO_CORNERS = 8
_SUBPIX_STOP = (30, 0.01)  # iterations, px: as stereo_calib.cpp
_STEREO_STOP = (100, 1e-6)  # iterations, relative change


@dataclass(frozen=True)
class Board:
    """A planar calibration board.

    Attributes
    ----------
    kind : {"chessboard", "charuco"}
    cols, rows : int
        Chessboard: inner corners per row and per column (``9x6``).
        ChArUco: squares per row and per column.
    square : float
        Side of one square, in the length unit wanted for T (mm).
    marker : float
        ChArUco marker side, same unit; unused for a chessboard.
    dictionary : str
        ChArUco dictionary name, e.g. ``"DICT_5X5_100"``.
    """

    kind: str
    cols: int
    rows: int
    square: float
    marker: float = 0.0
    dictionary: str = "DICT_5X5_100"

    def object_points(self):
        """Board corners in the board frame (z = 0), ``(N, 3)`` float64, indexed by corner id.

        Chessboard ids run along rows (x fastest), as ``findChessboardCorners``
        returns them; ChArUco ids are OpenCV's charuco corner ids.
        """
        if self.kind == "charuco":
            return np.asarray(self.cv_board().getChessboardCorners(), dtype=float).reshape(-1, 3)
        grid = np.mgrid[0 : self.cols, 0 : self.rows].T.reshape(-1, 2)
        return np.column_stack([grid * self.square, np.zeros(len(grid))]).astype(float)

    def cv_board(self):
        """The ``cv2.aruco.CharucoBoard`` of a ChArUco board."""
        import cv2

        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker, dictionary)


@dataclass
class View:
    """One image pair and what became of it.

    Attributes
    ----------
    name : str
        The pair's name (the file-name suffix, e.g. ``"01"``).
    left, right : Path or None
        Image files.
    ids : ndarray, shape (N,), int or None
        Board corner ids seen in both images.
    left_points, right_points : ndarray, shape (N, 2) or None
        Detected corners, pixels.
    rejected : str or None
        Why the view is not used, or None when it is.
    errors : tuple of float
        RMS reprojection error in the left and right image, px (used views).
    epipolar : float
        Mean distance of a corner to its epipolar line, px (used views).
    """

    name: str
    left: Path | None
    right: Path | None
    ids: np.ndarray | None = None
    left_points: np.ndarray | None = None
    right_points: np.ndarray | None = None
    rejected: str | None = None
    errors: tuple = (float("nan"), float("nan"))
    epipolar: float = float("nan")


@dataclass
class StereoCalibrationResult:
    """Everything a calibration run found, for calibration.yaml and its report.

    Attributes
    ----------
    calibration : StereoCalibration
        With ``std`` entries ``intrinsics1``, ``intrinsics2``, ``extrinsics`` and their joint ``cov``.
    views : list of View
        Every pair found, used or rejected, in name order.
    board : Board
    rms : float
        RMS reprojection error of the stereo fit over both images, px.
    rms_left, rms_right : float
        RMS reprojection error of each camera's own calibration, px.
    epipolar_error : float
        Mean corner-to-epipolar-line distance over both images, px
        (half of the ``average epipolar err`` that stereo_calib.cpp prints,
        which sums the two images' distances).
    """

    calibration: StereoCalibration
    views: list
    board: Board
    rms: float
    rms_left: float
    rms_right: float
    epipolar_error: float

    @property
    def used(self):
        return [v for v in self.views if v.rejected is None]

    @property
    def rejected(self):
        return [v for v in self.views if v.rejected is not None]


# ------------------------------------------------------------ finding pairs


def _images_in(folder):
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _natural_key(text):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text)]


def find_pairs(folder):
    """Find the left/right image pairs in a folder.

    Two layouts are understood: ``left*`` / ``right*`` files side by side,
    paired by the rest of the file name (``left01.jpg`` with ``right01.jpg``;
    case-insensitive, any image type), or ``left/`` and ``right/`` subfolders
    holding files of the same names.

    Parameters
    ----------
    folder : str or Path

    Returns
    -------
    views : list of View
        Sorted by name. An image without its partner becomes a View with
        ``rejected`` set and the missing side None.

    Raises
    ------
    InputError
        When the folder does not exist, is empty, or holds no left/right images.
    """
    folder = Path(folder)
    if not folder.exists():
        raise InputError(folder, "folder not found")
    if not folder.is_dir():
        raise InputError(folder, "not a folder (expected a folder of left/right image pairs)")
    if not any(folder.iterdir()):
        raise InputError(folder, "folder is empty: expected left*/right* image pairs or left/ and right/ subfolders")
    left, right = {}, {}
    sub_l, sub_r = folder / "left", folder / "right"
    if sub_l.is_dir() or sub_r.is_dir():
        for sub, side in ((sub_l, left), (sub_r, right)):
            if sub.is_dir():
                for p in _images_in(sub):
                    side[p.stem] = p
    for p in _images_in(folder):
        m = re.match(r"(left|right)[_\-. ]?(.*)$", p.stem, re.IGNORECASE)
        if m:
            (left if m.group(1).lower() == "left" else right)[m.group(2) or p.suffix.lower()] = p
    if not left and not right:
        raise InputError(
            folder, "no image pairs: expected files named left*/right* (e.g. left01.jpg, right01.jpg) or left/ and right/ subfolders"
        )
    views = []
    for name in sorted(set(left) | set(right), key=_natural_key):
        lp, rp = left.get(name), right.get(name)
        view = View(name, lp, rp)
        if rp is None:
            view.rejected = "left image only: no right image with the same name"
        elif lp is None:
            view.rejected = "right image only: no left image with the same name"
        views.append(view)
    if all(v.rejected for v in views):
        raise InputError(folder, f"no complete left/right pair among {len(views)} image(s): names do not match")
    return views


def read_grey(path):
    """Read an image as 8-bit grey levels, ``(H, W)`` uint8.

    16-bit images are scaled to 8 bits (the board detectors need 8 bits).

    Raises
    ------
    InputError
        When the file is missing, empty or not a readable image.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "image not found")
    if path.stat().st_size == 0:
        raise InputError(path, "image file is empty")
    img = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "not a readable image (corrupt or truncated?)")
    if img.ndim == 3:
        img = cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2GRAY) if img.shape[2] >= 3 else img[:, :, 0]
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    elif img.dtype != np.uint8:
        raise InputError(path, f"unsupported pixel type {img.dtype}; expected 8- or 16-bit")
    return img


# -------------------------------------------------------------- detection


def _subpix_half_window(corners, cols, rows):
    """Half-size of the cornerSubPix window for a detected grid, px.

    The window must not reach the neighbouring corners, or cornerSubPix pulls
    the corner towards them: stereo_calib.cpp's fixed (11, 11) half-window,
    23 px wide, is wider than the squares of OpenCV's own sample images.
    0.4 of the smallest corner spacing keeps every neighbour outside; 10 px
    is enough for any blur.
    """
    g = corners.reshape(rows, cols, 2)
    d = min(
        np.linalg.norm(np.diff(g, axis=0), axis=2).min() if rows > 1 else np.inf,
        np.linalg.norm(np.diff(g, axis=1), axis=2).min() if cols > 1 else np.inf,
    )
    return int(np.clip(np.floor(0.4 * d), 2, 10))


def detect_chessboard(image, pattern, half_window=None):
    """Find a chessboard's inner corners to sub-pixel accuracy.

    As stereo_calib.cpp: ``findChessboardCorners`` with adaptive thresholding
    and normalisation, retried on the image upsampled 2x when it fails, then
    ``cornerSubPix`` on the original image.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8
    pattern : tuple of int
        ``(cols, rows)`` inner corners.
    half_window : int, optional
        cornerSubPix half-window, px; by default from the corner spacing
        (see ``_subpix_half_window``).

    Returns
    -------
    corners : ndarray, shape (cols * rows, 2), float64, or None
        Pixel coordinates in ``findChessboardCorners`` order, None when the
        board is not found.
    """
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    corners = None
    for scale in (1, 2):
        timg = image if scale == 1 else cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR_EXACT)
        found, c = cv2.findChessboardCorners(timg, tuple(pattern), flags=flags)
        if found:
            # scale maps pixel centres as (u + 0.5) * s - 0.5; stereo_calib.cpp divides by s,
            # a 0.25 px offset that cornerSubPix removes anyway.
            corners = (c.reshape(-1, 2) + 0.5) / scale - 0.5
            break
    if corners is None:
        return None
    w = half_window or _subpix_half_window(corners, *pattern)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, *_SUBPIX_STOP)
    refined = cv2.cornerSubPix(image, corners.astype(np.float32).reshape(-1, 1, 2), (w, w), (-1, -1), criteria)
    return refined.reshape(-1, 2).astype(float)


def detect_charuco(image, board):
    """Find the ChArUco corners of ``board`` in ``image``.

    Returns
    -------
    ids : ndarray, shape (N,), int, or None
    corners : ndarray, shape (N, 2), float64, or None
        None when no corner is found.
    """
    import cv2

    detector = cv2.aruco.CharucoDetector(board.cv_board())
    corners, ids, _, _ = detector.detectBoard(image)
    if ids is None or len(ids) == 0:
        return None, None
    return ids.ravel().astype(int), corners.reshape(-1, 2).astype(float)


def detect_board(image, board):
    """Detect ``board``; returns ``(ids, corners)`` or ``(None, None)``."""
    if board.kind == "charuco":
        return detect_charuco(image, board)
    corners = detect_chessboard(image, (board.cols, board.rows))
    if corners is None:
        return None, None
    return np.arange(len(corners)), corners


def detect_views(views, board, progress=None):
    """Detect the board in every complete pair; sets ``ids`` and points or ``rejected``.

    Returns
    -------
    image_size : tuple of int
        ``(width, height)``, common to all images.

    Raises
    ------
    InputError
        On an unreadable image, or images of different sizes.
    """
    size = None
    for view in views:
        if view.rejected:
            continue
        found = []
        for path in (view.left, view.right):
            img = read_grey(path)
            this = (img.shape[1], img.shape[0])
            if size is None:
                size, first = this, path
            elif this != size:
                raise InputError(path, f"image is {this[0]}x{this[1]} pixels but {first.name} is {size[0]}x{size[1]}")
            found.append(detect_board(img, board))
        (il, pl), (ir, pr) = found
        if pl is None and pr is None:
            view.rejected = "board not found in either image"
        elif pl is None:
            view.rejected = "board not found in the left image"
        elif pr is None:
            view.rejected = "board not found in the right image"
        else:
            common, a, b = np.intersect1d(il, ir, return_indices=True)
            need = MIN_CHARUCO_CORNERS if board.kind == "charuco" else len(il)
            if len(common) < need:
                view.rejected = f"only {len(common)} board corners seen in both images (need {need})"
            else:
                view.ids, view.left_points, view.right_points = common, pl[a], pr[b]
        if progress:
            progress(f"pair {view.name}: " + (view.rejected or f"{len(view.ids)} corners"))
    return size


# ------------------------------------------------------------ calibration


def calibrate_camera(object_points, image_points, image_size, flags=0):
    """Calibrate one camera (Zhang [1]_) with ``cv2.calibrateCameraExtended``.

    Parameters
    ----------
    object_points : list of ndarray, shape (N_i, 3)
        Board corners in the board frame, board units.
    image_points : list of ndarray, shape (N_i, 2)
        Their detections, px.
    image_size : tuple of int
        ``(width, height)``.
    flags : int
        OpenCV calibration flags (0: fx, fy, cx, cy and k1, k2, p1, p2, k3 free).

    Returns
    -------
    dict
        ``K`` (3, 3); ``D`` (5,); ``rvecs``, ``tvecs`` (V, 3) board poses in the
        camera frame; ``std`` (4 + len(D),) standard uncertainties of
        (fx, fy, cx, cy, D...); ``per_view`` (V,) RMS reprojection error per
        view, px; ``rms`` overall, px; ``sigma2`` the residual variance per
        coordinate, px^2 (sum of squares over degrees of freedom).
    """
    import cv2

    obj = [np.asarray(o, np.float32).reshape(-1, 1, 3) for o in object_points]
    img = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in image_points]
    rms, K, D, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(
        obj, img, tuple(image_size), None, None, flags=flags
    )
    D = D.ravel()
    rvecs = np.array([r.ravel() for r in rvecs])
    tvecs = np.array([t.ravel() for t in tvecs])
    n_obs = 2 * sum(len(o) for o in obj)
    n_par = 4 + D.size + 6 * len(obj)
    sse = float(sum(_sse(o, p, r, t, K, D) for o, p, r, t in zip(object_points, image_points, rvecs, tvecs)))
    return {
        "K": K,
        "D": D,
        "rvecs": rvecs,
        "tvecs": tvecs,
        "std": std_in.ravel()[: 4 + D.size].copy(),
        "per_view": per_view.ravel().copy(),
        "rms": float(rms),
        "sigma2": sse / (n_obs - n_par),
    }


def _sse(obj, pts, rvec, tvec, K, D):
    import cv2

    proj = cv2.projectPoints(np.asarray(obj, float).reshape(-1, 1, 3), rvec, tvec, K, D)[0].reshape(-1, 2)
    return float(((proj - np.asarray(pts, float).reshape(-1, 2)) ** 2).sum())


def calibrate_pair(object_points, left_points, right_points, image_size, cam1, cam2):
    """Solve for R and T with both cameras' intrinsics fixed.

    Parameters
    ----------
    object_points, left_points, right_points : list of ndarray
        Per view, ``(N_i, 3)`` board points and ``(N_i, 2)`` detections.
    image_size : tuple of int
    cam1, cam2 : dict
        :func:`calibrate_camera` results.

    Returns
    -------
    dict
        ``R`` (3, 3), ``T`` (3,), ``rvecs``, ``tvecs`` (V, 3) board poses in the
        left camera frame, ``per_view`` (V, 2) RMS error in the left and right
        image, px, ``rms`` over both images, px.
    """
    import cv2

    obj = [np.asarray(o, np.float32).reshape(-1, 1, 3) for o in object_points]
    p1 = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in left_points]
    p2 = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in right_points]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, *_STEREO_STOP)
    out = cv2.stereoCalibrateExtended(
        obj, p1, p2, cam1["K"].copy(), cam1["D"].copy(), cam2["K"].copy(), cam2["D"].copy(),
        tuple(image_size), None, None, flags=cv2.CALIB_FIX_INTRINSIC, criteria=criteria,
    )
    rms, R, T, rvecs, tvecs, per_view = out[0], out[5], out[6], out[9], out[10], out[11]
    return {
        "R": R,
        "T": T.ravel(),
        "rvecs": np.array([r.ravel() for r in rvecs]),
        "tvecs": np.array([t.ravel() for t in tvecs]),
        "per_view": np.asarray(per_view).reshape(-1, 2),
        "rms": float(rms),
    }


# ------------------------------------------------------------ uncertainty


def camera_jacobian(obj, rvec, tvec, K, D):
    """Projection of board points and its Jacobian, from ``cv2.projectPoints``.

    Parameters
    ----------
    obj : ndarray, shape (N, 3)
        Board points, board frame.
    rvec, tvec : ndarray, shape (3,)
        Board pose in the camera frame.
    K : ndarray, shape (3, 3)
    D : ndarray, shape (n,)

    Returns
    -------
    uv : ndarray, shape (2N,)
        Projections, interleaved ``(u0, v0, u1, v1, ...)``, px.
    J_pose : ndarray, shape (2N, 6)
        Derivatives with respect to (rvec, tvec).
    J_intr : ndarray, shape (2N, 4 + n)
        Derivatives with respect to (fx, fy, cx, cy, D...), the
        calibrateCameraExtended order.
    """
    import cv2

    uv, jac = cv2.projectPoints(np.asarray(obj, float).reshape(-1, 1, 3), np.asarray(rvec, float), np.asarray(tvec, float), K, D)
    return uv.reshape(-1), jac[:, :6], jac[:, 6:]


def _mono_jacobian(obj, rvecs, tvecs, K, D):
    """Jacobian of one camera's calibration problem: columns (intrinsics, pose_0, ..., pose_V-1)."""
    n_in = 4 + len(D)
    blocks = [camera_jacobian(o, r, t, K, D) for o, r, t in zip(obj, rvecs, tvecs)]
    rows = sum(b[0].size for b in blocks)
    J = np.zeros((rows, n_in + 6 * len(blocks)))
    at = 0
    for i, (uv, jp, ji) in enumerate(blocks):
        J[at : at + uv.size, :n_in] = ji
        J[at : at + uv.size, n_in + 6 * i : n_in + 6 * i + 6] = jp
        at += uv.size
    return J


def _stereo_jacobian(obj, rvecs, tvecs, rvec, T, K1, D1, K2, D2):
    """Jacobians of the stereo problem's residuals (all left, then all right rows).

    Returns ``J_phi`` with columns (pose_0..pose_V-1, rvec of R, T) and
    ``J_theta`` with columns (intrinsics1, intrinsics2).
    """
    import cv2

    V = len(obj)
    n1, n2 = 4 + len(D1), 4 + len(D2)
    sizes = [2 * len(o) for o in obj]
    m = sum(sizes)
    J_phi = np.zeros((2 * m, 6 * V + 6))
    J_theta = np.zeros((2 * m, n1 + n2))
    at = 0
    for i, o in enumerate(obj):
        s = sizes[i]
        _, jp, ji = camera_jacobian(o, rvecs[i], tvecs[i], K1, D1)
        J_phi[at : at + s, 6 * i : 6 * i + 6] = jp
        J_theta[at : at + s, :n1] = ji
        # Right-camera pose of the board: X_r = R (R_i X + t_i) + T.
        r3, t3, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(
            np.asarray(rvecs[i], float), np.asarray(tvecs[i], float), np.asarray(rvec, float), np.asarray(T, float)
        )
        _, jp3, ji2 = camera_jacobian(o, r3.ravel(), t3.ravel(), K2, D2)
        jr, jt = jp3[:, :3], jp3[:, 3:]
        rr = m + at
        J_phi[rr : rr + s, 6 * i : 6 * i + 3] = jr @ dr3dr1 + jt @ dt3dr1
        J_phi[rr : rr + s, 6 * i + 3 : 6 * i + 6] = jr @ dr3dt1 + jt @ dt3dt1
        J_phi[rr : rr + s, 6 * V : 6 * V + 3] = jr @ dr3dr2 + jt @ dt3dr2
        J_phi[rr : rr + s, 6 * V + 3 :] = jr @ dr3dt2 + jt @ dt3dt2
        J_theta[rr : rr + s, n1:] = ji2
        at += s
    return J_phi, J_theta


def parameter_covariance(obj, cam1, cam2, pair):
    """Covariance of all the rig's parameters together, by first-order back-propagation.

    Each camera's problem gives its intrinsics theta linear (to first order)
    in the image noise: ``d theta = A dy`` with ``A`` the intrinsics' rows of
    ``(J_c^T J_c)^-1 J_c^T``. The stereo step solves
    ``min_phi |y - f(theta_hat, phi)|^2`` for the board poses and (R, T) =
    phi with theta_hat fixed, so

        d phi = B dy,   B = (J_phi^T J_phi)^-1 J_phi^T (I - J_theta A),

    and with ``G = [A; B_RT]`` (B_RT: the rows of R and T)

        Cov(theta1, theta2, R, T) = G Sigma G^T,

    ``Sigma`` diagonal: each camera's residual variance sigma^2 (sum of
    squares over degrees of freedom of its own calibration) on its rows.
    This is H&Z's back-propagation [2]_ in sandwich form. The off-diagonal
    blocks matter: R and T absorb much of the intrinsics' error (the
    ``-J_theta A`` term), so the epipolar geometry is known far better than
    independent per-parameter uncertainties say.

    Parameters
    ----------
    obj : list of ndarray, shape (N_i, 3)
        Board points of each used view.
    cam1, cam2 : dict
        :func:`calibrate_camera` results (left, right) on these views.
    pair : dict
        :func:`calibrate_pair` result.

    Returns
    -------
    cov : ndarray, shape (n1 + n2 + 6, n1 + n2 + 6)
        Order: (fx, fy, cx, cy, D...) of each camera, then (rx, ry, rz, tx,
        ty, tz); px, unitless, rad and board units.
    """
    import cv2

    K1, D1, K2, D2 = cam1["K"], cam1["D"], cam2["K"], cam2["D"]
    n1, n2 = 4 + len(D1), 4 + len(D2)
    rvec = cv2.Rodrigues(pair["R"])[0].ravel()
    J_phi, J_theta = _stereo_jacobian(obj, pair["rvecs"], pair["tvecs"], rvec, pair["T"], K1, D1, K2, D2)
    m = J_phi.shape[0] // 2

    # theta's sensitivity to the image noise, through each camera's own problem.
    A = np.zeros((n1 + n2, 2 * m))
    for k, (cam, cols, rows) in enumerate(((cam1, slice(0, n1), slice(0, m)), (cam2, slice(n1, n1 + n2), slice(m, 2 * m)))):
        Jc = _mono_jacobian(obj, cam["rvecs"], cam["tvecs"], cam["K"], cam["D"])
        A[cols, rows] = np.linalg.lstsq(Jc, np.eye(Jc.shape[0]), rcond=None)[0][: cols.stop - cols.start]
    B = np.linalg.solve(J_phi.T @ J_phi, J_phi.T @ (np.eye(2 * m) - J_theta @ A))
    G = np.vstack([A, B[-6:]])
    sigma2 = np.concatenate([np.full(m, cam1["sigma2"]), np.full(m, cam2["sigma2"])])
    cov = (G * sigma2) @ G.T
    return 0.5 * (cov + cov.T)


# ---------------------------------------------------------------- epipolar


def epipolar_distances(left_points, right_points, calib):
    """Distances of corresponding points to each other's epipolar lines.

    Both point sets are undistorted first (to pixel coordinates of the ideal
    pinhole cameras K1, K2), then with ``F = K2^-T [T]x R K1^-1`` [2]_ the
    distance of each right point to ``F x_left`` and of each left point to
    ``F^T x_right``.

    Parameters
    ----------
    left_points, right_points : ndarray, shape (N, 2)
        Corresponding pixels in the distorted images.
    calib : StereoCalibration

    Returns
    -------
    d_left, d_right : ndarray, shape (N,)
        Distances in the left and right image, px.
    """
    def ideal(pts, K, D):
        xn = undistort_points(pts, K, D)
        return np.column_stack([xn, np.ones(len(xn))]) @ K.T

    x1 = ideal(left_points, calib.K1, calib.D1)
    x2 = ideal(right_points, calib.K2, calib.D2)
    t = calib.T
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(calib.K2).T @ tx @ calib.R @ np.linalg.inv(calib.K1)
    l2 = x1 @ F.T  # lines in the right image
    l1 = x2 @ F  # lines in the left image
    alg = np.einsum("ij,ij->i", x2, l2)
    return np.abs(alg) / np.hypot(l1[:, 0], l1[:, 1]), np.abs(alg) / np.hypot(l2[:, 0], l2[:, 1])


# ---------------------------------------------------------------- the run


def _fit(views, board, size):
    pts = board.object_points()
    obj = [pts[v.ids] for v in views]
    cam1 = calibrate_camera(obj, [v.left_points for v in views], size)
    cam2 = calibrate_camera(obj, [v.right_points for v in views], size)
    pair = calibrate_pair(obj, [v.left_points for v in views], [v.right_points for v in views], size, cam1, cam2)
    return obj, cam1, cam2, pair


def calibrate_stereo(folder, board, progress=None):
    """Calibrate a stereo rig from a folder of board image pairs.

    Pairs are found by :func:`find_pairs`, the board detected in each, each
    camera calibrated (:func:`calibrate_camera`), then the pair
    (:func:`calibrate_pair`, intrinsics fixed). A view whose RMS reprojection
    error in either image exceeds ``OUTLIER_FACTOR`` times the median of the
    views is rejected, worst first, and the calibration repeated without it,
    until none is left; every rejection is recorded with its reason.

    Parameters
    ----------
    folder : str or Path
    board : Board
    progress : callable, optional
        Called with one-line progress messages.

    Returns
    -------
    StereoCalibrationResult

    Raises
    ------
    InputError
        Folder missing or empty, no pairs, an unreadable image, images of
        different sizes, or fewer than ``MIN_VIEWS`` usable pairs.
    """
    folder = Path(folder)
    views = find_pairs(folder)
    size = detect_views(views, board, progress)

    def usable():
        return [v for v in views if v.rejected is None]

    if len(usable()) < MIN_VIEWS:
        found = len(usable())
        if found == 0 and all(v.rejected.startswith("board not found") for v in views if v.left and v.right):
            raise InputError(folder, f"the {_board_text(board)} was not found in any image pair")
        raise InputError(folder, f"only {found} usable image pair(s), need at least {MIN_VIEWS}: " + _reasons(views))

    while True:
        used = usable()
        obj, cam1, cam2, pair = _fit(used, board, size)
        worst = np.max(pair["per_view"], axis=1)
        med = float(np.median(worst))
        i = int(np.argmax(worst))
        if worst[i] <= OUTLIER_FACTOR * med or len(used) <= MIN_VIEWS:
            break
        used[i].rejected = (
            f"outlier: reprojection error {worst[i]:.3f} px is more than {OUTLIER_FACTOR:g}x the median "
            f"{med:.3f} px of the views (calibrated again without it)"
        )
        if progress:
            progress(f"pair {used[i].name}: rejected, {used[i].rejected}")
        if len(usable()) < MIN_VIEWS:
            raise InputError(folder, f"fewer than {MIN_VIEWS} consistent image pairs: " + _reasons(views))

    cov = parameter_covariance(obj, cam1, cam2, pair)
    calib = validate_calibration(
        StereoCalibration(size, cam1["K"], cam1["D"], cam2["K"], cam2["D"], pair["R"], pair["T"], cov=cov))
    d_all = []
    for v, errs in zip(used, pair["per_view"]):
        dl, dr = epipolar_distances(v.left_points, v.right_points, calib)
        v.errors = (float(errs[0]), float(errs[1]))
        v.epipolar = float(np.mean(np.concatenate([dl, dr])))
        d_all.append(np.concatenate([dl, dr]))
    return StereoCalibrationResult(
        calibration=calib,
        views=views,
        board=board,
        rms=pair["rms"],
        rms_left=cam1["rms"],
        rms_right=cam2["rms"],
        epipolar_error=float(np.mean(np.concatenate(d_all))),
    )


def _board_text(board):
    if board.kind == "charuco":
        return f"{board.cols}x{board.rows} ChArUco board ({board.dictionary})"
    return f"{board.cols}x{board.rows} chessboard"


def _reasons(views):
    bad = [f"{v.name}: {v.rejected}" for v in views if v.rejected]
    return "; ".join(bad[:4]) + (f"; and {len(bad) - 4} more" if len(bad) > 4 else "")
