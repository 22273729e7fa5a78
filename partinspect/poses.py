"""Where the part sits in front of the rig: the default view and ``--pose``.

A pose is a 4 x 4 homogeneous ``part_to_camera`` matrix mapping part-frame
points (the STEP model's frame, mm) into the left camera (rig) frame.

The default view looks at the part from above and from its front-left, the
way an inspector sets a part under a fixed rig: the top face (+Z) and two
side faces (-X, -Y) show, tilted, and the image is rolled about the viewing
axis so that no edge parallel to a part axis runs along the (roughly
horizontal) epipolar lines, where stereo matching is ill-conditioned.
"""

import json
import re
from pathlib import Path

import numpy as np

from partinspect.errors import InputError

__all__ = ["PoseError", "VIEW_ELEVATION", "VIEW_AZIMUTH", "VIEW_ROLL", "bounds_of", "view_rotation", "default_pose", "parse_pose", "euler_pose", "fixation_point", "parse_views", "turned_pose"]

class PoseError(InputError, ValueError):
    """A ``--pose`` text that cannot be read.

    Both an `InputError` (the command line reports it in one line, exit
    code 2) and a `ValueError` (for library callers).
    """

    def __init__(self, problem):
        super().__init__(None, problem)


VIEW_ELEVATION = np.deg2rad(45.0)
"""Angle of the viewing direction above the part's XY plane: the top face is
tilted 45 degrees from facing the left camera (42 from the right one)."""
VIEW_AZIMUTH = np.deg2rad(212.0)
"""Direction, in the part's XY plane measured from +X towards +Y, from the
part to the camera: front-left, so that with the rig's convergence both
side faces (and holes in them) show in both images, obliquely but never
near edge-on."""
VIEW_ROLL = np.deg2rad(20.0)
"""Rotation about the optical axis, so that no edge along a part axis runs
near the epipolar lines, where its depth would be ill-determined."""


def fixation_point(rig):
    """The point the two optical axes converge on, in the rig (left camera) frame.

    Parameters
    ----------
    rig : StereoCalibration

    Returns
    -------
    point : ndarray, shape (3,)
        Midpoint of the shortest segment between the two optical axes, mm.

    Raises
    ------
    ValueError
        If the optical axes are parallel (a rig that does not converge).
    """
    c1, a1 = np.zeros(3), np.array([0.0, 0.0, 1.0])
    R, T = np.asarray(rig.R, float), np.asarray(rig.T, float)
    c2, a2 = -R.T @ T, R.T @ a1
    # Closest points c1 + s a1 and c2 + t a2 of two skew lines.
    b = a1 @ a2
    d = c1 - c2
    denom = 1.0 - b * b
    if denom < 1e-12:
        raise ValueError("the optical axes are parallel: the rig has no fixation point")
    s = (b * (a2 @ d) - (a1 @ d)) / denom
    t = ((a2 @ d) - b * (a1 @ d)) / denom
    return 0.5 * ((c1 + s * a1) + (c2 + t * a2))


def bounds_of(mesh_or_bounds):
    """Axis-aligned bounds of a mesh, a shape, or given bounds.

    Parameters
    ----------
    mesh_or_bounds : trimesh.Trimesh, cadquery.Shape or array_like
        Anything with ``.bounds`` (trimesh), a cadquery shape (its
        ``BoundingBox()``), or bounds as ``[[xmin, ymin, zmin], [xmax, ymax,
        zmax]]`` or six numbers in that order.

    Returns
    -------
    bounds : ndarray, shape (2, 3)
        Part frame, mm.
    """
    if hasattr(mesh_or_bounds, "BoundingBox"):
        bb = mesh_or_bounds.BoundingBox()
        return np.array([[bb.xmin, bb.ymin, bb.zmin], [bb.xmax, bb.ymax, bb.zmax]])
    b = getattr(mesh_or_bounds, "bounds", mesh_or_bounds)
    b = np.asarray(b, dtype=float).reshape(2, 3)
    if not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
        raise ValueError(f"not valid bounds: {b.tolist()}")
    return b


def view_rotation(elevation=VIEW_ELEVATION, azimuth=VIEW_AZIMUTH, roll=VIEW_ROLL):
    """Rotation part frame -> camera frame for a camera looking at the part.

    Parameters
    ----------
    elevation : float
        Radians above the part's XY plane of the direction from the part to
        the camera.
    azimuth : float
        Radians, that direction's heading in the part's XY plane from +X
        towards +Y.
    roll : float
        Radians of rotation about the optical axis; at zero the part's +Z
        points straight up in the image.

    Returns
    -------
    R : ndarray, shape (3, 3)
        ``x_cam = R @ X_part`` (directions).
    """
    ce = np.cos(elevation)
    to_camera = np.array([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)])
    z = -to_camera
    up = np.array([0.0, 0.0, 1.0])
    y = -(up - (up @ z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    c, s = np.cos(roll), np.sin(roll)
    roll_m = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return roll_m @ np.stack([x, y, z])


def _place(R, bounds, position):
    center = 0.5 * (bounds[0] + bounds[1])
    P = np.eye(4)
    P[:3, :3] = R
    P[:3, 3] = np.asarray(position, dtype=float) - R @ center
    return P


def default_pose(mesh_or_bounds, rig):
    """The default pose: the part's bounding-box centre at the rig's fixation point.

    Parameters
    ----------
    mesh_or_bounds : trimesh.Trimesh, cadquery.Shape or array_like
        See :func:`bounds_of`.
    rig : StereoCalibration

    Returns
    -------
    part_to_camera : ndarray, shape (4, 4)
        Rotation :func:`view_rotation` with the module's VIEW_* angles.
    """
    return _place(view_rotation(), bounds_of(mesh_or_bounds), fixation_point(rig))


def _rotation_xyz(rx, ry, rz):
    """Extrinsic rotations about fixed X, then Y, then Z (radians): Rz Ry Rx."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def euler_pose(angles_deg, mesh_or_bounds=None, position=None, rig=None):
    """A pose from rotation angles, as ``--pose RX,RY,RZ[,TX,TY,TZ]`` gives it.

    Parameters
    ----------
    angles_deg : sequence of 3 float
        Extrinsic rotations, degrees, about the camera's fixed x, then y, then
        z axes, applied to the part as if its frame were first aligned with
        the left camera frame (so ``0,0,0`` shows the part's -Z face, its +X
        pointing right and +Y down in the image; ``180,0,0`` shows +Z).
        The rotation is about the part's bounding-box centre.
    mesh_or_bounds : optional
        See :func:`bounds_of`; without it the rotation is about the part
        frame's origin.
    position : sequence of 3 float, optional
        Where the centre goes in the left camera frame, mm; default the
        rig's fixation point.
    rig : StereoCalibration, optional
        For the fixation point; needed when ``position`` is not given.

    Returns
    -------
    part_to_camera : ndarray, shape (4, 4)
    """
    if position is None and rig is None:
        raise ValueError("euler_pose needs a rig (for its fixation point) or a position")
    R = _rotation_xyz(*np.deg2rad(np.asarray(angles_deg, dtype=float)))
    bounds = np.zeros((2, 3)) if mesh_or_bounds is None else bounds_of(mesh_or_bounds)
    if position is None:
        position = fixation_point(rig)
    return _place(R, bounds, position)


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUMBERS = re.compile(rf"^\s*{_NUMBER}\s*(?:,\s*{_NUMBER}\s*)*$")


def _check_matrix(path, P):
    P = np.asarray(P, dtype=float)
    if P.shape != (4, 4):
        raise InputError(path, f"part_to_camera must be a 4x4 matrix, got shape {'x'.join(map(str, P.shape))}")
    if not np.all(np.isfinite(P)):
        raise InputError(path, "part_to_camera contains NaN or infinite values")
    if np.abs(P[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise InputError(path, "part_to_camera's last row must be 0, 0, 0, 1")
    R = P[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > 1e-6 or np.linalg.det(R) < 0:
        raise InputError(path, f"part_to_camera's 3x3 block is not a rotation (R^T R - I up to {err:.2g}, det {np.linalg.det(R):.3g})")
    return P


def parse_pose(text, mesh_or_bounds=None, rig=None):
    """Read a ``--pose`` argument.

    Parameters
    ----------
    text : str or os.PathLike
        ``"RX,RY,RZ"`` or ``"RX,RY,RZ,TX,TY,TZ"`` (degrees, then mm; see
        :func:`euler_pose`), or the path of a JSON file holding
        ``{"part_to_camera": [[4 x 4]]}``.
    mesh_or_bounds : optional
        The part, for its bounding-box centre (see :func:`bounds_of`).
    rig : StereoCalibration, optional
        For the default position, its fixation point.

    Returns
    -------
    part_to_camera : ndarray, shape (4, 4)

    Raises
    ------
    PoseError
        (an InputError and a ValueError) Angles text with the wrong count of
        numbers, or a position with the part at or behind the camera.
    InputError
        A JSON file that is missing, unreadable or does not hold a rigid 4x4
        ``part_to_camera``.
    """
    s = str(text)
    if _NUMBERS.match(s):
        values = [float(v) for v in s.split(",")]
        if len(values) not in (3, 6):
            raise PoseError(f"--pose: expected RX,RY,RZ or RX,RY,RZ,TX,TY,TZ (degrees, mm), got {len(values)} numbers in {s!r}")
        position = values[3:] if len(values) == 6 else None
        if position is not None and position[2] <= 0:
            raise PoseError(f"--pose: TZ must be positive (in front of the left camera), got {position[2]:g} mm")
        return euler_pose(values[:3], mesh_or_bounds, position, rig)
    path = Path(s)
    if not path.is_file():
        looks_numeric = re.fullmatch(r"[\s\d.,eE+-]*", s) is not None
        if looks_numeric:
            raise PoseError(f"--pose: expected RX,RY,RZ or RX,RY,RZ,TX,TY,TZ (comma-separated numbers), got {s!r}")
        raise InputError(path, "pose file not found" if not path.exists() else "pose path is not a file")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"not a readable JSON pose file ({exc})") from None
    if not isinstance(data, dict) or "part_to_camera" not in data:
        raise InputError(path, 'expected a JSON object with "part_to_camera": [[4x4]]')
    try:
        P = np.array(data["part_to_camera"], dtype=float)
    except (TypeError, ValueError):
        raise InputError(path, "part_to_camera must be a 4x4 array of numbers") from None
    return _check_matrix(path, P)


def parse_views(text):
    """Read ``--views``: one ``RX,RY,RZ`` turn of the part per view, separated by ``;``.

    Parameters
    ----------
    text : str
        E.g. ``"0,0,0;0,0,120;0,0,240"`` (degrees; a turntable at 0, 120
        and 240 degrees about the part's Z).

    Returns
    -------
    list of ndarray, shape (3,)
        Degrees, one per view, in the order given.

    Raises
    ------
    PoseError
        An empty list, or a view that is not three numbers.
    """
    views = []
    for k, item in enumerate(str(text).split(";"), 1):
        if not item.strip():
            continue
        if not _NUMBERS.match(item) or len(item.split(",")) != 3:
            raise PoseError(f"--views: view {k} must be RX,RY,RZ (degrees), got {item.strip()!r}")
        views.append(np.array([float(v) for v in item.split(",")]))
    if not views:
        raise PoseError(f"--views: expected RX,RY,RZ;RX,RY,RZ;... (degrees), got {text!r}")
    return views


def turned_pose(part_to_camera, angles_deg, mesh_or_bounds=None):
    """A pose with the part first turned in its own frame, as on a turntable or re-placed on the fixture.

    Parameters
    ----------
    part_to_camera : ndarray, shape (4, 4)
        The pose without the turn.
    angles_deg : sequence of 3 float
        Extrinsic rotations, degrees, about the part frame's fixed X, then
        Y, then Z axes through the bounding-box centre (``0,0,120``: a
        turntable's 120 degrees about the part's Z).
    mesh_or_bounds : optional
        See :func:`bounds_of`; without it the turn is about the part
        frame's origin.

    Returns
    -------
    ndarray, shape (4, 4)
        ``part_to_camera @ Turn``: a part point ``X`` is turned to
        ``c + R (X - c)`` and then seen as the unturned part was.
    """
    bounds = np.zeros((2, 3)) if mesh_or_bounds is None else bounds_of(mesh_or_bounds)
    c = 0.5 * (bounds[0] + bounds[1])
    turn = np.eye(4)
    turn[:3, :3] = _rotation_xyz(*np.deg2rad(np.asarray(angles_deg, dtype=float)))
    turn[:3, 3] = c - turn[:3, :3] @ c
    return np.asarray(part_to_camera, float) @ turn
