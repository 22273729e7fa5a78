import json

import numpy as np
import pytest

from partinspect.simulate.folder import SAMPLES, render_to_folder
from partinspect.simulate.truth import SCHEMA, deviated_geometry, drawn_radius, feature_visibility, to_json
from partinspect.cad.edge_sampling import feature_geometry, sample_edge
from partinspect.frames import orthonormal_frame
from tests.simulate.scenes import step_path

SMALL = (612, 512)
DEVIATIONS = ["circle-4.diameter=0.08", "circle-8.center=0.05,-0.03,0"]


@pytest.fixture(scope="module")
def folder_run(tmp_path_factory):
    """The plate rendered to a folder twice with the same arguments, once with another seed."""
    out = []
    for k, seed in enumerate((1, 1, 2)):
        d = tmp_path_factory.mktemp(f"render{k}")
        messages = []
        truth = render_to_folder(
            step_path("plate"), d, noise=2.0, seed=seed, deviations=DEVIATIONS, image_size=SMALL, progress=messages.append
        )
        out.append((d, truth, messages))
    return out


FILES = ("images/left.png", "images/right.png", "images/calibration.yaml", "truth.json")


def test_render_to_folder_writes_everything(folder_run):
    d, truth, messages = folder_run[0]
    for name in FILES:
        assert (d / name).is_file()
    assert not [p for p in d.rglob("*") if p.name.startswith(".")]  # no temporary files left
    assert len(messages) >= 5 and all(isinstance(m, str) for m in messages)
    import cv2

    from partinspect.vision.calibration import read_calibration

    img = cv2.imread(str(d / "images/left.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (SMALL[1], SMALL[0]) and img.dtype == np.uint8
    calib = read_calibration(d / "images/calibration.yaml")
    assert calib.image_size == SMALL
    assert json.loads((d / "truth.json").read_text()) == json.loads(to_json(truth))


def test_same_arguments_same_bytes_other_seed_other_images(folder_run):
    (a, _, _), (b, _, _), (c, _, _) = folder_run
    for name in FILES:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert (a / "images/left.png").read_bytes() != (c / "images/left.png").read_bytes()
    assert (a / "images/calibration.yaml").read_bytes() == (c / "images/calibration.yaml").read_bytes()
    ta, tc = (json.loads((x / "truth.json").read_text()) for x in (a, c))
    assert ta["seed"] == 1 and tc["seed"] == 2
    ta["seed"] = tc["seed"] = 0
    assert ta == tc  # only the seed differs in the truth


def test_truth_contents(folder_run, plate):
    _, truth, _ = folder_run[0]
    assert truth["schema"] == SCHEMA == "truth/1"
    assert truth["units"] == "mm"
    assert truth["image_size"] == list(SMALL)
    assert truth["noise"] == 2.0 and truth["seed"] == 1 and truth["blur_sigma"] == 0.6
    assert truth["distortion"] is False
    assert truth["sampling"]["rays_per_supersampled_pixel"] == SAMPLES**2 == 256
    P = np.array(truth["part_to_camera"])
    from partinspect.poses import default_pose
    from partinspect.simulate.rig import default_rig

    np.testing.assert_allclose(P, default_pose(plate.shape, default_rig(SMALL)), atol=1e-9)
    assert [d["feature"] for d in truth["deviations"]] == ["circle-4", "circle-8"]
    assert truth["deviations"][0]["param"] == "diameter" and truth["deviations"][0]["delta"] == 0.08
    assert truth["deviations"][1]["delta"] == [0.05, -0.03, 0.0]
    ids = [f["id"] for f in truth["features"]]
    assert ids == [f.id for f in plate.inv.features]
    for f in truth["features"]:
        nominal = feature_geometry(plate.inv[f["id"]])
        for key, value in nominal.items():
            np.testing.assert_allclose(f["nominal"][key], value, atol=1e-9)
        assert set(f["visibility"]) == {"left", "right"}
        for cam in f["visibility"].values():
            assert set(cam) == {"in_image", "unoccluded", "contrast", "visible"}
            assert 0 <= cam["visible"] <= min(cam["in_image"], cam["unoccluded"], cam["contrast"]) <= 1
        both = min(f["visibility"]["left"]["visible"], f["visibility"]["right"]["visible"]) >= 0.5
        assert f["visible_both"] is both
    by_id = {f["id"]: f for f in truth["features"]}
    # The deviated hole: both rims 0.04 mm larger in radius; the moved one: both rims moved.
    for fid in ("circle-3", "circle-4"):
        assert by_id[fid]["deviated"]
        # Less the drawn polygon's shortfall (drawn_radius): 2.1e-6 r at the render's 1257 vertices a turn.
        assert by_id[fid]["rendered"]["radius"] == pytest.approx(by_id[fid]["nominal"]["radius"] + 0.04, abs=2e-5)
    for fid in ("circle-7", "circle-8"):
        assert by_id[fid]["deviated"]
        np.testing.assert_allclose(
            np.subtract(by_id[fid]["rendered"]["center"], by_id[fid]["nominal"]["center"]), [0.05, -0.03, 0], atol=1e-9
        )
    assert sum(f["deviated"] for f in truth["features"]) == 4


def test_visibility_of_the_default_view(folder_run):
    _, truth, _ = folder_run[0]
    by_id = {f["id"]: f for f in truth["features"]}
    # Top rims of all five holes (z = 10, or 6 in the milled-down region) show in both images.
    tops = [f for f in truth["features"] if f["kind"] == "circle" and f["nominal"]["center"][2] > 0]
    bottoms = [f for f in truth["features"] if f["kind"] == "circle" and f["nominal"]["center"][2] == 0]
    assert len(tops) == 5 and len(bottoms) == 5
    assert all(f["visible_both"] for f in tops)
    assert not any(f["visible_both"] for f in bottoms)  # seen only partly, through the holes
    # Edges of the bottom face at the back are hidden; the top face's front edges are not.
    lines = [f for f in truth["features"] if f["kind"] == "line"]
    hidden = [f for f in lines if f["nominal"]["start"][2] == 0 and f["nominal"]["end"][2] == 0
              and min(f["nominal"]["start"][1], f["nominal"]["end"][1]) == 60]
    assert hidden and all(f["visibility"]["left"]["unoccluded"] == 0 for f in hidden)
    assert sum(f["visible_both"] for f in lines) >= 10
    assert by_id  # ids are unique
    assert len(by_id) == len(truth["features"])


def test_analytic_deviated_geometry_matches_the_deviated_model(plate, bracket):
    """The truth's as-rendered geometry is what a re-inventory of the deviated solid finds."""
    from partinspect.cad.deviate import deviate, parse_deviation
    from partinspect.cad.features import inventory

    cases = [
        (plate, ["circle-2.radius=-0.05", "circle-10.x=0.07", "circle-6.center=-0.02,0.03,0"]),
        (bracket, [f"{bracket_wall_hole(bracket)}.diameter=0.1", f"{bracket_wall_hole(bracket)}.z=0.05"]),
    ]
    for part, texts in cases:
        devs = [parse_deviation(t) for t in texts]
        expected = deviated_geometry(part.inv, devs)
        found = inventory(deviate(part.shape, part.inv, devs))
        changed = 0
        for f in part.inv.features:
            e = expected[f.id]
            # Match by geometry, not by id (a changed size may reorder ids).
            candidates = [g for g in found.features if g.kind == f.kind]
            if f.kind == "line":
                g = min(candidates, key=lambda g: np.abs(g.start - e["start"]).sum() + np.abs(g.end - e["end"]).sum())
                np.testing.assert_allclose([g.start, g.end], [e["start"], e["end"]], atol=1e-6)
            else:
                g = min(candidates, key=lambda g: np.abs(g.center - e["center"]).sum() + abs(g.radius - e["radius"]))
                np.testing.assert_allclose(g.center, e["center"], atol=1e-6)
                assert g.radius == pytest.approx(e["radius"], abs=1e-6)
                changed += not np.allclose(e["center"], f.center) or e["radius"] != f.radius
        assert changed == 2 * len({t.split(".")[0] for t in texts})  # both rims of each hole


def bracket_wall_hole(bracket):
    """Id of the bracket's 10 mm wall hole rim on the wall's front face (y = 38)."""
    for f in bracket.inv.of_kind("circle"):
        if abs(f.radius - 5.0) < 1e-9 and abs(f.center[1] - 38.0) < 1e-9:
            return f.id
    raise AssertionError("no 10 mm wall hole")


def test_a_hole_turned_away_is_not_visible(bracket):
    """Wall-hole rims on the wall's front face show in the default view; seen from behind they do not."""
    from partinspect.poses import default_pose, parse_pose
    from partinspect.simulate.rig import default_rig

    rig = default_rig(SMALL)
    front = bracket.inv[bracket_wall_hole(bracket)]
    back = next(f for f in bracket.inv.of_kind("circle") if f is not front and abs(f.radius - 5.0) < 1e-9
                and abs(f.center[1] - 50.0) < 1e-9)
    views = {"default": default_pose(bracket.shape, rig), "from behind": parse_pose("-135,0,160", bracket.shape, rig)}
    seen = {}
    for view, P in views.items():
        for f in (front, back):
            seen[view, f.id] = feature_visibility(bracket.scene, rig, P, f.kind, feature_geometry(f))
    assert seen["default", front.id]["visible_both"]
    assert not seen["default", back.id]["visible_both"]
    assert not seen["from behind", front.id]["visible_both"]
    assert seen["from behind", front.id]["left"]["unoccluded"] < 0.2
    assert seen["from behind", back.id]["visible_both"]


def test_sample_edge():
    g = {"center": np.array([1.0, 2.0, 3.0]), "normal": np.array([0.0, 0.0, 1.0]), "radius": 2.0,
         "angle_start": 0.5, "angle_end": 2.0}
    pts, tan = sample_edge("arc", g, n=50)
    r = pts - g["center"]
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 2.0)
    np.testing.assert_allclose(r[:, 2], 0, atol=1e-12)
    angle = np.arctan2(r[:, 1], r[:, 0])
    assert angle.min() > 0.5 and angle.max() < 2.0  # strictly inside: no corners
    np.testing.assert_allclose(np.einsum("ij,ij->i", tan, r), 0, atol=1e-12)
    pts, tan = sample_edge("line", {"start": np.zeros(3), "end": np.array([10.0, 0, 0])})
    assert len(pts) == 40 and pts[:, 0].min() > 0 and pts[:, 0].max() < 10
    np.testing.assert_allclose(tan, [[1, 0, 0]] * 40)


def test_to_json_rounds_and_is_deterministic():
    t = {"a": np.array([1 / 3, -0.0, 2e-12]), "b": np.float64(-1e-13), "c": [True, np.int64(3)]}
    text = to_json(t)
    assert text == to_json(t)
    data = json.loads(text)
    assert data == {"a": [0.333333333, 0.0, 0.0], "b": 0.0, "c": [True, 3]}
    assert "-0.0" not in text


def test_edge_far_outside_the_image_is_not_visible_even_where_the_lens_model_folds():
    """An edge running out past the fold of a strong distortion model: not in the image, no error.

    The default rig's radial distortion folds back beyond about 0.8 of the
    focal length off axis (a render of a large NIST part failed there).
    """
    from partinspect.cad.raycast import camera_in_part
    from partinspect.cad.sightlines import edge_visibility
    from tests.simulate.scenes import Part

    p = Part("plate")
    rig = p.rig(distortion=True, size=SMALL)
    pose = p.pose(rig)
    # Along a ray direction from 0.3 to 1.1 focal lengths off axis, 400 mm away, in the part frame.
    r = np.linspace(0.3, 1.1, 400)
    cam = np.stack([0.8 * r * 400.0, -0.6 * r * 400.0, np.full_like(r, 400.0)], axis=1)
    K, D, R, t = camera_in_part(rig, 0, pose)
    pts = (cam - t) @ R
    tang = np.tile((np.array([0.8, -0.6, 0.0]) @ R), (len(r), 1))
    v = edge_visibility(p.scene, rig, 0, pose, pts, tang)
    assert not v["in_image"].any() and not v["contrast"].any()


def test_a_face_boundary_shaded_alike_beside_an_edge_does_not_hide_it(bracket):
    """The bracket's slot end (arc-2) seen in the left camera: 1.5 px inside
    its rim the slot's wall gives way to the face seen past it, shaded alike
    (1-2 grey levels against the rim's 50). That boundary is no second edge
    (the 2D chain finds the rim there), so the rim keeps its contrast; where
    the background shows 0.25 px inside the rim (a step of 140 grey
    levels) it does not. The rule without the shading (any change of face)
    lost single samples there, and with the trim at each end of a visible
    stretch the planner lost 20 deg of the arc at each."""
    from partinspect.poses import default_pose
    from partinspect.simulate.rig import default_rig
    from partinspect.cad.sightlines import edge_visibility

    rig = default_rig((1224, 1024))
    pose = default_pose(bracket.shape, rig)
    arc = bracket.inv["arc-2"]
    g = feature_geometry(arc)
    assert arc.kind == "arc" and abs(g["radius"] - 4.0) < 1e-9
    n = 720
    P, T = sample_edge("arc", g, n)
    t = np.rad2deg(g["angle_start"] + (np.arange(n) + 0.5) / n * (g["angle_end"] - g["angle_start"]))
    vis = edge_visibility(bracket.scene, rig, 0, pose, P, T)
    alike = (t > 140) & (t < 170)
    assert vis["contrast"][alike].all()
    assert not vis["contrast"][(t > 192) & (t < 196)].all()


@pytest.mark.parametrize("sides", [12, 180, 1257])
def test_a_polygons_drawn_radius_is_its_mean_distance_from_the_centre(sides):
    # A polygon inscribed in a 40 mm circle, tilted, its sides unequal (so that which sides count
    # matters), as a mesh's vertices (with others off the circle).
    r, centre, normal = 40.0, np.array([3.0, -2.0, 7.0]), np.array([0.2, -0.3, 0.93])
    normal /= np.linalg.norm(normal)
    x = np.cross(normal, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(normal, x)
    jitter = np.random.default_rng(sides).uniform(-0.4, 0.4, sides)
    t = (np.arange(sides) + jitter) * 2.0 * np.pi / sides + 0.1
    ring = centre + r * (np.cos(t)[:, None] * x + np.sin(t)[:, None] * y)
    other = centre + np.array([[0.0, 0.0, 5.0], [10.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    drawn = drawn_radius(np.vstack([ring, other]), {"center": centre, "normal": normal, "radius": r})
    # The polygon's mean distance from the centre along its sides (each side weighted by its length,
    # as evenly spaced edge points weight it), by brute force.
    s = (np.arange(20000) + 0.5) / 20000

    def mean_distance(a, b):
        per_side = np.linalg.norm(a[:, None] + s[None, :, None] * (b - a)[:, None] - centre, axis=2).mean(axis=1)
        return np.average(per_side, weights=np.linalg.norm(b - a, axis=1))

    assert drawn == pytest.approx(mean_distance(ring, np.roll(ring, -1, axis=0)), rel=1e-9)
    assert drawn < r
    # An arc: only its own sides count (the ring's vertices within it, consecutive), not the chord
    # across its gap nor the sides outside it.
    arc = {"center": centre, "normal": normal, "radius": r, "angle_start": 0.0, "angle_end": np.pi}
    fx, fy, _ = orthonormal_frame(normal)  # the frame the arc's angles are measured in
    angle = np.arctan2((ring - centre) @ fy, (ring - centre) @ fx) % (2 * np.pi)
    inside = np.flatnonzero(angle <= np.pi)
    inside = inside[np.argsort(angle[inside])]
    own = mean_distance(ring[inside[:-1]], ring[inside[1:]])
    assert drawn_radius(np.vstack([ring, other]), arc) == pytest.approx(own, rel=1e-9)
