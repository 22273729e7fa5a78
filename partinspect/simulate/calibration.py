"""A stated calibration as a real calibration makes it: a board seen by the true rig, calibrated.

A calibration is never exact, and its errors are not independent per
parameter: they are what one board session leaves, correlated as the
calibration's own least squares correlates them (a focal length error comes
with a matching translation error). So the stated calibration of a render
is made the way a user makes one: a chessboard in ``n_views`` poses before
the true rig, its corners projected through the true cameras (lens model
included) with Gaussian detection noise, and the same calibration
``inspect calibrate`` runs (:func:`partinspect.vision.stereo_calibration.calibrate_camera`,
:func:`~partinspect.vision.stereo_calibration.calibrate_pair`,
:func:`~partinspect.vision.stereo_calibration.parameter_covariance`). The
result states its parameters' covariance, and is off the true rig by one
draw of what it describes.

Frames: the left camera is the rig frame; mm, radians.

References
----------
.. [1] Zhang, Z. (2000). A flexible new technique for camera calibration.
       IEEE Trans. PAMI 22(11), 1330-1334.
"""

from dataclasses import replace

import numpy as np

from partinspect.vision.calibration import StereoCalibration, project_points, validate_calibration
from partinspect.vision.stereo_calibration import Board, calibrate_camera, calibrate_pair, parameter_covariance

__all__ = ["CORNER_NOISE", "N_VIEWS", "DRIFTS", "calibration_board", "board_views", "simulated_calibration",
           "drifted_rig"]

CORNER_NOISE = 0.1
"""px: standard deviation of a detected chessboard corner (``cornerSubPix``
on a sharp board reaches 0.05-0.1 px; OpenCV's sample pairs calibrate to
0.2 px RMS)."""

N_VIEWS = 15
"""Board poses of one calibration session (OpenCV's sample set has 13)."""

_MAX_TILT = np.deg2rad(35.0)


def calibration_board(rig):
    """A 9 x 6 chessboard whose side is about 70 % of the field of view at the working distance, mm squares."""
    from partinspect.poses import fixation_point

    z = float(fixation_point(rig)[2])
    width_mm = rig.image_size[0] / rig.K1[0, 0] * z
    return Board("chessboard", 9, 6, round(0.7 * width_mm / 10.0, 1))


def board_views(rig, board, rng, n_views=N_VIEWS, margin=20.0):
    """Board poses seen whole by both cameras, and the corners' true pixels.

    Poses are drawn about the rig's fixation point: the board's centre
    within a quarter of its side sideways and a tenth of the distance in
    depth, tilted up to 35 deg about both board axes and turned about its
    normal at random, kept when every corner lies ``margin`` px inside both
    images.

    Returns
    -------
    list of (ndarray (N, 2), ndarray (N, 2))
        Left and right pixels of the corners (``board.object_points()``
        order), noise-free.
    """
    import cv2

    from partinspect.poses import fixation_point

    obj = board.object_points()
    centre = obj.mean(axis=0)
    target = fixation_point(rig)
    side = float(np.ptp(obj[:, 0]))
    w, h = rig.image_size
    views = []
    for _ in range(100 * n_views):
        if len(views) == n_views:
            break
        tilt = rng.uniform(-_MAX_TILT, _MAX_TILT, 2)
        R = cv2.Rodrigues(np.array([tilt[0], tilt[1], 0.0]))[0] @ cv2.Rodrigues(
            np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]))[0]
        c = target + np.r_[rng.uniform(-0.25, 0.25, 2) * side, rng.uniform(-0.1, 0.1) * target[2]]
        X = (obj - centre) @ R.T + c
        pix = [project_points(X, *rig.camera(i)) for i in (0, 1)]
        inside = all(np.isfinite(p).all() and p[:, 0].min() > margin and p[:, 1].min() > margin
                     and p[:, 0].max() < w - 1 - margin and p[:, 1].max() < h - 1 - margin for p in pix)
        if inside:
            views.append((pix[0], pix[1]))
    if len(views) < n_views:
        raise ValueError(f"only {len(views)} of {n_views} board poses fit both images")
    return views


def simulated_calibration(rig, rng, *, n_views=N_VIEWS, corner_noise=CORNER_NOISE, board=None):
    """The calibration a board session with this rig would state.

    Parameters
    ----------
    rig : StereoCalibration
        The true rig (its image size set).
    rng : numpy.random.Generator
        Draws the board poses and the corner noise.
    n_views : int
    corner_noise : float
        px, per corner coordinate.
    board : Board, optional
        Default :func:`calibration_board`.

    Returns
    -------
    StereoCalibration
        With ``cov`` and ``std`` (intrinsics of both cameras, extrinsics), as
        ``inspect calibrate`` writes it.
    """
    board = board or calibration_board(rig)
    obj = board.object_points()
    views = board_views(rig, board, rng, n_views)
    left = [p + rng.normal(0.0, corner_noise, p.shape) for p, _ in views]
    right = [q + rng.normal(0.0, corner_noise, q.shape) for _, q in views]
    objs = [obj] * len(views)
    size = tuple(rig.image_size)
    cam1 = calibrate_camera(objs, left, size)
    cam2 = calibrate_camera(objs, right, size)
    pair = calibrate_pair(objs, left, right, size, cam1, cam2)
    cov = parameter_covariance(objs, cam1, cam2, pair)
    return validate_calibration(
        StereoCalibration(size, cam1["K"], cam1["D"], cam2["K"], cam2["D"], pair["R"], pair["T"], cov=cov))


DRIFTS = ("shift", "roll")
"""How :func:`drifted_rig` can move the right camera after calibration."""


def drifted_rig(rig, kind, px):
    """The rig after its right camera moved, as a calibrated rig drifts on a shop floor.

    Parameters
    ----------
    rig : StereoCalibration
        As calibrated (its image size set).
    kind : {"shift", "roll"}
        "shift": the right camera's principal point moves down by ``px``
        (a refocused lens, a sensor that settled), which moves every
        epipolar line across itself by about ``px``; "roll": the right
        camera turns about its optical axis so that points at the image's
        side edges move by ``px`` across the epipolar lines (a bumped
        camera), a drift that grows across the image.
    px : float
        Pixels, signed.

    Returns
    -------
    StereoCalibration
        The moved rig, without stated uncertainties (it is a true rig).
    """
    import cv2

    if kind == "shift":
        K2 = np.array(rig.K2, float)
        K2[1, 2] += px
        return replace(rig, K2=K2, std={}, cov=None)
    if kind == "roll":
        Q = cv2.Rodrigues(np.array([0.0, 0.0, px / (0.5 * rig.image_size[0])]))[0]
        return replace(rig, R=Q @ np.asarray(rig.R, float), T=Q @ np.asarray(rig.T, float).ravel(), std={}, cov=None)
    raise ValueError(f"unknown drift {kind!r}: expected one of {', '.join(DRIFTS)}")
