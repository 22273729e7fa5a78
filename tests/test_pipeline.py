"""A whole `inspect` run on the bundled sample parts."""

import hashlib
import json
import shutil
from importlib import resources

import cv2
import jsonschema
import numpy as np
import pytest

from partinspect.cli import main

SCHEMA = json.loads(resources.files("partinspect.reports").joinpath("schemas/report-1.schema.json").read_text())


def digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def plate(repo):
    part = repo / "examples" / "plate" / "part.step"
    if not (part.parent / "images" / "left.png").exists():
        pytest.fail("examples/plate/images is missing: render it with inspect render (see README)")
    return part


@pytest.fixture
def workdir(tmp_path, plate):
    # A copy under a path with a space and non-ASCII letters, as users have.
    d = tmp_path / "Prüfung 1"
    shutil.copytree(plate.parent, d / "plate", ignore=shutil.ignore_patterns("truth.json", "make_part.py"))
    return d / "plate"


def test_nominal_plate_passes_or_is_inconclusive_and_says_why(workdir, tmp_path, monkeypatch, capsys, plate):
    """Issue 5's acceptance: the sample rendered at nominal geometry never fails."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    before = digest(workdir)
    out = tmp_path / "out dir"
    code = main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(out), "-q"])
    report = json.loads((out / "report.json").read_text())
    assert code == {"pass": 0, "inconclusive": 3}[report["verdict"]], capsys.readouterr().err
    assert digest(workdir) == before  # inputs never written
    jsonschema.validate(report, SCHEMA)
    truth = json.loads((plate.parent / "truth.json").read_text())

    # The pose found without a hint is the rendered one.
    T, T_true = np.array(report["registration"]["part_to_camera"]), np.array(truth["part_to_camera"])
    assert np.allclose(T[:3, :3], T_true[:3, :3], atol=1e-4) and np.allclose(T[:3, 3], T_true[:3, 3], atol=0.02)
    assert 0 < report["registration"]["rms"] < 0.02

    # Every edge both cameras see is measured; every other says why not.
    seen = {f["id"] for f in truth["features"] if f["visible_both"]}
    by_id = {f["id"]: f for f in report["features"]}
    assert seen and all(by_id[i]["measured"] is not None for i in seen)
    for f in report["features"]:
        if f["measured"] is None:
            assert f["status"] == "not measured" and f["reason"]
        else:
            assert f["status"] in ("pass", "inconclusive", "measured")
            assert np.all(np.linalg.eigvalsh(np.array(f["measured"]["covariance"])) > 0)
            assert "edge_break" not in f  # no break stated

    # Nothing fails; an inconclusive one straddles a limit with its U, or was not measured.
    decisions = {c["decision"] for c in report["characteristics"]}
    assert decisions <= {"pass", "inconclusive"} and "pass" in decisions
    for c in report["characteristics"]:
        if c["decision"] == "inconclusive" and c["measured"] is not None:
            lo, up, y, U = c["lower_limit"], c["upper_limit"], c["measured"], c["expanded_uncertainty"]
            assert (up is not None and y + U > up) or (lo is not None and y - U < lo), c
        assert c["reason"]
    # Clean data: the first round meets no situation, nothing is re-run, no advice.
    assert len(report["adaptive"]["rounds"]) == 1 and report["adaptive"]["advice"] == []
    # General tolerances of edges out of view are listed, not judged.
    assert report["not_inspected"] and all(c["reason"] for c in report["not_inspected"])
    assert not {c["feature"] for c in report["not_inspected"]} & seen

    assert {i["role"] for i in report["inputs"]} >= {"part", "left image", "right image", "calibration"}
    html = (out / "report.html").read_text()
    assert report["verdict"] in html and "Prüfung 1" in html
    first = digest(out)
    # Same inputs, same outputs, byte for byte; a second run replaces the first cleanly.
    assert main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(out), "-q"]) == code
    assert digest(out) == first
    assert sorted(p.name for p in out.iterdir()) == ["junit.xml", "report.html", "report.json"]


def test_image_of_wrong_size_is_refused_before_anything_is_written(workdir, tmp_path, capsys):
    right = workdir / "images" / "right.png"
    img = cv2.imread(str(right), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(right), img[:-8])
    out = tmp_path / "out"
    code = main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f"inspect: error: {right}: image is ") and err.count("\n") == 1
    assert not out.exists()


def test_black_image_is_refused(workdir, tmp_path, capsys):
    left = workdir / "images" / "left.png"
    img = cv2.imread(str(left), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(left), np.zeros_like(img))
    code = main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(tmp_path / "o"), "-q"])
    assert code == 2
    assert "all black" in capsys.readouterr().err


@pytest.fixture(scope="module")
def deviated(repo, tmp_path_factory):
    """The plate made 0.1 mm oversize at circle-4 and with circle-2 moved, rendered at half size."""
    step = repo / "examples" / "plate" / "part.step"
    render = tmp_path_factory.mktemp("deviated") / "render"
    assert main(["render", str(step), str(render), "--size", "1224x1024", "--seed", "3", "-q",
                 "--deviate", "circle-4.diameter=0.1", "--deviate", "circle-2.center=0.08,0,0"]) == 0
    return step, render


def test_deviated_hole_fails_and_nothing_else_does(deviated, tmp_path, capsys):
    """circle-4 (limits 0 / +0.05) made 0.1 mm oversize fails on that characteristic alone."""
    step, render = deviated
    out = tmp_path / "inspection"
    code = main([str(step), str(render / "images"), "-o", str(out), "-q"])
    assert code == 1, capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    failed = [c["id"] for c in report["characteristics"] if c["decision"] == "fail"]
    assert failed == ["circle-4.diameter"]
    c = next(c for c in report["characteristics"] if c["id"] == "circle-4.diameter")
    assert abs(c["measured"] - 12.1) < 0.03 and c["measured"] - c["expanded_uncertainty"] > c["upper_limit"]
    for c in report["characteristics"]:
        if c["measured"] is None:
            assert c["reason"].startswith("not measured: ") and len(c["reason"]) > len("not measured: ")
    junit = (out / "junit.xml").read_text()
    assert "circle-4.diameter" in junit and "<failure" in junit


def test_monte_carlo_uncertainty_agrees_with_first_order(deviated, tmp_path):
    from partinspect.pipeline import run_inspection

    step, render = deviated
    mc = run_inspection(step, render / "images", tmp_path / "mc", uncertainty="montecarlo", draws=40).report
    fo = run_inspection(step, render / "images", tmp_path / "fo").report
    assert mc["uncertainty"]["method"].startswith("Monte Carlo") and mc["uncertainty"]["draws"] == 40
    assert fo["uncertainty"]["method"].startswith("first-order")
    # 40 draws estimate a standard deviation to about +-11 %: the median ratio is far tighter.
    assert 0.85 < mc["uncertainty"]["std_ratio_median"] < 1.15
    u_fo = {c["id"]: c["standard_uncertainty"] for c in fo["characteristics"] if c["type"] == "diameter" and c["measured"]}
    u_mc = {c["id"]: c["standard_uncertainty"] for c in mc["characteristics"] if c["id"] in u_fo}
    assert u_fo and all(0.6 < u_mc[k] / u_fo[k] < 1.5 for k in u_fo), (u_fo, u_mc)


def test_pose_hint_gives_the_searched_pose_and_a_wrong_hint_is_refused(deviated, tmp_path, capsys):
    step, render = deviated
    truth = render / "truth.json"
    out = tmp_path / "hinted"
    assert main([str(step), str(render / "images"), "-o", str(out), "-q", "--pose-hint", str(truth)]) == 1
    T = np.array(json.loads((out / "report.json").read_text())["registration"]["part_to_camera"])
    T_true = np.array(json.loads(truth.read_text())["part_to_camera"])
    assert np.allclose(T[:3, :3], T_true[:3, :3], atol=2e-4) and np.allclose(T[:3, 3], T_true[:3, 3], atol=0.05)
    # A hint 5 mm off matches nothing: the run says so rather than measuring against a wrong pose.
    wrong = tmp_path / "wrong.json"
    T_true[:3, 3] += [5.0, 0.0, 0.0]
    wrong.write_text(json.dumps({"part_to_camera": T_true.tolist()}))
    capsys.readouterr()
    code = main([str(step), str(render / "images"), "-o", str(tmp_path / "w"), "-q", "--pose-hint", str(wrong)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "align" in err, err
    assert not (tmp_path / "w").exists()


def test_a_feature_merged_from_another_adaptive_round_keeps_its_own_edge_data():
    """A re-run's feature joins the first round's result (adaptive processing) with its own edge
    normals and filter scale, so its Monte Carlo draws the noise it was measured with."""
    from types import SimpleNamespace

    from partinspect.vision.posed import merged_stereo
    from partinspect.vision.montecarlo import monte_carlo
    from partinspect.vision.stereo import measure_stereo
    from tests.vision import stereo_scenes as S
    from tests.vision.test_montecarlo import _ratio

    rig, _, L, R = S.render("plate", 2.0, 0)
    base, new = measure_stereo(L, R, rig), measure_stereo(L, R, rig, sigma=1.5)
    circles = [f for f in new.features if f.kind != "line"]
    i = max(range(len(circles)), key=lambda k: len(circles[k].correspondences))
    reg = SimpleNamespace(assignment={"circle": {i: "circle-x"}, "line": {}}, measured_feature=lambda kind, k: circles[k])
    merged = merged_stereo(base, new, reg, {"circle-x"})

    assert len(merged.features) == len(base.features) + 1 and merged.features[:-1] == base.features
    f = merged.features[-1]
    fl, fr = merged.left.features[f.left], merged.right.features[f.right]
    assert fl is new.left.features[circles[i].left] and fr is new.right.features[circles[i].right]
    assert fl.corr_length == 1.5 and base.left.features[0].corr_length == 1.0
    assert merged.left.edges is base.left.edges  # the base round's edges, indexed by its own features only
    (m,) = monte_carlo(merged, rig, [len(merged.features) - 1], draws=150, seed=1, calibration=False)
    ratio = _ratio(m, merged)[[0, 1, 2, 6]]
    assert np.all(np.abs(ratio - 1) < 0.15), ratio


def test_an_edge_found_only_inside_a_longer_collinear_one_says_so():
    """Two collinear CAD edges (a step's two lips in line) merge into one line in the images; the one
    not measured is not reported as 'no edge found' but as part of the longer edge, with its fate."""
    from types import SimpleNamespace

    from partinspect.cad.visibility import FeatureVisibility
    from partinspect.diagnosis import unmeasured_reason
    from partinspect.simulate.rig import default_rig
    from partinspect.vision.calibration import project_points

    rig = default_rig((1224, 1024))
    pose = np.eye(4)
    edge = SimpleNamespace(kind="line", id="line-9", start=(-10.0, 5.0, 400.0), end=(0.0, 5.0, 400.0))
    longer = np.c_[np.linspace(-10.0, 25.0, 300), np.full(300, 5.0), np.full(300, 400.0)]
    elsewhere = longer + [0.0, 20.0, 0.0]

    def image(points):
        return [SimpleNamespace(uv=project_points(points, K, D, R, T)) for K, D, R, T in
                ((rig.K1, rig.D1, np.eye(3), np.zeros(3)), (rig.K2, rig.D2, rig.R, rig.T))]

    def reason(points, owners, unmatched=None, edge_points=None):
        left, right = image(points)
        el, er = image(points if edge_points is None else edge_points)
        stereo = SimpleNamespace(left=SimpleNamespace(noise=2.0, features=[left], edges=SimpleNamespace(xy=el.uv)),
                                 right=SimpleNamespace(noise=2.0, features=[right], edges=SimpleNamespace(xy=er.uv)))
        vis = FeatureVisibility((1.0, 1.0), (1.0, 1.0), (1.0, 1.0), (60.0, 55.0))
        return unmeasured_reason(edge, vis, rig, pose, stereo, unmatched or {}, owners)

    owned = {("left", 0): "line-7", ("right", 0): "line-7"}
    assert reason(longer, owned) == ("left image: found as part of a longer edge that runs on past it, measured as line-7; "
                                     "right image: found as part of a longer edge that runs on past it, measured as line-7")
    assert "not matched: two or more partners" in reason(longer, {}, {("left", 0): "two or more partners fit"})
    assert reason(elsewhere, owned) == "no edge found along it in the left image; no edge found along it in the right image"
    # Edge points along it that no line or arc took (a short edge between two corners loses its ends to them).
    along = np.c_[np.linspace(-9.0, -1.0, 40), np.full(40, 5.0), np.full(40, 400.0)]
    assert reason(elsewhere, owned, edge_points=np.vstack([elsewhere, along])).startswith(
        "left image: edge points found along it, but too few of them clear of the edges meeting it at its ends")
    # Its own stretch found in both images but not measured: that is what it says, rather
    # than "found as part of a longer edge"; a reason of its own image features comes first.
    vis = FeatureVisibility((1.0, 1.0), (1.0, 1.0), (1.0, 1.0), (60.0, 55.0))

    def with_stretch(points, unmatched):
        left, right = image(points)
        stereo = SimpleNamespace(left=SimpleNamespace(noise=2.0, features=[left]),
                                 right=SimpleNamespace(noise=2.0, features=[right]),
                                 guided_failed=(("line-3", "x"), ("line-9", "its stretch runs 2.0 deg from ...")))
        return unmeasured_reason(edge, vis, rig, pose, stereo, unmatched, {})

    assert with_stretch(longer, {}) == ("its own stretch of a longer straight edge was found in both images, "
                                        "but not measured: its stretch runs 2.0 deg from ...")
    left, right = image(longer)
    taken = SimpleNamespace(left=SimpleNamespace(noise=2.0, features=[left]), right=SimpleNamespace(noise=2.0, features=[right]),
                            withdrawn=(("line-9", "its points in the left image all lie on the image of line-3"),))
    assert unmeasured_reason(edge, vis, rig, pose, taken, {}, {}) == (
        "measured, then taken out: its points in the left image all lie on the image of line-3")
    own = np.c_[np.linspace(-10.0, 0.0, 100), np.full(100, 5.0), np.full(100, 400.0)]
    assert with_stretch(own, {("left", 0): "line nearly parallel", ("right", 0): "line nearly parallel"}) == (
        "left image: line nearly parallel; right image: line nearly parallel")


@pytest.fixture(scope="module")
def slotted(tmp_path_factory):
    """A block with a slot across its top: each long top edge is two collinear CAD edges, one line in the images."""
    import cadquery as cq

    from partinspect.simulate.folder import render_to_folder

    d = tmp_path_factory.mktemp("slotted")
    block = cq.Workplane("XY").box(70, 40, 12, centered=(True, True, False))
    block = block.cut(cq.Workplane("XY").box(12, 50, 5, centered=(True, True, False)).translate((0, 0, 7)))
    # Two holes of different sizes: the part must not look the same turned about its axis.
    block = block.faces(">Z").workplane().pushPoints([(-22, 8)]).hole(8)
    block = block.faces(">Z").workplane().pushPoints([(22, -6)]).hole(5)
    cq.exporters.export(block, str(d / "part.step"))
    render_to_folder(d / "part.step", d, image_size=(1224, 1024))
    return d


def test_collinear_edges_either_side_of_a_slot_are_each_measured(slotted, tmp_path):
    """The four lips of the slot merge pairwise into two image lines that match no single CAD edge;
    under the registered pose each is measured on its own stretch of them, lies on its nominal
    line and within its ends, and says how it was measured."""
    out = tmp_path / "out"
    code = main([str(slotted / "part.step"), str(slotted / "images"), "-o", str(out), "-q"])
    report = json.loads((out / "report.json").read_text())
    assert code in (0, 3)
    jsonschema.validate(report, SCHEMA)
    truth = json.loads((slotted / "truth.json").read_text())

    def lip(f):
        if f["kind"] != "line":
            return False
        a, b = np.array(f["nominal"]["start"]), np.array(f["nominal"]["end"])
        return a[2] == b[2] == 12 and a[1] == b[1] and abs(a[1]) == 20

    lips = [f for f in report["features"] if lip(f)]
    assert len(lips) == 4
    for f in lips:
        assert f["measured"] is not None and "own stretch of a longer straight edge" in f["reason"], f
        a, b = np.array(f["nominal"]["start"]), np.array(f["nominal"]["end"])
        d = (b - a) / np.linalg.norm(b - a)
        for p in (np.array(f["measured"]["start"]), np.array(f["measured"]["end"])):
            v = p - a
            assert np.linalg.norm(v - (v @ d) * d) < 0.05  # on the nominal line
            assert -0.05 < v @ d < np.linalg.norm(b - a) + 0.05  # not across the slot
    seen = {f["id"] for f in truth["features"] if f["visible_both"]}
    assert all(f["measured"] is not None for f in report["features"] if f["id"] in seen)
    assert not any("runs on past it" in (f.get("reason") or "") for f in report["features"])


def _drifted_copy(workdir, dy):
    """The plate's pair with the stated calibration's right principal point moved by ``dy`` px (the rig drifted)."""
    from dataclasses import replace

    from partinspect.vision.calibration import read_calibration, write_calibration

    calib = read_calibration(workdir / "images")
    K2 = calib.K2.copy()
    K2[1, 2] += dy
    write_calibration(workdir / "images" / "calibration.yaml", replace(calib, K2=K2))
    return workdir


def test_a_drifted_rig_is_found_corrected_and_said(workdir, tmp_path, plate):
    """Half a pixel of drift across the epipolar lines: every circle is still measured (before, the two
    images' arcs were 'not one circle' and all ten were lost), the drift is estimated within 0.02 px,
    and the report says what was corrected."""
    _drifted_copy(workdir, 0.5)
    out = tmp_path / "out"
    code = main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(out), "-q"])
    report = json.loads((out / "report.json").read_text())
    jsonschema.validate(report, SCHEMA)
    check = report["calibration_check"]
    assert check["verdict"] == "drifted" and check["tangencies"] >= 6
    assert abs(check["epipolar_residual_px"] - 0.5) < 0.02
    assert check["correction_deg"] != 0 and check["correction_std_deg"] > 0
    truth = json.loads((plate.parent / "truth.json").read_text())
    seen = {f["id"] for f in truth["features"] if f["visible_both"]}
    by_id = {f["id"]: f for f in report["features"]}
    assert all(by_id[i]["measured"] is not None for i in seen)
    assert code in (0, 3) and "fail" not in {c["decision"] for c in report["characteristics"]}


def test_a_rig_drifted_beyond_correction_is_refused(workdir, tmp_path, capsys):
    _drifted_copy(workdir, 4.0)
    out = tmp_path / "out"
    assert main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "calibration.yaml" in err[0] and "recalibrate" in err[0], err
    assert not out.exists() or not any(out.iterdir())


def test_refine_rig_re_estimates_a_rolled_rig_and_says_so(workdir, tmp_path, capsys):
    """The stated rig rolled by 1 px at the image's sides: with --refine-rig the run measures with the
    rig refined from the registered circles, says so on its summary line and in the report, and the
    rotation it states is the true one within its standard uncertainties."""
    from dataclasses import replace

    from partinspect.vision.calibration import read_calibration, write_calibration

    true = read_calibration(workdir / "images")
    Q = cv2.Rodrigues(np.array([0.0, 0.0, 1.0 / (0.5 * true.image_size[0])]))[0]
    write_calibration(workdir / "images" / "calibration.yaml", replace(true, R=Q @ true.R, T=Q @ np.ravel(true.T)))
    out = tmp_path / "out"
    code = main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(out), "--refine-rig"])
    assert code in (0, 3)
    assert "measured with the rig refined from" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    jsonschema.validate(report, SCHEMA)
    rr = report["rig_refinement"]
    assert rr["refined"] and rr["significant"] and rr["circles"] >= 6
    rows = {p["name"]: p for p in rr["parameters"]}
    true_r = np.degrees(cv2.Rodrigues(true.R)[0].ravel())
    for k, name in enumerate(("rx", "ry", "rz")):
        assert abs(rows[name]["refined"] - true_r[k]) < 3 * rows[name]["standard_uncertainty"], rows[name]
    assert abs(rows["rz"]["significance"]) > 10
    assert rr["baseline_mm"] == pytest.approx(np.linalg.norm(true.T), rel=1e-9)
    budget = report["uncertainty"]["calibration"]
    assert budget["stated"] == "none" and budget["refined_rig"] and not budget["complete"]
    html = (out / "report.html").read_text()
    assert "rig refined from the part (--refine-rig)" in html
    assert "only the refined rig's orientation uncertainty is carried" in html


def test_refine_rig_is_refused_for_a_views_folder(tmp_path, plate, capsys):
    views = tmp_path / "views"
    shutil.copytree(plate.parent / "images", views / "view-1")
    assert main([str(plate), str(views), "-o", str(tmp_path / "out"), "--refine-rig", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--refine-rig" in err[0] and "views folder" in err[0], err


def test_refine_rig_leaves_an_oversize_hole_oversize(deviated, tmp_path):
    """circle-4 made 0.1 mm oversize, the stated rig a board session's rolled by 1 px since: the refined
    run still reads it 12.1 and fails it; the registration told the refinement which circle it is, never
    how large it should be."""
    from dataclasses import replace

    from partinspect.simulate.calibration import drifted_rig, simulated_calibration
    from partinspect.vision.calibration import read_calibration, write_calibration

    step, render = deviated
    images = tmp_path / "images"
    shutil.copytree(render / "images", images)
    board = simulated_calibration(read_calibration(images), np.random.default_rng(3))
    write_calibration(images / "calibration.yaml",
                      replace(drifted_rig(board, "roll", 1.0), std=board.std, cov=board.cov))
    out = tmp_path / "out"
    assert main([str(step), str(images), "-o", str(out), "-q", "--refine-rig"]) == 1
    report = json.loads((out / "report.json").read_text())
    rr = report["rig_refinement"]
    assert rr["refined"] and rr["significant"] and "rz" in {p["name"] for p in rr["parameters"]}
    c = next(c for c in report["characteristics"] if c["id"] == "circle-4.diameter")
    assert c["decision"] == "fail" and abs(c["measured"] - 12.1) < 3 * c["standard_uncertainty"] + 0.005
    assert c["measured"] - 12.0 > 10 * c["standard_uncertainty"]


def test_pmi_datums_that_leave_the_pose_free_fall_back_to_every_feature(monkeypatch):
    # The PMI's datums were not asked for: where their edges, as seen, do
    # not fix the pose, the run aligns on every feature (report.json says
    # so); datums a spec file names still stop the run.
    from types import SimpleNamespace

    from partinspect import pipeline
    from partinspect.cad import registration
    from partinspect.errors import InputError

    calls = []

    def register(circles, lines, inv, datums=None, pose_hint=None):
        calls.append(datums)
        if datums is not None:
            raise registration.RegistrationError("alignment is ambiguous: the datum features give 4 constraints")
        return "every-feature pose"

    monkeypatch.setattr(registration, "register", register)
    stereo = SimpleNamespace(features=[])
    pmi = SimpleNamespace(alignment_datums=("line-1", "line-2"), datum_frame=(("A", ("line-1", "line-2")),))
    inputs = SimpleNamespace(resolved=pmi, inv=None, images="images")
    assert pipeline._register(stereo, inputs) == "every-feature pose"
    assert calls == [("line-1", "line-2"), None]
    spec = SimpleNamespace(alignment_datums=("line-1", "line-2"), datum_frame=())
    with pytest.raises(InputError, match="4 constraints"):
        pipeline._register(stereo, SimpleNamespace(resolved=spec, inv=None, images="images"))


def test_a_stated_edge_break_has_its_band_place_predicted_on_the_rims_seen_from_their_face(workdir, tmp_path):
    from partinspect.pipeline import run_inspection

    spec = tmp_path / "broken.tol.yaml"
    spec.write_text("edge_break: {min: 0.1, max: 0.1}\n")
    report = run_inspection(workdir / "part.step", workdir / "images", tmp_path / "out", tolerances=spec).report
    sizes = {c["feature"]: c.get("details", {}) for c in report["characteristics"]
             if c["type"] == "diameter" and c["measured"] is not None}
    placed = {f: d["edge_break"] for f, d in sizes.items() if "edge_break" in d}
    assert {"circle-2", "circle-4", "circle-8"} <= set(placed)
    moved = {f for f, eb in placed.items() if "points moved" in eb["band_place"]}
    assert len(moved) >= 3  # a rim whose moved points are no longer one circle keeps its fit, corrected by s
    U = {c["feature"]: c["expanded_uncertainty"] for c in report["characteristics"] if c["type"] == "diameter"}
    for f, eb in placed.items():
        assert eb["band_place"].startswith("predicted from the light on the part")
        assert 0.0 <= eb["s"] <= 1.0 and eb["s_standard_uncertainty"] < 1 / np.sqrt(12)
        if f in moved:
            # The break's size is stated exactly and each point carries its place's u, not the whole
            # band's 0.082 mm: the diameter's U is a fraction of the uniform band's 2 x 0.1 / sqrt(3).
            assert eb["standard_uncertainty"] == pytest.approx(0.0, abs=1e-6) and eb["correction"] == 0.0
            assert U[f] < 0.5 * 0.2 / np.sqrt(3)
    assert "circle-3" not in placed  # the bottom rim, seen through its hole: the wall's own silhouette
    stages = {t["stage"] for t in report["timings"]["stages"]}
    assert "edge-break band places" in stages
    assert "edge-break line places" in stages  # the lines' places too (vision.line_band)


@pytest.fixture(scope="module")
def broken_plate(plate, tmp_path_factory):
    """The plate rendered small with every convex edge rounded R 0.1 mm (the STEP file sharp)."""
    out = tmp_path_factory.mktemp("broken") / "render"
    assert main(["render", str(plate), str(out), "--edge-break", "R0.1", "--size", "612x512", "--pose",
                 str(plate.parent / "truth.json"), "-q"]) == 0
    return out


def test_a_broken_render_says_per_feature_where_its_edge_was_taken(broken_plate, plate, tmp_path):
    from partinspect.pipeline import run_inspection

    spec = tmp_path / "broken.tol.yaml"
    spec.write_text("edge_break: {min: 0.1, max: 0.1}\n")
    report = run_inspection(plate, broken_plate / "images", tmp_path / "out", tolerances=spec).report
    jsonschema.validate(report, SCHEMA)
    measured = {f["id"]: f for f in report["features"] if f["measured"] is not None}
    eb = {fid: f["edge_break"] for fid, f in measured.items()}  # every measured feature says
    moved = {fid for fid, e in eb.items() if e["measured_at"] == "predicted band place"}
    rims = moved & {"circle-2", "circle-4", "circle-6", "circle-8", "circle-10"}  # the top rims
    lines = {fid for fid in moved if fid.startswith("line-")}
    assert len(rims) >= 3 and len(lines) >= 5
    sizes = {c["feature"]: c["details"]["edge_break"] for c in report["characteristics"]
             if c["type"] == "diameter" and c["measured"] is not None}
    z = []
    for fid in rims:
        e, m, nominal = eb[fid], measured[fid]["measured"], measured[fid]["nominal"]
        assert 0 < e["band_place"] < 1 and e["offset"] == pytest.approx(e["band_place"] * e["break_size"], abs=1e-5)
        assert e["band_place"] == pytest.approx(sizes[fid]["s"], abs=1e-4)  # the size's place, the same
        assert e["standard_uncertainty"] < 0.5 * e["band_standard_uncertainty"]
        z.append((m["radius"] - nominal["radius"]) / m["radius_std"])
    # Moved onto the sharp rim, the fit measures the wall (the nominal here), not the apparent rim
    # s b outside it (0.025-0.035 mm, 2-4 radius_std).
    assert np.sqrt(np.mean(np.square(z))) < 2.0, z
    for fid in lines:
        e = eb[fid]
        assert 0 < abs(e["offset"]) < e["break_size"] and e["towards_face"].startswith("face-")
        assert e["standard_uncertainty"] < e["band_standard_uncertainty"]
    for fid in set(eb) - moved:
        assert eb[fid]["standard_uncertainty"] == pytest.approx(0.0816497, abs=1e-6) and eb[fid]["reason"]
    # The pose registered on the moved features lies within its stated covariance of the rendered one.
    from partinspect.cad.pose_refine import pose_error

    truth = json.loads((broken_plate / "truth.json").read_text())
    reg = report["registration"]
    xi = pose_error(np.array(reg["part_to_camera"]), np.array(truth["part_to_camera"]))
    assert xi @ np.linalg.solve(np.array(reg["pose_covariance"]), xi) < 22.46  # chi-square on 6, chance 1e-3
    html = (tmp_path / "out" / "report.html").read_text()
    assert html.count('class="sub small edge-break"') == len(measured)
    assert html.count("moved onto the sharp edge by its predicted band place") == len(moved)
