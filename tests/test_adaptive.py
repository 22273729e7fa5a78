"""The situation graph: which situations hold, which actions follow, which round is kept."""

from types import SimpleNamespace

import numpy as np
import pytest

from partinspect.adaptive import DEFAULTS, SITUATIONS, measure_adaptively, measured_ids, met_situations, state_of
from partinspect.cad.visibility import FeatureVisibility
from partinspect.errors import InputError


def _side(noise=2.0, strength=200.0, noise_ratio=1.0):
    edges = SimpleNamespace(strength=np.full(50, strength), sigma=1.0)
    fit = SimpleNamespace(consistency=SimpleNamespace(noise_ratio=noise_ratio))
    return SimpleNamespace(noise=noise, edges=edges, features=[SimpleNamespace(fit=fit)] * 3)


def _stereo(**kw):
    return SimpleNamespace(left=_side(**kw), right=_side(**kw))


SEEN = FeatureVisibility((1.0, 1.0), (1.0, 1.0), (1.0, 1.0), (60.0, 55.0))
FLAT = FeatureVisibility((1.0, 1.0), (1.0, 1.0), (1.0, 1.0), (3.0, 2.0))  # in view, no grey step
HIDDEN = FeatureVisibility((1.0, 1.0), (0.0, 0.0), (0.0, 0.0), (float("nan"),) * 2)


def _registration(ids, wrms=1.0, dof=60):
    return SimpleNamespace(assignment={"circle": {}, "line": dict(enumerate(ids))}, weighted_rms=wrms, dof=dof)


def test_missing_counts_only_edges_in_view_with_a_grey_step():
    vis = {"line-1": SEEN, "line-2": SEEN, "line-3": FLAT, "line-4": HIDDEN}
    s = state_of(DEFAULTS, _stereo(), _registration(["line-1"]), vis)
    assert s.missing == ("line-2",)
    names = [sit.name for sit, _ in met_situations(s)]
    assert names == ["expected edges missing"]


def test_clean_data_meets_no_situation_and_runs_once():
    calls = []

    def run(params):
        calls.append(dict(params))
        return _stereo(), _registration(["line-1"]), {"line-1": SEEN}

    best, log, advice = measure_adaptively(run)
    assert calls == [DEFAULTS] and len(log) == 1 and advice == []
    assert best.params == DEFAULTS


def test_actions_are_tried_in_order_and_the_better_round_is_kept():
    vis = {"line-1": SEEN, "line-2": SEEN}
    calls = []

    def run(params):
        calls.append(dict(params))
        found = ["line-1", "line-2"] if params["sigma"] > 1.0 else ["line-1"]
        return _stereo(), _registration(found), vis

    best, log, advice = measure_adaptively(run)
    actions = next(s for s in SITUATIONS if s.name == "expected edges missing").actions
    assert calls[1] == {**DEFAULTS, **actions[0]}  # the first action, on the defaults
    assert all(c["sigma"] == 1.0 for c in calls[:-1]) and calls[-1]["sigma"] == 1.5  # sigma last, as listed
    assert best.params["sigma"] == 1.5 and best.state.missing == ()
    assert log[-1]["kept"] and log[-1]["after"]["change"] == {"sigma": 1.5}
    assert advice == []


def test_a_rerun_that_only_fits_the_pose_better_does_not_replace_the_defaults():
    # Both rounds miss line-2; the re-runs' registrations fit better (a different feature left
    # out of the pose fit, say), which says nothing of how well the edges were measured.
    vis = {"line-1": SEEN, "line-2": SEEN}

    def run(params):
        wrms = 1.0 if params == DEFAULTS else 0.8
        return _stereo(), _registration(["line-1"], wrms), vis

    best, log, advice = measure_adaptively(run)
    assert len(log) == 4 and best.params == DEFAULTS
    assert [e["kept"] for e in log] == [True, False, False, False]
    assert [a["situation"] for a in advice] == ["expected edges missing"]


def test_a_rerun_that_mends_a_situation_and_measures_as_much_is_kept():
    vis = {"line-1": SEEN}

    def run(params):
        ratio = 2.0 if params["sigma"] == 1.0 else 1.1
        return _stereo(noise_ratio=ratio), _registration(["line-1"], 1.2 if ratio > 1.5 else 1.3), vis

    best, log, advice = measure_adaptively(run)
    assert best.params["sigma"] == 1.5 and [e["kept"] for e in log] == [True, True]
    assert advice == []


def test_a_rerun_that_mends_one_situation_but_meets_another_is_not_kept():
    vis = {"line-1": SEEN}

    def run(params):
        if params["sigma"] == 1.0:
            return _stereo(noise_ratio=2.0), _registration(["line-1"]), vis
        return _stereo(strength=1.0), _registration(["line-1"]), vis  # mended, but its edges now faint

    best, log, advice = measure_adaptively(run)
    assert best.params == DEFAULTS and [e["kept"] for e in log] == [True, False]


def _trading_rounds():
    """A first round missing line-3; the re-run with lower thresholds finds it but loses line-2."""
    vis = {"line-1": SEEN, "line-2": SEEN, "line-3": SEEN}
    calls = []

    def run(params):
        calls.append(dict(params))
        found = ["line-1", "line-2"] if params == DEFAULTS else ["line-1", "line-3"]
        return _stereo(), _registration(found), vis

    def merge(best, new, ids):
        merged = [fid for fid in ("line-1", "line-2", "line-3") if fid in measured_ids(best.registration) or fid in ids]
        return _stereo(), _registration(merged), vis

    return run, merge, calls


def test_a_rerun_for_missing_edges_adds_what_it_found_to_the_best_round():
    run, merge, calls = _trading_rounds()
    best, log, advice = measure_adaptively(run, merge=merge)
    assert len(calls) == 2  # nothing missing after the merge: no further action
    assert measured_ids(best.registration) == {"line-1", "line-2", "line-3"} and best.state.missing == ()
    assert log[1]["kept"] and log[1]["added"] == ["line-3"] and log[1]["missing"] == []
    assert advice == []


def test_without_a_merge_a_rerun_that_trades_one_edge_for_another_is_not_kept():
    run, _, calls = _trading_rounds()
    best, log, advice = measure_adaptively(run)
    assert best.params == DEFAULTS and not any(e["kept"] for e in log[1:]) and "added" not in log[1]
    assert [a["situation"] for a in advice] == ["expected edges missing"]


def test_a_persisting_situation_gives_its_advice():
    def run(params):
        return _stereo(noise_ratio=2.0), _registration(["line-1"]), {"line-1": SEEN}

    best, log, advice = measure_adaptively(run)
    assert len(log) == 2  # one action for this situation, then nothing left to try
    assert [a["situation"] for a in advice] == ["residuals inconsistent with the noise"]
    assert "focus" in advice[0]["advice"]


@pytest.mark.parametrize("wrms, dof, met", [(10.3, 120, True), (2.2, 60, True), (1.8, 60, False), (2.5, 3, False)])
def test_a_registration_misfit_beyond_chance_and_the_limit_is_reported(wrms, dof, met):
    # Beyond REGISTRATION_RMS_LIMIT and beyond chance (p < 1e-6): 2.5 on 3
    # degrees of freedom is chi-square 19, p = 3e-4, which chance allows.
    calls = []

    def run(params):
        calls.append(dict(params))
        return _stereo(), _registration(["line-1"], wrms, dof), {"line-1": SEEN}

    best, log, advice = measure_adaptively(run)
    names = [a["situation"] for a in advice]
    assert names == (["registration inconsistent"] if met else [])
    assert len(calls) == 1  # no processing change can mend it: advice only
    if met:
        assert f"{wrms:.1f} times" in advice[0]["detail"] and "calibration" in advice[0]["advice"]


def test_no_alignment_in_any_round_raises_the_first_error():
    def run(params):
        e = InputError("images", f"cannot align (sigma {params['sigma']})")
        e.stereo = _stereo()
        raise e

    with pytest.raises(InputError, match="sigma 1"):
        measure_adaptively(run)


# ------------------------------------------------------------ on rendered images


@pytest.fixture(scope="module")
def plate_variants(repo, tmp_path_factory):
    """The plate rendered once without noise at half size; nominal (noise 2), doubled noise
    (4) and half contrast (grey steps halved about the background, noise 2) made from it."""
    import shutil

    import cv2

    from partinspect.cli import main
    from partinspect.cad.raycast import DEFAULT_SHADING

    root = tmp_path_factory.mktemp("adaptive")
    clean = root / "clean"
    step = repo / "examples" / "plate" / "part.step"
    assert main(["render", str(step), str(clean), "--size", "1224x1024", "--noise", "0", "-q"]) == 0
    rng = np.random.default_rng(11)
    bg = DEFAULT_SHADING.background
    out = {}
    for name, contrast, noise in (("nominal", 1.0, 2.0), ("noisy", 1.0, 4.0), ("faint", 0.5, 2.0)):
        d = root / name / "images"
        shutil.copytree(clean / "images", d)
        for side in ("left", "right"):
            img = cv2.imread(str(clean / "images" / f"{side}.png"), cv2.IMREAD_UNCHANGED).astype(float)
            img = bg + contrast * (img - bg) + rng.normal(0.0, noise, img.shape)
            cv2.imwrite(str(d / f"{side}.png"), np.clip(np.rint(img), 0, 255).astype(np.uint8))
        out[name] = d
    return step, out


def _measured(report):
    return {f["id"] for f in report["features"] if f["measured"] is not None}


def _undetectable(step, images_dir, report, noise):
    """CAD edges in view whose grey step in these images is below the chain's detection limit."""
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.cad.visibility import visibility
    from partinspect.vision.calibration import read_calibration
    from partinspect.vision.images import read_pair

    shape = load_step(step)
    calib = read_calibration(images_dir / "calibration.yaml")
    left, right, _ = read_pair(images_dir, calib)
    pose = np.array(report["registration"]["part_to_camera"], float)
    seen = visibility(shape, inventory(shape), calib, pose, images=(left, right))
    return {k for k, v in seen.items() if v.in_view and not v.shows_edge(noise)}


def test_doubled_noise_and_half_contrast_measure_what_the_nominal_render_does(plate_variants, tmp_path):
    """Issue 9's acceptance: degraded images still measure every feature the nominal one does,
    and the report lists the rounds, with the action taken before each re-run."""
    from partinspect.pipeline import run_inspection

    step, images = plate_variants
    reports = {k: run_inspection(step, d, tmp_path / k).report for k, d in images.items()}
    nominal = _measured(reports["nominal"])
    assert len(nominal) >= 15
    # An edge whose grey step is below the detection limit in the nominal images, which the
    # nominal run still measured from a few points where a neighbouring edge's smoothing lends
    # it a gradient, is no requirement on the degraded ones (plate line-11: 2 grey levels, 8
    # points beside a corner of the part).
    faint_edges = _undetectable(step, images["nominal"], reports["nominal"], noise=2.0)
    assert len(faint_edges & nominal) <= 1, faint_edges & nominal
    nominal -= faint_edges
    for name in ("noisy", "faint"):
        rep = reports[name]
        assert nominal <= _measured(rep), (name, nominal - _measured(rep), rep["adaptive"])
        rounds = rep["adaptive"]["rounds"]
        assert rounds and rounds[0]["params"]["sigma"] == 1.0
        assert sum(r["kept"] for r in rounds) >= 1
        for r in rounds[1:]:
            # Every re-run names the situation that caused it and the change made.
            assert r["after"]["situation"] in {s.name for s in SITUATIONS} and r["after"]["change"]
        # No verdict is won by degrading the images: what the nominal run judged, this one judges
        # or leaves inconclusive, never turns a nominal pass into a fail.
        fails = {c["id"] for c in rep["characteristics"] if c["decision"] == "fail"}
        assert not fails, (name, fails)


def test_a_rerun_recovers_edges_at_four_times_the_noise_and_keeps_the_rest(tmp_path):
    """The bracket at 1224 x 1024 with noise 8 (four times the nominal): the first round misses
    expected edges of 4-6 noise units of grey step (a wall hole, an arc); re-runs at lower
    thresholds and with the 1.5 px filter find them, and what they find joins the first round's
    features instead of replacing them (a re-run kept whole loses other edges)."""
    import cv2

    from partinspect.pipeline import run_inspection
    from partinspect.simulate.render import render_radiance_pair
    from partinspect.simulate.folder import BLUR_SIGMA
    from partinspect.simulate.render import sensor
    from partinspect.simulate.rig import default_rig
    from partinspect.vision.calibration import write_calibration
    from tests.simulate.scenes import Part

    part = Part("bracket")
    rig = default_rig((1224, 1024))
    radiance = render_radiance_pair(part.scene, rig, part.pose(rig), blur_sigma=BLUR_SIGMA)
    reports = {}
    for name, noise in (("nominal", 2.0), ("noisy", 8.0)):
        images = tmp_path / name / "images"
        images.mkdir(parents=True)
        rng = np.random.default_rng([0, 3])
        for side, img in zip(("left", "right"), radiance):
            cv2.imwrite(str(images / f"{side}.png"), sensor(img, noise, rng))
        write_calibration(images / "calibration.yaml", rig)
        reports[name] = run_inspection(part.path, images, tmp_path / name / "out").report
    rounds = reports["noisy"]["adaptive"]["rounds"]
    added = [fid for r in rounds if r["kept"] for fid in r.get("added", [])]
    assert rounds[0]["missing"] and added, rounds
    assert set(added) <= _measured(reports["noisy"])
    assert len(next(r for r in reversed(rounds) if r["kept"])["missing"]) < len(rounds[0]["missing"])
    # Nothing the nominal pair measures is lost on the way.
    assert _measured(reports["nominal"]) <= _measured(reports["noisy"]), rounds


def test_an_ambiguous_pose_is_run_again_and_a_round_with_one_pose_is_kept():
    """Two poses explaining the features alike is a situation: a re-run may measure the feature
    that tells them apart, and a round that finds one pose beats one that finds several, even
    with an edge fewer measured."""
    vis = {"line-1": SEEN, "line-2": SEEN}
    calls = []

    def run(params):
        calls.append(dict(params))
        one = params["min_points"] == 8
        reg = _registration(["line-1"] if one else ["line-1", "line-2"])
        reg.ambiguity = "" if one else "two poses 180.0 degrees apart explain the 2 matched features equally well"
        return _stereo(), reg, vis

    best, log, advice = measure_adaptively(run)
    assert [s["name"] for s in log[0]["situations"]] == ["pose ambiguous"]
    assert calls[1] == {**DEFAULTS, "min_points": 8}
    assert best.params["min_points"] == 8 and log[1]["kept"] and best.state.missing == ("line-2",)
    assert "pose ambiguous" not in [a["situation"] for a in advice]
