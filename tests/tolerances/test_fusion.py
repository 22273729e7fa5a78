"""Fusion of several views: the consistency test, the combination, characteristics on combined features."""

import math

import numpy as np
import pytest

from partinspect.cad.registration import register
from partinspect.poses import turned_pose
from partinspect.simulate.measured import measure_features
from partinspect.tolerances.evaluate_fused import evaluate_fused, pair_value
from partinspect.tolerances.fusion import (
    VIEW_P,
    combine,
    consistent_views,
    expand,
    fuse,
    motion_test,
    pose_information,
    reduce,
    view_motion,
)
from partinspect.tolerances.geometry import feature_distance
from partinspect.tolerances.resolve import Characteristic

BOUNDS = np.array([[0.0, 0.0, 0.0], [80.0, 60.0, 10.0]])


def C(cid, ctype, feats, nominal=0.0, lo=None, up=1.0, unit="mm"):
    return Characteristic(cid, ctype, tuple(feats), nominal, lo, up, "test", unit=unit)


def test_combine_two_equal_views_shrinks_u_by_sqrt_two_and_unequal_ones_by_their_covariances():
    C1 = np.diag([4.0, 1.0])
    _, cov, W = combine([np.zeros(2), np.ones(2)], [C1, C1])
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(C1)) / math.sqrt(2))
    np.testing.assert_allclose(sum(W), np.eye(2))
    y, cov, _ = combine([np.array([0.0]), np.array([3.0])], [np.array([[1.0]]), np.array([[4.0]])])
    # inverse-variance weights 4/5 and 1/5; variance 1 / (1 + 1/4)
    assert y[0] == pytest.approx(0.6) and cov[0, 0] == pytest.approx(0.8)


def test_combining_in_blocks_weights_each_block_alone_and_keeps_the_full_covariance():
    # two views whose radius (index 1) correlates with the centre (index 0) in opposite senses
    C1 = np.array([[1.0, 0.9], [0.9, 1.0]])
    C2 = np.array([[1.0, -0.9], [-0.9, 1.0]])
    ys = [np.array([0.0, 0.0]), np.array([1.0, 1.0])]
    _, full, _ = combine(ys, [C1, C2])
    y, cov, W = combine(ys, [C1, C2], blocks=[(0, 1), (1, 2)])
    # the full GLS lets each view's centre correct the other's radius: 0.095, a fifth of the scalar 0.5
    assert full[1, 1] == pytest.approx(0.095)
    # apart, each block is the scalar combination of the marginals; the covariance is the weighted sum's
    assert cov[1, 1] == pytest.approx(0.5) and y[1] == pytest.approx(0.5)
    np.testing.assert_allclose(cov, sum(w @ c @ w.T for w, c in zip(W, [C1, C2])))


def test_consistency_test_passes_chance_and_names_an_outlier_view():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((3, 3))
    cov = A @ A.T + np.eye(3)
    L = np.linalg.cholesky(cov)
    kept_all, false = 0, 0
    for _ in range(2000):
        ys = [L @ rng.standard_normal(3) for _ in range(3)]
        kept, rejected = consistent_views(ys, [cov] * 3, significance=0.99)
        false += len(rejected) > 0
        kept_all += len(kept) == 3
    # each of 3 views tested at 99 %: about 3 % of consistent triples lose a view
    assert 0.01 < false / 2000 < 0.06
    ys = [L @ rng.standard_normal(3) for _ in range(3)]
    ys[1] = ys[1] + 8 * L @ np.array([1.0, 0, 0])
    kept, rejected = consistent_views(ys, [cov] * 3)
    assert kept == [0, 2] and rejected[0]["index"] == 1 and rejected[0]["chi2"] > rejected[0]["threshold"]
    assert not rejected[0]["pair"]
    # two that disagree: the one ranked lower goes
    kept, rejected = consistent_views(ys[:2], [cov] * 2, rank=[1.0, 0.5])
    assert kept == [1] and rejected[0]["index"] == 0 and rejected[0]["pair"]


def test_reduced_form_ignores_where_along_a_line_and_the_axis_sign(plate):
    inv = plate[0]
    line, circle = inv["line-5"], inv["circle-4"]
    d = (line.end - line.start) / np.linalg.norm(line.end - line.start)
    x = np.r_[line.start + [0.0, 0.01, 0.02], d]
    y = reduce("line", x, line)
    np.testing.assert_allclose(reduce("line", np.r_[x[:3] + 7.0 * d, -d], line), y, atol=1e-12)
    np.testing.assert_allclose(reduce("line", expand("line", y, line), line), y, atol=1e-12)
    c = np.r_[circle.center + 0.01, -circle.normal, circle.radius + 0.003]
    yc = reduce("circle", c, circle)
    np.testing.assert_allclose(expand("circle", yc, circle), np.r_[c[:3], circle.normal, c[6]], atol=1e-12)


def _views(plate, turns, rng, shifts=None):
    inv, T, ids = plate
    regs = []
    for k, turn in enumerate(turns):
        P = turned_pose(T, turn, BOUNDS)
        m = measure_features(inv, P, ids, rng, n_points=0, shifts=(shifts or {}).get(k))
        regs.append(register(m.circles, m.lines, inv, pose_hint=P))
    return regs


def test_two_consistent_views_shrink_u_as_their_covariances_predict(plate):
    inv = plate[0]
    regs = _views(plate, [(0, 0, 0), (0, 0, 25)], np.random.default_rng(3))
    parts = [r.features_in_part_frame() for r in regs]
    fused = fuse(parts, inv)
    f = fused["circle-4"]
    assert f.views == (0, 1) and not f.rejected
    one = [next(p for p in ps if p.cad_id == "circle-4") for ps in parts]
    u = [math.sqrt(p.param_cov[0, 0]) for p in one]
    predicted = 1.0 / math.sqrt(sum(1.0 / p.param_cov[0, 0] for p in one))  # the x coordinate alone
    assert math.sqrt(f.param_cov[0, 0]) < min(u)
    assert math.sqrt(f.param_cov[0, 0]) == pytest.approx(predicted, rel=0.25)
    assert f.radius_std == pytest.approx(1 / math.sqrt(sum(1 / p.radius_std**2 for p in one)), rel=0.05)


def test_an_outlier_view_is_left_out_and_named(plate):
    inv = plate[0]
    shifts = {2: {"circle-4": np.array([0.2, 0.0, 0.0])}}  # view 3 (a bumped measurement) sees the hole elsewhere
    regs = _views(plate, [(0, 0, 0), (0, 0, 20), (0, 0, -20)], np.random.default_rng(4), shifts)
    fused = fuse([r.features_in_part_frame() for r in regs], inv)
    f = fused["circle-4"]
    assert f.views == (0, 1)
    assert [r["view"] for r in f.rejected] == [2] and "beyond chance" in f.rejected[0]["reason"]
    assert not fused["circle-2"].rejected


def test_fused_characteristics_are_honest_over_draws(plate):
    inv = plate[0]
    chars = [
        C("d", "diameter", ["circle-4"], 12.0, 11.9, 12.1),
        C("p", "position", ["circle-2"], up=0.1),
        C("cc", "distance", ["circle-2", "circle-4"], feature_distance(inv["circle-2"], inv["circle-4"]), 0, 100),
        C("ll", "distance", ["line-5", "line-8"], 60.0, 59, 61),
        C("a", "angle", ["line-5", "line-1"], math.pi / 2, 1.5, 1.6, unit="rad"),
    ]
    rng = np.random.default_rng(5)
    z, both, rejected, tested = [], 0, 0, 0
    for draw in range(40):
        regs = _views(plate, [(0, 0, 0), (0, 0, 25)], rng)
        fused = fuse([r.features_in_part_frame() for r in regs], inv)
        rejected += sum(len(f.rejected) for f in fused.values())
        tested += len(fused)
        ev, used = evaluate_fused(chars, fused, regs, inv, seed=draw, n_mc=1000)
        both += sum(u == (0, 1) for u in used)
        z.append([(e.measured - c.nominal) / e.standard_uncertainty for e, c in zip(ev, chars)])
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert both > 0.9 * 40 * len(chars)
    # consistent views: a pair is split by chance in about 1 % of features
    assert rejected / tested < 0.04, (rejected, tested)
    # the position at zero offset is Rice-distributed: its u is the RMS of that error (see true_position)
    assert np.all((rms > 0.6) & (rms < 1.45)), rms


def test_a_distance_between_features_of_different_views_carries_both_poses(plate):
    inv, _, ids = plate
    regs = _views(plate, [(0, 0, 0), (0, 0, 25)], np.random.default_rng(6))
    parts = [r.features_in_part_frame() for r in regs]
    # circle-2 from view 1 only, circle-4 from view 2 only
    only = [[p for p in parts[0] if p.cad_id != "circle-4"], [p for p in parts[1] if p.cad_id != "circle-2"]]
    fused = fuse(only, inv)
    c = C("cc", "distance", ["circle-2", "circle-4"], feature_distance(inv["circle-2"], inv["circle-4"]), 0, 100)
    (ev,), (used,) = evaluate_fused([c], fused, regs, inv)
    assert used == (0, 1)
    a, b = fused["circle-2"], fused["circle-4"]
    n = (b.center - a.center) / np.linalg.norm(b.center - a.center)
    # independent views: the variances add, each with its own pose's part (the in-plane distance's gradient)
    expected = math.sqrt(n @ a.covariance @ n + n @ b.covariance @ n)
    assert ev.standard_uncertainty == pytest.approx(expected, rel=0.1)
    # the same two circles in one view: in the part frame with their cross-covariance through the shared pose
    # (what the combination uses), the distance's u is the rig frame's, where the pose does not enter
    one = fuse([parts[0]], inv)
    (ev1,), _ = evaluate_fused([c], one, regs[:1], inv)
    assert ev1.method == "first order (pose-invariant)"
    joint = pair_value(c, [one["circle-2"], one["circle-4"]], regs[:1], 2.0)
    assert joint.standard_uncertainty == pytest.approx(ev1.standard_uncertainty, rel=0.03)
    assert joint.measured == pytest.approx(ev1.measured, abs=1e-9)


def test_views_with_one_calibration_share_its_error(plate):
    """Two views through one rig whose calibration is off by a shared draw (a turn, a shift and a scale, the
    scale mostly, 3.6 times the image noise on a radius): its part does not average down over the views. The
    combined diameters' variance is about (n / 2 + g) against (n + g) / 2 taken as independent, and with the
    shared part carried u covers the errors."""
    from tests.cad.test_registration import _with_shared_error

    inv, T, ids = plate
    chars = [
        C("d4", "diameter", ["circle-4"], 12.0, 11.9, 12.1),
        C("d2", "diameter", ["circle-2"], 8.0, 7.9, 8.1),
        C("cc", "distance", ["circle-2", "circle-4"], feature_distance(inv["circle-2"], inv["circle-4"]), 0, 100),
    ]
    rng = np.random.default_rng(8)
    z, ratio = [], []
    for draw in range(30):
        e = rng.standard_normal(7)
        regs = []
        for turn in [(0, 0, 0), (0, 0, 25)]:
            P = turned_pose(T, turn, BOUNDS)
            m = measure_features(inv, P, ids, rng, n_points=0, lateral=0.0005, depth=0.002)
            circles, lines = _with_shared_error(m, e, (2e-5, 0.01, 3e-4))
            regs.append(register(circles, lines, inv, pose_hint=P))
        parts = [r.features_in_part_frame() for r in regs]
        shared, independent = fuse(parts, inv, registrations=regs), fuse(parts, inv)
        f, g = shared["circle-4"], independent["circle-4"]
        if f.views == (0, 1):
            ratio.append(f.radius_std ** 2 / g.radius_std ** 2)
        ev, _ = evaluate_fused(chars, shared, regs, inv, seed=draw, n_mc=200)
        z.append([(x.measured - c.nominal) / x.standard_uncertainty for x, c in zip(ev, chars)])
    n, g = 0.0005 ** 2, (6.0 * 3e-4) ** 2
    assert len(ratio) >= 27
    assert np.median(ratio) == pytest.approx((n / 2 + g) / ((n + g) / 2), rel=0.1)
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.6) & (rms < 1.4)), rms


def test_fused_position_at_mmc_and_parallelism(plate):
    """Over two views: the bonus from the combined size, the tilt from the combined lines."""
    from partinspect.tolerances.resolve import characteristics_for
    from partinspect.tolerances.spec import parse_spec

    inv = plate[0]
    chars = {c.id: c for c in characteristics_for(parse_spec(
        "features:\n  circle-4:\n    diameter: {upper: 0.1, lower: -0.05}\n"
        "    position: {tolerance: 0.05, material: MMC}\n"
        "angles:\n  - {between: [line-8, line-5], upper: 0.5, lower: -0.5, towards: [0, 1, 0]}\n"), inv)}
    picked = [chars["circle-4.position"], chars["circle-4.diameter"], chars["angle(line-8,line-5)"]]
    regs = _views(plate, [(0, 0, 0), (0, 0, 25)], np.random.default_rng(6))
    fused = fuse([r.features_in_part_frame() for r in regs], inv)
    (pos, size, par), used = evaluate_fused(picked, fused, regs, inv, n_mc=1000)
    assert used == [(0, 1)] * 3
    assert pos.details["measured_size"] == size.measured
    assert pos.details["bonus"] == pytest.approx(size.measured - 11.95, abs=1e-12)
    assert pos.measured == pytest.approx(pos.details["position"] - pos.details["bonus"], abs=1e-12)
    assert par.characteristic.type == "parallelism" and "combined" in par.method
    assert abs(par.measured) < 4 * par.standard_uncertainty and 0 < par.standard_uncertainty < 1e-3


def test_a_form_is_judged_in_the_view_that_judges_it_best(plate):
    """Both views see the whole edge; the second's points are four times less noisy: its straightness is the
    one reported (the first view, which the most points would have chosen on a tie, judges it far worse)."""
    from partinspect.tolerances.evaluate import evaluate_characteristic

    inv, T, ids = plate
    rng = np.random.default_rng(11)
    regs = []
    for turn, sd in [((0, 0, 0), 0.02), ((0, 0, 25), 0.005)]:
        P = turned_pose(T, turn, BOUNDS)
        m = measure_features(inv, P, ids, rng, n_points=60, point_lateral=sd / 4, point_depth=sd)
        regs.append(register(m.circles, m.lines, inv, pose_hint=P))
    fused = fuse([r.features_in_part_frame() for r in regs], inv)
    c = C("s", "straightness", ["line-5"], 0.0, None, 0.05)
    assert fused["line-5"].views == (0, 1)
    (ev,), (used,) = evaluate_fused([c], fused, regs, inv, n_mc=200)
    single = [evaluate_characteristic(c, r.features_in_part_frame(), r, inv, n_mc=200) for r in regs]
    assert used == (1,) and single[1].standard_uncertainty < 0.5 * single[0].standard_uncertainty
    assert ev.standard_uncertainty == pytest.approx(single[1].standard_uncertainty)


def _partly_determined(rng, n=12):
    """A pose covariance and 12 features of 4 parameters that see the whitened pose error strongly in 2 directions
    (information about 200 each) and weakly in the 4 others (under 0.1), unit covariance apart from the pose."""
    A = rng.standard_normal((6, 6))
    S = 1e-6 * (A @ A.T + np.eye(6))
    L = np.linalg.cholesky(S)
    Q, _ = np.linalg.qr(rng.standard_normal((6, 6)))
    responses = [(2.0 * rng.standard_normal((4, 2)) @ Q[:, :2].T + 0.02 * rng.standard_normal((4, 6)))
                 @ np.linalg.inv(L) for _ in range(n)]
    return S, L, Q, responses, [np.eye(4)] * n


def test_the_motion_is_tested_in_the_directions_the_shared_features_determine():
    """A view's pose error tested only where the shared features know it at least as well as its own covariance:
    2 of 6 directions here. Right views: the statistic is chi-square on 2 (mean 2, refused at VIEW_P's rate). A pose
    5 u off in a determined direction (non-centrality 24.9): refused with probability 0.92 on 2 degrees of freedom,
    0.78 if all six directions are tested as before (the same statistic over all six); 5 u off in an undetermined
    direction: not refused (the features cannot see it)."""
    from scipy.special import chdtrc

    rng = np.random.default_rng(39)
    S, L, Q, responses, covs = _partly_determined(rng)
    info, _, _ = pose_information(responses, covs, S)
    assert (info >= 1).sum() == 2 and info[-2] > 100 and info[:4].max() < 0.1

    def refused(offset, threshold, n):
        out = []
        for _ in range(n):
            xi = L @ (rng.standard_normal(6) + offset)
            t = motion_test([G @ xi + rng.standard_normal(4) for G in responses], responses, covs, S, threshold)
            out.append((t["chi2"], t["dof"], chdtrc(t["dof"], t["chi2"]) < VIEW_P))
        return out

    right = refused(np.zeros(6), 1.0, 1000)
    assert {d for _, d, _ in right} == {2}
    assert 1.75 < np.mean([c for c, _, _ in right]) < 2.25  # chi-square on 2: mean 2, its sd over 1000 draws 0.063
    assert np.mean([r for *_, r in right]) < 0.005
    new = np.mean([r for *_, r in refused(5 * Q[:, 0], 1.0, 300)])
    six = np.mean([r for *_, r in refused(5 * Q[:, 0], 0.0, 300)])
    assert new > 0.85 and new - six > 0.07, (new, six)  # expected 0.92 and 0.78 (binomial sd 0.016 and 0.024)
    assert np.mean([r for *_, r in refused(5 * Q[:, 4], 1.0, 300)]) < 0.01


def test_a_view_whose_shared_features_are_all_its_datums_has_no_motion_to_test(plate):
    """On the plate every feature a view shares with the others is a datum of its pose: its part-frame value is
    its registration residual, uncorrelated with the pose estimate, so the features tell nothing of the pose error
    (information below 0.05 of the pose's own in every direction) and no motion is fitted or tested."""
    inv = plate[0]
    regs = _views(plate, [(0, 0, 0), (0, 0, 25), (0, 0, -25)], np.random.default_rng(12))
    parts = [r.features_in_part_frame() for r in regs]
    for v in range(3):
        shared = [pf for pf in parts[v] if pf.cad_id and any(q.cad_id == pf.cad_id for u in range(3) if u != v
                                                             for q in parts[u])]
        assert len(shared) >= 3 and all(pf.datum for pf in shared)
        t = view_motion(v, [u for u in range(3) if u != v], parts, regs, inv)
        assert t["info"].max() < 0.05, t["info"]
        assert t["dof"] == 0 and t["p"] == 1.0 and not t["outliers"]
