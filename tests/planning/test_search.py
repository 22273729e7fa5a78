"""A badly chosen pose: the plan names what it spoils and proposes a pose that fixes it."""

import math

import numpy as np
import pytest

from partinspect.planning.predict import predict_pose
from partinspect.planning.search import FixturePose, fixture_pose, pose_text, search_poses
from tests.planning.conftest import view_pose

EDGE_ON_VIEW = (10.0, 250.0, 20.0)
"""10 degrees above the plate's top face: its holes are seen nearly edge-on."""
EPIPOLAR_VIEW = (45.0, 270.0, 0.0)
"""Square to the front face, unrolled: the front edge (line-5, "front-top-edge")
runs along the epipolar lines."""


@pytest.fixture(scope="module")
def rig():
    """A quarter of the default rig's resolution: the geometry of the views is the same, the search faster."""
    from partinspect.simulate.rig import default_rig

    return default_rig((612, 512))


def _search(plate, rig, chars, view, **limits):
    start = view_pose(plate, rig, *view)
    b = np.asarray(plate.mesh.bounds, float)
    center = 0.5 * (b[0] + b[1])

    # Decidable when U <= T: what is tested is that the pose, not the noise budget, spoils them.
    def predict(P, fp):
        return predict_pose(plate.inv, plate.scene, rig, P, chars, label=fp.label, max_ratio=1.0,
                            angles=(fp.rotation, fp.tilt_x, fp.tilt_y))

    return search_poses(predict, start, center, **limits), center


@pytest.fixture(scope="module")
def edge_on(plate, rig, spec_characteristics):
    return _search(plate, rig, spec_characteristics, EDGE_ON_VIEW, rotation=0.0, max_tilt=30.0)


@pytest.fixture(scope="module")
def epipolar(plate, rig, spec_characteristics):
    return _search(plate, rig, spec_characteristics, EPIPOLAR_VIEW, rotation=60.0, step=30.0, max_tilt=0.0)


def test_edge_on_holes_named_and_a_tilt_fixes_them(edge_on, plate, rig):
    result, center = edge_on
    why = {c.id: c.reason for c in result.start.characteristics}
    for cid, fid in (("circle-4.diameter", "circle-4"), ("circle-4.position", "circle-4"),
                     ("circle-8.diameter", "circle-8")):
        assert f"{fid} is seen nearly edge-on" in why[cid]
    assert "edge-on" in why["distance(circle-2,circle-4)"]
    best = result.best
    for fid in ("circle-2", "circle-4", "circle-8"):
        assert best.features[fid].status == "measured" and best.features[fid].view_angle < np.deg2rad(65)
    got = {c.id: c for c in best.characteristics}
    assert all(math.isfinite(got[cid].U) for cid in why if cid != "front-top-edge.straightness")
    assert {"circle-4.diameter", "circle-8.diameter", "distance(circle-2,circle-4)"} <= {
        c.id for c in best.characteristics if c.decidable}
    assert best.angles[0] == 0.0 and best.angles[1:] != (0.0, 0.0)
    # The proposal is given as --pose text that reproduces the pose.
    from partinspect.poses import parse_pose

    P = parse_pose(pose_text(best.part_to_camera, center), np.asarray(plate.mesh.bounds), rig)
    assert np.allclose(P, best.part_to_camera, atol=2e-3)


def test_line_along_the_epipolar_lines_named_and_a_rotation_fixes_it(epipolar):
    result, _ = epipolar
    start = {c.id: c for c in result.start.characteristics}
    c = start["front-top-edge.straightness"]
    assert not math.isfinite(c.U)
    assert "line-5 runs" in c.reason and "from the epipolar lines" in c.reason
    assert result.start.features["line-5"].status == "degenerate"
    best = result.best
    assert best.angles[0] != 0.0
    assert best.features["line-5"].status == "measured"
    assert best.features["line-5"].epipolar_angle > np.deg2rad(20)
    assert all(math.isfinite(c.U) for c in best.characteristics)
    assert best.n_decidable >= result.start.n_decidable


def test_fixture_pose_turns_about_the_centre():
    start = np.eye(4)
    start[:3, 3] = [1.0, 2.0, 400.0]
    c = np.array([10.0, 5.0, 2.0])
    P = fixture_pose(start, c, FixturePose(90.0, 10.0, -5.0))
    assert np.allclose(P[:3, :3] @ c + P[:3, 3], c + start[:3, 3])
    assert np.allclose(P[:3, :3] @ [0, 0, 1.0], fixture_pose(start, c, FixturePose(0.0, 10.0, -5.0))[:3, 2])
    assert math.isclose(np.linalg.det(P[:3, :3]), 1.0)
