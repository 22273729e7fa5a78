"""The occluding contours of curved faces (:mod:`partinspect.cad.outlines`)."""

import numpy as np
import pytest

from partinspect.cad.outlines import outline_images
from partinspect.cad.raycast import build_scene, camera_in_part
from partinspect.cad.visibility import visibility_mesh
from partinspect.poses import default_pose
from partinspect.simulate.rig import default_rig
from partinspect.vision.calibration import project_points

RADIUS, HEIGHT = 10.0, 8.0


@pytest.fixture(scope="module")
def disc():
    import cadquery as cq

    shape = cq.Workplane("XY").circle(RADIUS).extrude(HEIGHT).val()
    rig = default_rig((1224, 1024))
    return shape, rig, default_pose(shape, rig)


def _generatrices(rig, index, pose):
    """The disc's two contour generatrices seen from camera ``index``, sampled, in its image (px)."""
    K, D, R, t = camera_in_part(rig, index, pose)
    eye = -R.T @ t
    # A sight line grazes the side where (p - eye) . n = 0: r = rho cos(theta - phi).
    rho, phi = np.hypot(eye[0], eye[1]), np.arctan2(eye[1], eye[0])
    z = np.linspace(0.0, HEIGHT, 400)
    out = []
    for theta in (phi + np.arccos(RADIUS / rho), phi - np.arccos(RADIUS / rho)):
        pts = np.column_stack([np.full_like(z, RADIUS * np.cos(theta)), np.full_like(z, RADIUS * np.sin(theta)), z])
        out.append(project_points(pts, K, D, R, t))
    return out


def test_a_discs_outline_is_its_two_grazing_generatrices_in_each_image(disc):
    shape, rig, pose = disc
    out = outline_images(build_scene(visibility_mesh(shape)), rig, pose)
    assert len(out) == 1 and next(iter(out)).endswith(" outline")
    for index in (0, 1):
        samples = next(iter(out.values()))[index]
        lines = _generatrices(rig, index, pose)
        # Every sample lies on one of the exact generatrices' images, across
        # them within the mesh's chord error (0.05 mm, under half a px
        # here); along them the ends may slide by a px, where the image
        # of the rim runs tangent to the outline.
        across, along = [], []
        for line in lines:
            a, b = line[0], line[-1]
            u = (b - a) / np.linalg.norm(b - a)
            rel = samples - a
            across.append(np.abs(rel[:, 0] * u[1] - rel[:, 1] * u[0]))
            along.append(rel @ u)
        near = np.argmin(across, axis=0)
        assert np.min(across, axis=0).max() < 0.6
        # Each generatrix is found along its whole height.
        for k, line in enumerate(lines):
            t = np.sort(np.asarray(along)[k, near == k])
            height = np.linalg.norm(line[-1] - line[0])
            assert t[0] < 1.5 and t[-1] > height - 1.5 and np.diff(t).max() < 1.0, (t[0], t[-1], height)
            assert np.all(np.abs(t - np.clip(t, 0.0, height)) < 1.5)


@pytest.mark.parametrize("part", ["plate_path", "bracket_path"])
def test_the_sample_parts_bores_show_no_outline(part, request):
    from partinspect.cad.step import load_step

    shape = load_step(request.getfixturevalue(part))
    rig = default_rig((1224, 1024))
    # Their curved faces are bores: concave, their contours behind the walls.
    assert outline_images(build_scene(visibility_mesh(shape)), rig, default_pose(shape, rig)) == {}


def test_only_convex_faces_show_an_outline():
    # A generated plate with round vertical corners, a counterbore and a
    # countersink, at a pose where the countersink's cone turns edge-on to
    # the right camera: its facets, twisted between rings of vertices, fold
    # outwards at places there, but the cone is concave and shows no outline.
    from partinspect.cad.features import inventory
    from partinspect.simulate.parts import random_part
    from tests.simulate.scenes import ROUND_CORNER_POSE, ROUND_CORNER_SEED

    shape = random_part(ROUND_CORNER_SEED).shape
    pose = np.array(ROUND_CORNER_POSE)
    inv = inventory(shape)
    out = outline_images(build_scene(visibility_mesh(shape, inv)), default_rig(), pose)
    surfaces = {inv[key.split()[0]].surface for key in out}
    assert surfaces == {"cylinder"}, out.keys()
    corners = [f.id for f in inv.faces if f.surface == "cylinder" and f.centroid[2] > 1.0 and
               any(g.kind == "arc" and abs(g.radius - 5.0) < 1e-6 for g in inv.features if f.id in g.faces)]
    assert {key.split()[0] for key in out} <= set(corners)
    assert len(out) >= 2
