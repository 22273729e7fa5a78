"""Several views of one part: --views rendering, the views folder as input, fusion end to end."""

import json
import os

import numpy as np
import pytest

from partinspect.errors import InputError
from partinspect.poses import parse_views, turned_pose

SIZE = (612, 512)
VIEWS = "0,0,0;0,0,180"


@pytest.fixture(scope="session")
def plate_views(tmp_path_factory, repo):
    """The sample plate rendered small in two turntable views (0 and 180 degrees)."""
    from partinspect.simulate.folder import render_views_to_folder

    out = tmp_path_factory.mktemp("views")
    truths = render_views_to_folder(repo / "examples/plate/part.step", out, VIEWS, image_size=SIZE, noise=1.0)
    return out, truths


def test_parse_views_reads_each_turn_and_names_a_bad_one():
    views = parse_views("0,0,0; 0,0,120 ;0,0,240")
    assert [v.tolist() for v in views] == [[0, 0, 0], [0, 0, 120], [0, 0, 240]]
    with pytest.raises(InputError, match="view 2 must be RX,RY,RZ"):
        parse_views("0,0,0;0,120")
    with pytest.raises(InputError, match="expected RX,RY,RZ"):
        parse_views(" ; ")


def test_turned_pose_turns_the_part_about_its_centre():
    base = np.eye(4)
    base[:3, 3] = [1.0, 2.0, 300.0]
    bounds = np.array([[0.0, 0.0, 0.0], [80.0, 60.0, 10.0]])
    P = turned_pose(base, [0, 0, 90], bounds)
    centre = np.array([40.0, 30.0, 5.0, 1.0])
    np.testing.assert_allclose(P @ centre, base @ centre)  # the centre stays put
    # +X of the part turns to +Y (a right-handed turn about Z)
    np.testing.assert_allclose(P[:3, :3] @ [1.0, 0, 0], base[:3, :3] @ [0, 1.0, 0], atol=1e-12)
    np.testing.assert_allclose(turned_pose(base, [0, 0, 0], bounds), base)


def test_render_views_writes_one_images_folder_per_view(plate_views):
    out, truths = plate_views
    assert sorted(p.name for p in out.iterdir()) == ["view-1", "view-2"]
    for k in (1, 2):
        names = sorted(p.name for p in (out / f"view-{k}").iterdir())
        assert names == ["calibration.yaml", "left.png", "right.png", "truth.json"]
    poses = [np.array(json.loads((out / f"view-{k}/truth.json").read_text())["part_to_camera"]) for k in (1, 2)]
    # the same rig, the part turned by 180 degrees about its Z: the rotations differ by that turn
    turn = poses[0][:3, :3].T @ poses[1][:3, :3]
    np.testing.assert_allclose(turn, np.diag([-1.0, -1.0, 1.0]), atol=1e-9)
    assert truths[0]["seed"] != truths[1]["seed"]


def test_each_view_alone_inspects_as_a_pair(plate_views, repo, tmp_path):
    from partinspect.pipeline import run_inspection

    out, _ = plate_views
    result = run_inspection(repo / "examples/plate/part.step", out / "view-2", tmp_path / "o")
    assert result.report["summary"]["features_measured"] >= 12
    assert "views" not in result.report


@pytest.fixture(scope="session")
def plate_views_report(plate_views, repo, tmp_path_factory):
    from partinspect.multiview import run_views

    out, _ = plate_views
    return run_views(repo / "examples/plate/part.step", out, tmp_path_factory.mktemp("views-out"))


def test_a_views_folder_is_one_inspection_with_fused_features(plate_views_report, plate_views):
    import jsonschema
    from importlib import resources

    report = plate_views_report.report
    views = report["views"]
    assert [v["name"] for v in views] == ["view-1", "view-2"] and all(v["used"] for v in views)
    per_view = [v["features_measured"] for v in views]
    measured = {f["id"] for f in report["features"] if f["measured"] is not None}
    # the turned view sees edges the first does not: more features measured than in either alone
    assert len(measured) > max(per_view)
    assert measured == set(views[0]["features"]) | set(views[1]["features"])
    both = set(views[0]["features"]) & set(views[1]["features"])
    assert both, "the two views share features (the top face's holes)"
    by_id = {c["id"]: c for c in report["characteristics"]}
    for c in report["characteristics"]:
        assert set(c["views"]) <= {"view-1", "view-2"}
        assert (c["measured"] is None) == (not c["views"])
    # a hole on the top face is seen in both views: its diameter is combined, with a u below each view's
    d = by_id["circle-4.diameter"]
    if "circle-4" not in {f["feature"] for f in report["fusion"]["left_out"]}:
        assert d["views"] == ["view-1", "view-2"] and "combined over 2 views" in d["method"]
    # no characteristic of an edge that some view measured is "not inspected"
    for c in report["not_inspected"]:
        assert not set(c["features"]) & measured
    schema = json.loads(resources.files("partinspect.reports").joinpath("schemas/report-1.schema.json").read_text())
    jsonschema.validate(report, schema)
    # the stages are added up over the views
    if "SOURCE_DATE_EPOCH" not in os.environ:
        stages = {s["stage"] for s in report["timings"]["stages"]}
        assert {"loading the CAD model", "measuring the images", "evaluating", "report"} <= stages
    html = (plate_views_report.out_dir / "report.html").read_text()
    assert 'id="views"' in html and "view-2" in html
    # the view strip: each view's image with the curves it measured, named by their CAD ids
    strip = html[html.index('id="fig-views"'):html.index('id="fig-images"')]
    assert strip.count('class="photo-panel"') == 2 and "view-1 · left image" in strip and "view-2 · left image" in strip
    for v in views:
        shown = [f for f in v["features"] if f"<title>{f} (" in strip]
        assert len(shown) >= v["features_measured"] - 1, (v["name"], shown)


def test_shared_calibration_at_the_top_of_the_views_folder(plate_views, repo, tmp_path):
    import shutil

    from partinspect.multiview import is_views_folder
    from partinspect.pipeline import load_inputs

    out, _ = plate_views
    views = tmp_path / "views"
    for k in (1, 2):
        (views / f"view-{k}").mkdir(parents=True)
        for name in ("left.png", "right.png"):
            shutil.copy(out / f"view-{k}" / name, views / f"view-{k}" / name)
    shutil.copy(out / "view-1/calibration.yaml", views / "calibration.yaml")
    assert is_views_folder(views) and not is_views_folder(views / "view-1")
    inputs = load_inputs(repo / "examples/plate/part.step", views / "view-2", tmp_path / "o", None, None,
                         lambda m: None, calibration_dir=views)
    assert inputs.calib_file == views / "calibration.yaml"
    with pytest.raises(InputError, match="no calibration.yaml"):
        load_inputs(repo / "examples/plate/part.step", views / "view-2", tmp_path / "o", None, None, lambda m: None)


def test_a_view_that_cannot_be_measured_is_left_out_with_its_reason(plate_views, repo, tmp_path):
    import shutil

    import cv2

    from partinspect.multiview import run_views

    out, _ = plate_views
    views = tmp_path / "views"
    shutil.copytree(out / "view-1", views / "view-1")
    (views / "view-2").mkdir()
    shutil.copy(out / "view-1/calibration.yaml", views / "view-2")
    rng = np.random.default_rng(0)
    for name in ("left.png", "right.png"):  # a pair without the part in it
        cv2.imwrite(str(views / "view-2" / name), np.clip(40 + 2 * rng.standard_normal(SIZE[::-1]), 0, 255).astype(np.uint8))
    result = run_views(repo / "examples/plate/part.step", views, tmp_path / "o")
    entries = {v["name"]: v for v in result.report["views"]}
    assert entries["view-1"]["used"] and not entries["view-2"]["used"]
    assert "cannot align" in entries["view-2"]["reason"]
    assert "1 of 2 views fused (view-2 left out" in result.summary_line()
    assert all(c["views"] in ([], ["view-1"]) for c in result.report["characteristics"])


def test_a_view_missing_an_image_or_a_pose_hint_is_refused_by_name(plate_views, repo, tmp_path):
    import shutil

    from partinspect.multiview import run_views

    out, _ = plate_views
    views = tmp_path / "views"
    shutil.copytree(out / "view-1", views / "view-1")
    shutil.copytree(out / "view-2", views / "view-2")
    with pytest.raises(InputError, match="pose-hint"):
        run_views(repo / "examples/plate/part.step", views, tmp_path / "o", pose_hint="0,0,0,0,0,300")
    (views / "view-2" / "right.png").unlink()
    with pytest.raises(InputError) as e:
        run_views(repo / "examples/plate/part.step", views, tmp_path / "o")
    assert "view-2" in str(e.value) and "right.png" in str(e.value)
    assert not (tmp_path / "o" / "report.json").exists()


@pytest.fixture(scope="session")
def plate_three_views(tmp_path_factory, repo):
    """The plate in three turntable views; a copy whose view-3 camera was turned 0.05 deg after calibrating."""
    import shutil

    import cv2

    from partinspect.simulate.folder import render_views_to_folder

    out = tmp_path_factory.mktemp("three-views")
    render_views_to_folder(repo / "examples/plate/part.step", out, parse_views("0,0,0;0,0,120;0,0,240"),
                           image_size=SIZE, noise=1.0)
    bumped = tmp_path_factory.mktemp("bumped") / "views"
    shutil.copytree(out, bumped)
    path = str(bumped / "view-3" / "calibration.yaml")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    values = {n: fs.getNode(n).mat() for n in ("K1", "D1", "K2", "D2", "R", "T")}
    size = [int(fs.getNode(n).real()) for n in ("image_width", "image_height")]
    fs.release()
    a = np.radians(0.05)  # about the vertical axis: every disparity off by ~1.6 px, the epipolar lines kept
    values["R"] = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]) @ values["R"]
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", size[0])
    fs.write("image_height", size[1])
    for name, value in values.items():
        fs.write(name, value)
    fs.release()
    return out, bumped


def test_a_bumped_view_is_left_out_whole_and_good_views_are_kept(plate_three_views, repo, tmp_path):
    from partinspect.multiview import run_views

    good, bumped = plate_three_views
    report = run_views(repo / "examples/plate/part.step", good, tmp_path / "good").report
    assert all(v["used"] for v in report["views"])
    report = run_views(repo / "examples/plate/part.step", bumped, tmp_path / "bumped").report
    entries = {v["name"]: v for v in report["views"]}
    assert entries["view-1"]["used"] and entries["view-2"]["used"] and not entries["view-3"]["used"]
    assert "a camera moved since calibrating" in entries["view-3"]["reason"]
    # nothing the bumped view measured is passed on
    assert all("view-3" not in c["views"] for c in report["characteristics"])


def test_a_views_folder_in_a_batch_is_one_part(plate_views, repo, tmp_path):
    """inspect batch's worker inspects a views folder as one part, its input hashes over every view's files."""
    from partinspect.digest import sha256_file
    from partinspect.production.manifest import Job
    from partinspect.production.worker import images_digest, inspect_part

    folder, _ = plate_views
    job = Job("V-001", repo / "examples/plate/part.step", folder, None, None, 2, None)
    row = inspect_part(job, tmp_path)
    part = row["part"]
    assert part["status"] == "done" and part["exit_code"] in (0, 1, 3), part["error"]
    report = json.loads((tmp_path / "V-001" / "report.json").read_text())
    assert [v["name"] for v in report["views"]] == ["view-1", "view-2"]
    assert len(row["characteristics"]) == len(report["characteristics"]) > 0
    views = sorted(p for p in folder.iterdir() if p.is_dir())
    lines = [f"{v.name}:{sha256_file(v / 'left.png')}" for v in views]
    import hashlib

    assert part["left_sha256"] == hashlib.sha256("\n".join(lines).encode()).hexdigest()
    assert part["left_sha256"] != images_digest(folder, ("right.png",)) and part["calibration_sha256"] is not None
    # a pair folder's digest is its file's hash
    assert images_digest(views[0], ("left.png",)) == sha256_file(views[0] / "left.png")


@pytest.mark.parametrize("two_cpus", [True, False])
def test_two_views_measured_side_by_side_give_the_same_report(two_cpus, plate_views_report, plate_views, repo,
                                                               tmp_path, monkeypatch):
    """With a CPU idle, two views are measured at once (one in a forked child): the same report as one after the
    other, the child's stages added to the timings."""
    from partinspect.multiview import run_views
    from partinspect.vision import forked

    monkeypatch.setattr(forked, "can_fork", lambda: two_cpus)
    monkeypatch.setattr(forked, "idle_cpus", lambda: 2.0 if two_cpus else 0.0)
    out, _ = plate_views
    result = run_views(repo / "examples/plate/part.step", out, tmp_path / "o")

    def numbers(report):
        return [(c["id"], c["measured"], c["standard_uncertainty"], c["decision"]) for c in report["characteristics"]]

    assert numbers(result.report) == numbers(plate_views_report.report)
    assert result.report["fusion"] == plate_views_report.report["fusion"]
    if "SOURCE_DATE_EPOCH" not in os.environ:
        stages = {s["stage"]: s["seconds"] for s in result.report["timings"]["stages"]}
        assert stages["registering"] > 0 and stages["measuring the images"] > 0
