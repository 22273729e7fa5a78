"""A realistic industrial stereo rig: two 5 MP machine-vision cameras.

The numbers describe a common inspection set-up: 2/3" sensors of 2448 x 2048
pixels at 3.45 um pitch behind 25 mm lenses, 120 mm apart, converging on a
point 400 mm in front of the baseline. One pixel then covers about 0.055 mm
on the part, and the field of view is about 137 x 114 mm.

The two cameras are deliberately not identical (focal lengths differ by
0.1 %, principal points sit a few pixels off the centre in different
directions, the right camera is rolled by 0.2 degrees): code that silently
assumes an ideal rig fails on these images, as it would on a real one.

Frames follow DESIGN.md: OpenCV camera frames, the left camera is the rig
frame, ``X_right = R @ X_left + T`` in mm.
"""

import numpy as np

from partinspect.vision.calibration import StereoCalibration

__all__ = [
    "FULL_SIZE",
    "PIXEL_PITCH",
    "FOCAL_LENGTH",
    "BASELINE",
    "WORKING_DISTANCE",
    "default_rig",
    "SENSORS",
    "LENSES",
    "random_rig",
]

FULL_SIZE = (2448, 2048)
"""Sensor size in pixels (width, height) the rig numbers refer to."""
PIXEL_PITCH = 3.45e-3
"""Pixel pitch, mm."""
FOCAL_LENGTH = 25.0
"""Lens focal length, mm."""
BASELINE = 120.0
"""Distance between the projection centres, mm."""
WORKING_DISTANCE = 400.0
"""Distance from the baseline's midpoint to the fixation point, mm."""

# Per-camera departures from the ideal, at FULL_SIZE. Focal lengths in units
# of FOCAL_LENGTH / PIXEL_PITCH; principal-point offsets in pixels from the
# sensor centre (a few pixels is typical of lens mounting).
_FOCAL_SCALE = (1.0, 1.0011)
_PP_OFFSET = ((9.7, -6.3), (-12.4, 4.8))
# Small mounting error of the right camera (roll, pitch about its own axes),
# radians: real rigs are never perfectly aligned.
_RIGHT_ROLL = np.deg2rad(0.2)
_RIGHT_PITCH = np.deg2rad(0.03)
# OpenCV (k1, k2, p1, p2, k3): a modest barrel distortion of a 25 mm C-mount
# lens, about 4 px at the image corners, with a small decentring (tangential)
# part, different for the two lenses.
_DISTORTION = (
    (-0.062, 0.135, 2.1e-4, -1.7e-4, -0.41),
    (-0.055, 0.110, -1.3e-4, 2.4e-4, -0.30),
)


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _look_at(center, target):
    """World-to-camera rotation of an OpenCV camera at ``center`` looking at ``target``.

    The camera's y axis (image down) is kept in the plane spanned by the world
    y axis and the viewing direction, so the image is not rolled.
    """
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def _relative_pose(r_left, c_left, r_right, c_right):
    """``(R, T)`` with ``X_right = R @ X_left + T`` of two cameras ``X_cam = r (X_w - c)`` in a world frame."""
    return r_right @ r_left.T, r_right @ (c_left - c_right)


def _camera_matrix(index, image_size):
    w, h = image_size
    # Scale continuous image coordinates (origin at the top-left corner of the
    # top-left pixel, i.e. OpenCV's u + 0.5) so the field of view is kept.
    sx, sy = w / FULL_SIZE[0], h / FULL_SIZE[1]
    f = FOCAL_LENGTH / PIXEL_PITCH * _FOCAL_SCALE[index] * sx
    du, dv = _PP_OFFSET[index]
    cx = (FULL_SIZE[0] / 2 + du) * sx - 0.5
    cy = (FULL_SIZE[1] / 2 + dv) * sy - 0.5
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def default_rig(image_size=FULL_SIZE, distortion=False):
    """The default stereo calibration of the simulator.

    Parameters
    ----------
    image_size : tuple of int
        ``(width, height)`` in pixels. Sizes other than 2448 x 2048 keep the
        field of view: focal lengths and principal points are scaled by
        ``width / 2448`` (and ``height / 2048`` for the vertical principal
        point), as if the sensor were binned.
    distortion : bool
        False: zero distortion vectors. True: realistic radial
        ``(k1, k2, k3)`` and small tangential ``(p1, p2)`` distortion,
        different for the two lenses, about 4 px at the corners of a full
        2448 x 2048 image.

    Returns
    -------
    StereoCalibration
        Exact parameters (``std`` is empty: a simulated rig is known
        exactly). The cameras sit at ``(-60, 0, 0)`` and ``(60, 0, 0)`` of a
        frame centred on the baseline and both optical axes pass through
        ``(0, 0, 400)`` there (the right one to within its 0.03 degree pitch
        error); everything is expressed in the left camera frame.

    Examples
    --------
    >>> rig = default_rig()
    >>> round(rig.K1[0, 0], 1), round(rig.baseline, 3)
    (7246.4, 120.0)
    """
    w, h = (int(v) for v in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"image size must be positive, got {w}x{h}")
    half = BASELINE / 2
    fix = np.array([0.0, 0.0, WORKING_DISTANCE])
    c_left, c_right = np.array([-half, 0.0, 0.0]), np.array([half, 0.0, 0.0])
    r_left = _look_at(c_left, fix)
    r_right = _rot_x(_RIGHT_PITCH) @ _rot_z(_RIGHT_ROLL) @ _look_at(c_right, fix)
    R, T = _relative_pose(r_left, c_left, r_right, c_right)
    zero = np.zeros(5)
    D1, D2 = (np.array(d, float) for d in _DISTORTION) if distortion else (zero, zero.copy())
    return StereoCalibration(
        image_size=(w, h),
        K1=_camera_matrix(0, (w, h)),
        D1=D1,
        K2=_camera_matrix(1, (w, h)),
        D2=D2,
        R=R,
        T=T,
        std={},
    )


SENSORS = (
    ((2448, 2048), 3.45e-3),
    ((2064, 1544), 3.45e-3),
    ((1920, 1200), 5.86e-3),
    ((1440, 1080), 3.45e-3),
    ((2592, 2048), 4.8e-3),
)
"""``((width, height) px, pixel pitch mm)`` of common global-shutter
machine-vision sensors (Sony IMX264, IMX265, IMX174, IMX273; onsemi PYTHON
5000), from which :func:`random_rig` draws."""

LENSES = (12.0, 16.0, 25.0, 35.0, 50.0)
"""Fixed focal lengths of C-mount machine-vision lenses, mm."""


def random_rig(rng, field, *, distortion=True, tries=200):
    """A seeded stereo rig of two machine-vision cameras framing a part of size ``field``.

    A user's rig is not the simulator's default: other sensors, lenses,
    working distances, baselines, a baseline that need not be horizontal,
    cameras that differ a little. This draws one as a user would build it:
    a sensor (``SENSORS``) and a lens (``LENSES``) whose field of view at a
    working distance of at least ``2.5 field`` (perspective kept moderate)
    and at most 1200 mm has its shorter side 1.2-1.7 times ``field``; a
    vergence (the angle between the optical axes) of 12-35 degrees, which
    sets the baseline; the baseline turned about the viewing direction by
    any angle in +-90 degrees (a vertical rig makes vertical epipolar lines,
    a diagonal one diagonal lines); each camera's focal length 0.2 % apart
    (standard deviation), principal points about 1 % of the width off
    centre, the right camera rolled and pitched by mounting errors of 0.3
    and 0.05 degrees; and, with ``distortion``, Brown-Conrady distortion of
    a C-mount lens (barrel or mild pincushion, monotonic over the image,
    small decentring), different for the two lenses.

    Parameters
    ----------
    rng : numpy.random.Generator or int
    field : float
        Diameter of the part's bounding sphere, mm (it must fit the images
        whatever its pose).
    distortion : bool
    tries : int
        Sensor and lens draws before giving up.

    Returns
    -------
    StereoCalibration
        Exact parameters (``std`` empty), frames as :func:`default_rig`'s:
        both optical axes pass near the fixation point on the line through
        the baseline's midpoint, everything in the left camera frame.

    Raises
    ------
    ValueError
        If ``field`` is not positive, or no sensor and lens frame it.

    References
    ----------
    .. [1] Brown, D. C. (1966). Decentering distortion of lenses.
           Photogrammetric Engineering 32(3), 444-462.
    .. [2] Steger, C., Ulrich, M., Wiedemann, C. (2018). *Machine Vision
           Algorithms and Applications*, 2nd ed., ch. 2 (image acquisition:
           lenses, sensors) and 3.10 (stereo reconstruction). Wiley-VCH.
    """
    rng = np.random.default_rng(rng)
    if not field > 0:
        raise ValueError(f"field must be > 0 mm, got {field}")
    for _ in range(tries):
        (w, h), pitch = SENSORS[rng.integers(len(SENSORS))]
        lens = float(LENSES[rng.integers(len(LENSES))])
        distance = lens * field * rng.uniform(1.2, 1.7) / (min(w, h) * pitch)
        if 2.5 * field <= distance <= 1200.0:
            break
    else:
        raise ValueError(f"no sensor and lens frame a part of {field:g} mm between {2.5 * field:g} and 1200 mm")
    baseline = 2.0 * distance * np.tan(np.deg2rad(rng.uniform(12.0, 35.0)) / 2.0)
    turn = np.deg2rad(rng.uniform(-90.0, 90.0))
    along = np.array([np.cos(turn), np.sin(turn), 0.0])
    fix = np.array([0.0, 0.0, distance])
    c_left, c_right = -baseline / 2 * along, baseline / 2 * along
    r_left = _look_at(c_left, fix)
    mount = _rot_x(np.deg2rad(rng.normal(0.0, 0.05))) @ _rot_z(np.deg2rad(rng.normal(0.0, 0.3)))
    r_right = mount @ _look_at(c_right, fix)
    R, T = _relative_pose(r_left, c_left, r_right, c_right)
    cameras = []
    for _ in range(2):
        f = lens / pitch * (1.0 + rng.normal(0.0, 0.002))
        cx, cy = w / 2 + rng.normal(0.0, 0.01 * w) - 0.5, h / 2 + rng.normal(0.0, 0.01 * w) - 0.5
        K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        cameras.append((K, _lens_distortion(rng, np.hypot(w, h) / 2 / f) if distortion else np.zeros(5)))
    return StereoCalibration(
        image_size=(int(w), int(h)),
        K1=cameras[0][0],
        D1=cameras[0][1],
        K2=cameras[1][0],
        D2=cameras[1][1],
        R=R,
        T=T,
        std={},
    )


def _lens_distortion(rng, corner):
    """OpenCV ``(k1, k2, p1, p2, k3)`` of a C-mount lens, monotonic out to 1.2 ``corner`` (normalised radius).

    A radial model whose image radius ``r (1 + k1 r^2 + k2 r^4)`` turns back
    inside the image would fold it: such draws are made again.
    """
    r = np.linspace(0.0, 1.2 * corner, 200)
    while True:
        k1, k2 = rng.uniform(-0.15, 0.03), rng.uniform(-0.05, 0.15)
        if np.all(1.0 + 3.0 * k1 * r**2 + 5.0 * k2 * r**4 > 0.5):
            return np.array([k1, k2, rng.normal(0.0, 2e-4), rng.normal(0.0, 2e-4), 0.0])
