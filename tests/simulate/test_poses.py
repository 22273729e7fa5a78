import json

import numpy as np
import pytest

from partinspect.errors import InputError
from partinspect.poses import bounds_of, default_pose, euler_pose, parse_pose, view_rotation
from partinspect.simulate.rig import default_rig
from partinspect.poses import fixation_point
from partinspect.vision.calibration import camera_pose, project_points

RIG = default_rig()


def _line_of_sight(rig, index, point_rig):
    centre, _ = camera_pose(rig, index)
    v = centre - point_rig
    return v / np.linalg.norm(v)


def _to_rig(P, X):
    return np.asarray(X, float) @ P[:3, :3].T + P[:3, 3]


def test_default_pose_puts_the_box_centre_at_the_fixation_point(plate):
    P = default_pose(plate.mesh, RIG)
    b = bounds_of(plate.mesh)
    np.testing.assert_allclose(_to_rig(P, b.mean(axis=0)[None])[0], fixation_point(RIG), atol=1e-9)
    np.testing.assert_allclose(P[:3, :3] @ P[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(P[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_array_equal(P[3], [0, 0, 0, 1])
    # Same from a cadquery shape, a trimesh and bare bounds.
    np.testing.assert_allclose(default_pose(plate.shape, RIG), P, atol=1e-6)
    np.testing.assert_allclose(default_pose(b.ravel(), RIG), P, atol=1e-12)


@pytest.mark.parametrize("name", ["plate", "bracket"])
def test_default_pose_shows_top_and_two_sides_obliquely(parts, name):
    part = parts(name)
    P = default_pose(part.shape, RIG)
    centre = _to_rig(P, bounds_of(part.shape).mean(axis=0)[None])[0]
    for index in (0, 1):
        sight = _line_of_sight(RIG, index, centre)
        angle = {k: np.degrees(np.arccos(P[:3, :3] @ np.array(n, float) @ sight))
                 for k, n in {"+Z": (0, 0, 1), "-Y": (0, -1, 0), "-X": (-1, 0, 0)}.items()}
        assert 30 <= angle["+Z"] <= 50, angle  # the top tilted 30-45 degrees (about)
        assert angle["-Y"] < 75 and angle["-X"] < 75, angle  # both sides show, not edge-on


def _epipolar_direction(rig, index, uv):
    """Unit direction of the epipolar line through pixel uv of camera index."""
    K1, K2 = rig.K1, rig.K2
    tx = np.array([[0, -rig.T[2], rig.T[1]], [rig.T[2], 0, -rig.T[0]], [-rig.T[1], rig.T[0], 0]])
    F = np.linalg.inv(K2).T @ tx @ rig.R @ np.linalg.inv(K1)  # x2^T F x1 = 0
    # Every epipolar line of an image passes through its epipole: F e1 = 0
    # in the left image, F^T e2 = 0 in the right one.
    e = np.linalg.svd(F if index == 0 else F.T)[2][-1]
    l = np.cross(e, np.array([uv[0], uv[1], 1.0]))
    d = np.array([l[1], -l[0]])
    return d / np.linalg.norm(d)


@pytest.mark.parametrize("name", ["plate", "bracket"])
def test_no_straight_edge_runs_along_the_epipolar_lines(parts, name):
    part = parts(name)
    P = default_pose(part.shape, RIG)
    worst = 90.0
    for f in part.inv.of_kind("line"):
        for index in (0, 1):
            R = None if index == 0 else RIG.R
            t = None if index == 0 else RIG.T
            K = RIG.K1 if index == 0 else RIG.K2
            ends = project_points(_to_rig(P, [f.start, f.end]), K, np.zeros(5), R, t)
            d = ends[1] - ends[0]
            if np.linalg.norm(d) < 1e-6:
                continue  # seen end-on
            mid = ends.mean(axis=0)
            e = _epipolar_direction(RIG, index, mid)
            cos = abs(d @ e) / np.linalg.norm(d)
            worst = min(worst, np.degrees(np.arccos(min(1.0, cos))))
    assert worst >= 10.0


def test_epipolar_direction_helper_is_right():
    # A point and its epipolar line in the other image: the match lies on it.
    # Points along one left ray image on one epipolar line of the right image.
    X = np.outer([0.9, 1.1], [5.0, -3.0, 400.0])
    uv2 = project_points(X, RIG.K2, RIG.D2, RIG.R, RIG.T)
    d = _epipolar_direction(RIG, 1, uv2[0])
    v = (uv2[1] - uv2[0]) / np.linalg.norm(uv2[1] - uv2[0])
    assert abs(abs(d @ v) - 1) < 1e-9
    # And the other way round.
    centre, _ = camera_pose(RIG, 1)
    X = centre + np.outer([0.9, 1.1], np.array([5.0, -3.0, 400.0]) - centre)
    uv1 = project_points(X, RIG.K1, RIG.D1)
    d = _epipolar_direction(RIG, 0, uv1[0])
    v = (uv1[1] - uv1[0]) / np.linalg.norm(uv1[1] - uv1[0])
    assert abs(abs(d @ v) - 1) < 1e-9


@pytest.mark.parametrize("name", ["plate", "bracket"])
def test_holes_are_seen_obliquely_not_edge_on(parts, name):
    part = parts(name)
    P = default_pose(part.shape, RIG)
    normals = set()
    for f in part.inv.of_kind("circle"):
        normals.add(tuple(np.round(f.normal, 6)))
        centre = _to_rig(P, f.center[None])[0]
        for index in (0, 1):
            cos = abs(P[:3, :3] @ f.normal @ _line_of_sight(RIG, index, centre))
            assert 20 <= np.degrees(np.arccos(cos)) <= 75
    if name == "bracket":
        assert len(normals) == 2  # top-face holes and wall holes both checked


@pytest.mark.parametrize("name", ["plate", "bracket"])
def test_part_is_well_inside_both_images(parts, name):
    part = parts(name)
    P = default_pose(part.shape, RIG)
    W, H = RIG.image_size
    pts = _to_rig(P, part.mesh.vertices)
    for index in (0, 1):
        K, D, R, t = RIG.camera(index)
        uv = project_points(pts, K, D, R, t)
        assert uv[:, 0].min() > 0.05 * W and uv[:, 0].max() < 0.95 * W
        assert uv[:, 1].min() > 0.05 * H and uv[:, 1].max() < 0.95 * H


def test_view_rotation_is_a_rotation():
    R = view_rotation(0.7, 2.0, 0.3)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_parse_pose_angles():
    bounds = np.array([[0, 0, 0], [80, 60, 10.0]])
    P = parse_pose("0,0,0", bounds, RIG)
    np.testing.assert_allclose(P[:3, :3], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(_to_rig(P, [[40, 30, 5]])[0], fixation_point(RIG), atol=1e-12)
    # 180 about x shows the top face: +Z points at the camera (-z).
    P = parse_pose("180, 0, 0", bounds, RIG)
    np.testing.assert_allclose(P[:3, :3] @ [0, 0, 1], [0, 0, -1], atol=1e-12)
    # Extrinsic X then Y then Z: R = Rz Ry Rx.
    P = parse_pose("90,90,0", bounds, RIG)
    Rx = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    Ry = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    np.testing.assert_allclose(P[:3, :3], Ry @ Rx, atol=1e-12)
    P = parse_pose("10,20,30,1,-2,350", bounds, RIG)
    np.testing.assert_allclose(_to_rig(P, [[40, 30, 5]])[0], [1, -2, 350], atol=1e-12)
    np.testing.assert_allclose(P, euler_pose([10, 20, 30], bounds, [1, -2, 350]), atol=1e-15)
    # Without bounds: about the part origin.
    P = parse_pose("0,0,0,0,0,300")
    np.testing.assert_allclose(P[:3, 3], [0, 0, 300])


@pytest.mark.parametrize("text", ["1,2", "1,2,3,4", "1,2,3,4,5,6,7", "1,,2"])
def test_parse_pose_rejects_wrong_counts(text):
    with pytest.raises(ValueError, match="--pose"):
        parse_pose(text)


def test_parse_pose_rejects_a_part_behind_the_camera():
    with pytest.raises(ValueError, match="TZ"):
        parse_pose("0,0,0,0,0,-5")


def test_parse_pose_json(tmp_path):
    P = default_pose([[0, 0, 0], [80, 60, 10]], RIG)
    path = tmp_path / "pose.json"
    path.write_text(json.dumps({"part_to_camera": P.tolist()}))
    np.testing.assert_array_equal(parse_pose(str(path)), P)
    np.testing.assert_array_equal(parse_pose(path), P)


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "JSON"),
        ('{"pose": 1}', "part_to_camera"),
        ('{"part_to_camera": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}', "4x4"),
        ('{"part_to_camera": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 400], [0, 0, 0, 1]]}', "rotation"),
        ('{"part_to_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 400], [0, 0, 1, 1]]}', "last row"),
        ('{"part_to_camera": [["a", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 400], [0, 0, 0, 1]]}', "numbers"),
    ],
)
def test_parse_pose_bad_json(tmp_path, content, message):
    path = tmp_path / "pose.json"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as info:
        parse_pose(str(path))
    assert str(path) in str(info.value)


def test_parse_pose_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        parse_pose(str(tmp_path / "nope.json"))
