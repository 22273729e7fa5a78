"""The whole stereo chain on rendered sample parts, against the truth."""

import dataclasses
import os
import struct
from dataclasses import replace

import numpy as np
import pytest

from partinspect.vision.forked import can_fork
from partinspect.vision.ideal import camera_matrices
from partinspect.vision.matching import epipolar_geometry
from partinspect.vision.stereo import measure_stereo
from tests.vision import stereo_scenes as S

SEEDS = (0, 1)
CAL_STD = {"intrinsics1": np.r_[0.5, 0.5, 0.3, 0.3, np.zeros(5)],
           "intrinsics2": np.r_[0.5, 0.5, 0.3, 0.3, np.zeros(5)],
           "extrinsics": np.r_[2e-5, 2e-5, 2e-5, 0.005, 0.005, 0.005]}
_RESULTS = {}


def measured(seed, distortion=False):
    key = (seed, distortion)
    if key not in _RESULTS:
        rig, pose, L, R = S.render("plate", 2.0, seed, distortion)
        _RESULTS[key] = (rig, measure_stereo(L, R, rig))
    return _RESULTS[key]


def arc_views(seed=0):
    """(feature, left, right, views) of every matched arc pair of ``measured(seed)``, as the 3D fit takes them."""
    from partinspect.vision.stereo import feature_views

    rig, res = measured(seed)
    for f in res.features:
        fl, fr = res.left.features[f.left], res.right.features[f.right]
        if fl.kind == "arc":
            yield f, fl, fr, feature_views(fl, fr, res.left.edges.sigma, rig)


def errors(seed, distortion=False):
    """Per measured feature: (kind, id, error vector, covariance, radius error, radius std)."""
    rig, res = measured(seed, distortion)
    truths = {t["id"]: t for t in S.truth_in_rig("plate", distortion)}
    P1, _ = camera_matrices(rig)
    out = []
    for f in res.features:
        lab = S.label_image_feature(res.left.features[f.left].ideal.xy, list(truths.values()), P1)
        assert lab is not None
        t = truths[lab]
        if f.kind == "line":
            out.append(("line", lab, S.line_point_error(f.point, f.direction, t), f.covariance, 0.0, 0.0))
        else:
            out.append((f.kind, lab, f.center - t["center"], f.covariance, f.radius - t["radius"], f.radius_std))
    return out


def test_result_structure_and_nothing_dropped():
    rig, res = measured(0)
    m = res.matching
    assert len(res.features) + len(res.failed) == len(m.matches) >= 15
    n_l = len(res.left.features)
    seen = {x.left for x in m.matches} | {u.feature for u in m.unmatched if u.side == "left"}
    assert seen == set(range(n_l))
    for f in res.features:
        assert np.all(np.linalg.eigvalsh(f.covariance) >= -1e-15)
        assert len(f.correspondences) > 5
        if f.kind == "line":
            assert np.linalg.norm(f.end - f.start) > 1.0
        else:
            assert 0 < f.angle_end - f.angle_start <= 2 * np.pi + 1e-9


def test_the_points_error_model_cuts_its_tails_where_the_left_fit_rejected_points():
    # A form zone is set by its points' largest errors; the left fit let
    # through only points within Chauvenet's threshold for its count, and
    # the model the form's simulation draws from says so.
    from partinspect.vision.imagefeatures import chauvenet_z

    rig, res = measured(0)
    for f in res.features:
        n = len(res.left.features[f.left].ideal.xy)
        assert f.point_errors.outlier_z == pytest.approx(chauvenet_z(n))


def test_lines_accurate_and_honest():
    z = []
    for seed in SEEDS:
        for kind, lab, e, C, _, _ in errors(seed):
            if kind != "line":
                continue
            assert np.linalg.norm(e) < 0.03, (lab, e)  # mm
            z.append(e @ np.linalg.pinv(C, rcond=1e-10) @ e / 2)  # chi2(2) / 2
    # Normalised errors: mean chi2/dof near 1 (neither much too large nor too small).
    assert 0.4 < np.mean(z) < 2.5, np.mean(z)


def test_circles_accurate_depth_worst():
    E, dr = [], []
    for seed in SEEDS:
        for kind, lab, e, C, r, u in errors(seed):
            if kind == "circle":
                E.append(e)
                dr.append(r)
    E, dr = np.array(E), np.array(dr)
    assert len(E) >= 6
    assert np.abs(E).max() < 0.05 and np.abs(dr).max() < 0.03  # mm
    rms = np.sqrt((E**2).mean(axis=0))
    assert rms[2] > rms[0] and rms[2] > rms[1]  # the paper's observation: depth is worst


def test_circles_honest():
    # The rims of the plate's holes are rendered with their shaded inner walls
    # visible, which displaces the edge points (stereo module notes, "Rims of
    # holes"): corrected to first order, the rest carried as a Type B component.
    # Normalised errors over the circles of both draws (8 here: the same four
    # holes twice): centre chi2 / 3 and radius error / u near 1, neither much
    # too large (bias left unaccounted for) nor much too small (an inflated
    # budget); most inside their 95 % region. The bounds allow for the
    # sampling spread of 8 values (benchmarks/bench_stereo.py runs more).
    z, rz = [], []
    for seed in SEEDS:
        for kind, lab, e, C, r, u in errors(seed):
            if kind == "circle":
                z.append(e @ np.linalg.inv(C) @ e)
                rz.append(r / u)
    z, rz = np.array(z), np.array(rz)
    assert len(z) >= 6
    assert 0.4 < np.mean(z) / 3 < 2.5, z / 3
    assert np.mean(z <= 7.814727903251178) >= 0.75, z / 3  # chi2(3) 95 % quantile
    # Under this one light each hole's shading displacement is one fixed
    # offset, which the Type B (sized for how it varies over lights) covers
    # with room: 0.66 here (seeds 0-1); an inflated budget would read far lower.
    assert 0.35 < np.sqrt(np.mean(rz ** 2)) < 1.6, rz
    assert np.mean(np.abs(rz) <= 2) >= 0.75, rz


def test_rim_radii_are_stated_at_their_size():
    # A radius is the mean of its rim's displacements, which the fit's Type B
    # states with the shading bound read as a rectangular distribution's
    # half-width (rim_errors.rim_type_b) and the curvature correction's
    # remainder as one mode of the rim (rim_errors.curvature_mode).
    # With each point at 0.75 times the bound and a 0.01 px floor the radii
    # of these 14 rims (circles and arcs, seeds 0-1) read 0.52 RMS |error|/u,
    # the largest 1.06: stated about twice their size. Now 0.68, the largest
    # 1.31; none beyond the 99.9 % bound.
    rz = np.array([r / u for seed in SEEDS for kind, lab, e, C, r, u in errors(seed) if kind != "line"])
    assert len(rz) >= 12
    assert np.sqrt(np.mean(rz ** 2)) > 0.6, rz
    assert np.all(np.abs(rz) < 3.29), rz


def test_rim_type_b_reads_the_bound_as_a_rectangular_half_width():
    from partinspect.vision.rim_errors import RIM_DETECTOR_ERROR, rim_type_b

    b = np.array([0.0, 0.01, 0.1, 0.3])
    u = rim_type_b(b)
    assert u[0] == pytest.approx(RIM_DETECTOR_ERROR)
    # JCGM 100 4.3.7: +-a, no value likelier, u = a / sqrt(3); the floor in quadrature.
    assert u[3] == pytest.approx(np.hypot(0.3 / np.sqrt(3.0), RIM_DETECTOR_ERROR))
    assert np.all(np.diff(u) > 0)


def test_a_rims_curvature_remainder_is_one_mode_of_both_views():
    # What the curvature correction leaves is one unknown fraction of it for
    # the whole rim: a mode both views share, in proportion to each point's
    # correction, so it moves the radius by that fraction of the correction
    # and is not averaged away round the rim as the shading's rest is.
    from partinspect.vision.correspondences import curvature_bias
    from partinspect.vision.fit3d import information_parts
    from partinspect.vision.rim_errors import CURVATURE_REMAINDER

    checked = 0
    for f, fl, fr, views in arc_views():
        for v, side in zip(views, (fl, fr)):
            (k,) = [j for j, name in enumerate(v.mode_names) if name[0] == "curvature"]
            assert np.allclose(v.modes[k], CURVATURE_REMAINDER * curvature_bias(side.ideal.xy, side.fit, side.blur)[0],
                               rtol=0.05)
            assert np.all(v.modes[k] > 0)  # towards the centre of curvature everywhere: one sign round the rim
        assert views[0].mode_names == views[1].mode_names
        # Shared: the two views' weighted patterns add before the outer product
        # (a rank-one systematic information), not their outer products.
        plain = [type(v)(v.xy, v.sigma, v.P, modes=v.modes[k:k + 1], mode_names=v.mode_names[k:k + 1]) for v in views]
        J = np.ones((sum(len(v.xy) for v in plain), 1))
        _, _, Mb = information_parts(plain, J)
        a = sum(float(np.sum(v.modes[0] / v.total_sigma)) for v in plain)
        assert Mb[0, 0] == pytest.approx(a * a, rel=1e-9)
        checked += 1
    assert checked >= 4


def test_the_radius_leaves_the_detectors_floor_out():
    # The floor in rim_type_b is the detector's error point by point; the
    # radius takes the detector's share as the curvature mode, so its
    # systematic variance is the rest's alone: with a uniform rest b and the
    # floor f in quadrature, exactly b^2 / (b^2 + f^2) of the stated one.
    from dataclasses import replace

    from partinspect.vision.rim_errors import RIM_DETECTOR_ERROR, radius_type_b_scale

    checked = 0
    for f, _, _, views in arc_views():
        for b in (0.0, 0.004, 0.02):
            total = np.hypot(b, RIM_DETECTOR_ERROR)
            flat = [replace(v, bias=np.full(len(v.xy), total), modes=None, mode_names=None) for v in views]
            assert radius_type_b_scale(flat, f.fit) == pytest.approx(b / total, abs=1e-6)
        if f.kind == "circle":
            # Round a whole rim the floor, correlated over 0.2 rad, averages
            # out in the radius; the curvature mode, common to the rim, does
            # not, and is most of what remains (0.7-0.95 of the two here).
            withmode = [replace(v, bias=np.full(len(v.xy), RIM_DETECTOR_ERROR)) for v in views]
            assert radius_type_b_scale(withmode, f.fit) > 0.5
        checked += 1
    assert checked >= 4


def test_the_form_keeps_its_point_level_type_b():
    # The rims' point errors (what the form's zone is simulated with) keep
    # EDGE_BIAS_FACTOR times the bound with EDGE_BIAS_FLOOR; only the 3D
    # fit's centre and radius take rim_type_b.
    from partinspect.vision.edges import EDGE_BIAS_FACTOR
    from partinspect.vision.rim_errors import EDGE_BIAS_FLOOR, rim_type_b

    checked = 0
    for f, fl, _, views in arc_views():
        if fl.background_bound is None:
            continue
        view = views[0]
        assert np.allclose(view.bias, rim_type_b(fl.background_bound))
        model = f.point_errors
        stated = np.hypot(EDGE_BIAS_FACTOR * fl.background_bound, EDGE_BIAS_FLOOR)
        (k,) = model.systematic
        assert np.allclose(model.components[k][0], stated[f.correspondences.left_index])
        checked += 1
    assert checked >= 4



def test_rim_points_covariances_cover_their_errors():
    # Each triangulated rim point's radial distance from the true circle
    # against its standard uncertainty from point_covs (what the report's
    # point figures show): the correction's noise and the shading's Type B
    # rest are in it. The triangulation's own covariances (image noise and
    # the right fit only) gave a normalised RMS of 1.9 over these points,
    # 72 % within 2 u.
    truths = {t["id"]: t for t in S.truth_in_rig("plate")}
    z = []
    for seed in SEEDS:
        rig, res = measured(seed)
        P1, _ = camera_matrices(rig)
        for f in res.features:
            if f.kind == "line":
                # Lines: the same, but for the tiny along-edge part of the
                # points' noise and a removed phase ripple's correction error
                # (pixel_phase), which only adds, and little.
                c = f.correspondences.cov
                extra = f.point_covs - c
                fl = res.left.features[f.left]
                tol = 1e-3 * np.abs(c).max()
                if fl.phase_factor is None:
                    assert np.abs(extra).max() < tol
                else:
                    assert np.linalg.eigvalsh(extra).min() > -tol
                    assert np.trace(extra, axis1=1, axis2=2).max() < 0.1 * np.trace(c, axis1=1, axis2=2).max()
                continue
            t = truths[S.label_image_feature(res.left.features[f.left].ideal.xy, list(truths.values()), P1)]
            v = f.points - t["center"]
            v = v - np.outer(v @ t["normal"], t["normal"])
            rho = v / np.linalg.norm(v, axis=1)[:, None]
            u = np.sqrt(np.einsum("ni,nij,nj->n", rho, f.point_covs, rho))
            z.append((np.linalg.norm(v, axis=1) - t["radius"]) / u)
    z = np.concatenate(z)
    assert len(z) > 1000
    assert np.sqrt(np.mean(z ** 2)) < 1.45, np.sqrt(np.mean(z ** 2))
    assert np.mean(np.abs(z) <= 2) >= 0.85, np.mean(np.abs(z) <= 2)


def test_distorted_images_measured_through_ideal_pixels():
    # Within 0.05 mm, or within three standard uncertainties where those are
    # larger: the far rim of the plate's 12 mm hole (circle-3), seen over
    # 90 degrees through the hole, is measured to about 0.1 mm with 0.16 mm.
    errs = errors(0, distortion=True)
    assert len(errs) >= 12
    for kind, lab, e, C, r, u in errs:
        assert np.linalg.norm(e) < max(0.05, 3.0 * np.sqrt(np.trace(C))), (lab, e, np.sqrt(np.diag(C)))


def test_the_background_corrections_noise_has_the_stated_correlation():
    """The correction of a rim's points is the Gaussian mean along the edge
    of readings whose noise is correlated as the edge points' own (l = 1
    px): its noise then has the stated standard deviation and is
    correlated over correction_corr_length (2.2 px), not over 1 px."""
    from partinspect.vision.montecarlo import correlated_normal_errors
    from partinspect.vision.rim_errors import correction_corr_length, smoothed_background

    xy = np.c_[np.arange(120.0), np.zeros(120)]
    z = correlated_normal_errors(xy, 1.0, 4000, np.random.default_rng(3))
    std = np.full(120, 0.02)
    # The mean is linear in the readings: all draws at once, one per column.
    means, stated = smoothed_background(xy, 0.02 * z.T, std, 1.0)
    assert abs(means[60].std() / stated[60] - 1) < 0.05
    L = correction_corr_length(1.0)
    for d in (2, 4, 6):
        rho = np.corrcoef(means[60], means[60 + d])[0, 1]
        assert abs(rho - np.exp(-d * d / (4 * L * L))) < 0.04, (d, rho)
        if d < 6:
            assert rho - np.exp(-d * d / 4.0) > 0.3  # far from the image noise's correlation


def test_calibration_uncertainty_is_added():
    rig, res = measured(0)
    rig_std = replace(rig, std=CAL_STD)
    _, _, L, R = S.render("plate", 2.0, 0)
    res2 = measure_stereo(L, R, rig_std)
    assert res2.calibration_included and not res.calibration_included
    for a, b in zip(res.features, res2.features):
        assert np.allclose(a.params, b.params)
        assert np.allclose(b.param_cov, b.param_cov_image + b.param_cov_calibration + b.param_cov_systematic)
        assert np.allclose(a.param_cov_systematic, b.param_cov_systematic)
        assert np.all(np.linalg.eigvalsh(b.param_cov_calibration) > -1e-12)
        assert np.trace(b.covariance) > 2 * np.trace(a.covariance)


def test_a_rim_fading_against_its_lit_wall_does_not_bend_its_arc():
    """Under a light from the upper right (one of bench_stereo's six) the
    plate's 6 mm hole fades against its inner wall in both images; its
    contour ran on for a few points along the wall's shading (0.5-3 px off
    the rim, their uncertainty up to 30 times the rim's), and the short arc's
    ellipse took them in: the 3D centre came out 0.98 mm off, 17 standard
    uncertainties. Such points are now left out (imagefeatures.FADE_RATIO): the
    rim is then in two short pieces whose fits disagree and is not measured,
    and every hole rim measured is within its 99.9 % ellipsoid."""
    from partinspect.simulate.render import render_radiance, sensor
    from partinspect.cad.raycast import camera_in_part

    p = S.part("plate")
    rig = p.rig(False, S.SIZE)
    pose = p.pose(rig)
    light = pose[:3, :3].T @ np.array([0.3029156645346948, 0.31365622079365146, -0.899923260804469])
    rad = []
    for i in range(2):
        K, D, R, t = camera_in_part(rig, i, pose)
        rad.append(render_radiance(p.scene, K, D, R, t, rig.image_size, light, psf=0.6)[0])
    rng = np.random.default_rng(2000)
    for _ in range(6):  # bench_stereo's draw 3 of this light
        rng.standard_normal(rad[0].shape)
    res = measure_stereo(sensor(rad[0], 2.0, rng), sensor(rad[1], 2.0, rng), rig)
    truths = S.truth_in_rig("plate")
    by_id = {t["id"]: t for t in truths}
    P1 = camera_matrices(rig)[0]
    rims = 0
    for f in res.features:
        lab = S.label_image_feature(res.left.features[f.left].ideal.xy, truths, P1)
        if f.kind == "line" or lab is None or not by_id[lab]["visible_both"]:
            continue
        e = f.center - by_id[lab]["center"]
        assert e @ np.linalg.solve(f.covariance, e) < 16.27, (lab, f.kind, e)  # chi2(3) at 99.9 %
        rims += 1
    assert rims >= 1  # the 10 mm hole (circle-8); the others fade or are seen only through their hole


def test_rims_under_a_flat_shading_are_not_taken_as_exact():
    """A noiseless plate lit from the side (one of bench_stereo's 12 lights):
    the rims' shading bounds are near zero, the 8-bit rounding is the only
    noise, and without the Type B floor (``EDGE_BIAS_FLOOR``) the 4 mm hole's
    radius came out 8 u off (centre chi-square 68) and the 6 mm hole's centre
    at chi-square 23: the fit took its points as exact. With the floor
    alone the 4 mm hole's radius still read 2.9 u; the curvature
    correction's remainder, one mode of the whole rim, states it (0.9 u)."""
    from partinspect.simulate.render import render_pair
    from partinspect.cad.raycast import Shading

    p = S.part("plate")
    rig = p.rig(False, S.SIZE)
    pose = p.pose(rig)
    (L, R), _ = render_pair(p.scene, rig, pose, noise=0.0, shading=Shading(light=(0.436, -0.407, -0.802)))
    res = measure_stereo(L, R, rig)
    truths = S.truth_in_rig("plate")
    by_id = {t["id"]: t for t in truths}
    P1, _ = camera_matrices(rig)
    checked = 0
    for f in res.features:
        lab = S.label_image_feature(res.left.features[f.left].ideal.xy, truths, P1)
        if f.kind != "circle" or lab is None or not by_id[lab]["visible_both"]:
            continue
        t = by_id[lab]
        e = f.center - t["center"]
        assert e @ np.linalg.solve(f.covariance, e) < 16.27, (lab, e)  # chi2(3) at 99.9 %
        assert abs(f.radius - t["radius"]) < 2.0 * f.radius_std, (lab, f.radius - t["radius"], f.radius_std)
        checked += 1
    assert checked >= 4


def test_arcs_of_two_different_holes_are_not_one_circle():
    """The likelihood-ratio test of a matched pair of arcs: the left rim of the
    12 mm hole with the right rim of the 10 mm hole beside it (a mismatch seen
    under one of bench_stereo's lights) fails it by far; the true pairs pass."""
    from partinspect.vision.fit3d import circle_consistency
    from partinspect.vision.stereo import MISMATCH_P, feature_views, fit_feature, measure_images

    rig, pose, L, R = S.render("plate", 2.0, 0)
    truths = S.truth_in_rig("plate")
    P1, P2 = camera_matrices(rig)
    Lr, Rr = measure_images(L, rig.K1, rig.D1), measure_images(R, rig.K2, rig.D2)

    def arc(res, P, cid):
        return next(f for f in res.features if f.kind == "arc" and S.label_image_feature(f.ideal.xy, truths, P) == cid)

    def p_value(fl, fr):
        views = feature_views(fl, fr, Lr.edges.sigma, rig)
        # Start from the left rim's true circle: the fit's start is not what is tested.
        t = next(t for t in truths if t["id"] == "circle-4")
        th = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        e1 = np.cross(t["normal"], [1.0, 0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(t["normal"], e1)
        pts = t["center"] + t["radius"] * (np.outer(np.cos(th), e1) + np.outer(np.sin(th), e2))
        fit = fit_feature(fl, fr, views, pts, epipolar_geometry(rig))
        return circle_consistency(views, fit, (fl.fit.params, fr.fit.params))[1]

    assert p_value(arc(Lr, P1, "circle-4"), arc(Rr, P2, "circle-4")) > 1e-3
    assert p_value(arc(Lr, P1, "circle-4"), arc(Rr, P2, "circle-8")) < MISMATCH_P


def first_difference(a, b, path="result"):
    """Where two results differ, bit for bit (arrays by their bytes, floats by theirs), or None."""
    if type(a) is not type(b):
        return f"{path}: {type(a).__name__} vs {type(b).__name__}"
    if isinstance(a, np.ndarray):
        if a.dtype == object:
            return first_difference(list(a.ravel()), list(b.ravel()), path) if a.shape == b.shape else path
        same = a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
        return None if same else path
    if isinstance(a, float):
        return None if struct.pack("d", a) == struct.pack("d", b) else f"{path}: {a!r} vs {b!r}"
    if dataclasses.is_dataclass(a):
        pairs = [(f.name, getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)]
    elif isinstance(a, (list, tuple)):
        if len(a) != len(b):
            return f"{path}: {len(a)} vs {len(b)} items"
        pairs = [(f"[{i}]", x, y) for i, (x, y) in enumerate(zip(a, b))]
    elif isinstance(a, dict):
        if a.keys() != b.keys():
            return f"{path}: keys"
        pairs = [(f"[{k!r}]", a[k], b[k]) for k in a]
    elif hasattr(a, "__dict__"):
        return first_difference(vars(a), vars(b), path)
    else:
        return None if a == b else f"{path}: {a!r} vs {b!r}"
    for name, x, y in pairs:
        d = first_difference(x, y, f"{path}.{name}" if not name.startswith("[") else path + name)
        if d:
            return d
    return None


@pytest.mark.skipif(not can_fork(), reason="no os.fork or fewer than 2 CPUs: both paths are serial")
def test_parallel_and_serial_results_are_identical(monkeypatch):
    # The right image measured in a forked child, and that child kept for
    # its share of the 3D fits (one fork a pair): the same bits as measured
    # here, the edges, segments and features of both images and everything
    # built on them.
    rig, pose, L, R = S.render("plate", 2.0, 0, True)
    serial = measure_stereo(L, R, rig, parallel=False)
    fork, forks = os.fork, []
    monkeypatch.setattr(os, "fork", lambda: forks.append(1) or fork())
    parallel = measure_stereo(L, R, rig, parallel=True)
    assert len(forks) == 1
    assert len(parallel.right.segments) > 10 and len(parallel.features) >= 15
    assert first_difference(serial, parallel) is None, first_difference(serial, parallel)


@pytest.mark.parametrize("parallel", [False, True])
@pytest.mark.parametrize("side", ["left", "right"])
def test_an_exception_in_either_images_chain_is_raised_as_it_is(parallel, side):
    # A saturated image has no pixels to estimate the noise from: the same
    # ValueError whether that image was measured here or in the child.
    rig, pose, L, R = S.render("plate", 2.0, 0)
    white = np.full_like(L, 255)
    L, R = (white, R) if side == "left" else (L, white)
    with pytest.raises(ValueError, match="no unsaturated pixels"):
        measure_stereo(L, R, rig, parallel=parallel)


def _tip_arc(bump):
    """A flat ellipse's arc round its tip (ideal px), with 13 points just past the tip off the rim.

    Their offsets are those the stress run's ftc_09 rim showed there (up
    to 1.16 px, rising over 6 points and falling over 7), scaled by
    ``bump``.

    Returns the right ImageFeature, its View and the true ellipse's parameters.
    """
    from partinspect.vision.fit3d import View
    from partinspect.vision.fitting import fit_ellipse
    from partinspect.vision.ideal import IdealPoints
    from partinspect.vision.imagefeatures import ImageFeature

    true = np.array([100.0, 80.0, 30.0, 6.5, 0.46])
    xc, yc, a, b, th = true
    c, s = np.cos(th), np.sin(th)
    # One point per pixel of arc length from t = -2.4 to 2.4 rad, the tip at t = 0.
    tt = np.linspace(-2.4, 2.4, 4000)
    loc = np.c_[a * np.cos(tt), b * np.sin(tt)]
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(loc, axis=0), axis=1))]
    t = np.interp(np.arange(0.0, arc[-1], 1.0), arc, tt)
    xy = np.c_[xc + a * np.cos(t) * c - b * np.sin(t) * s, yc + a * np.cos(t) * s + b * np.sin(t) * c]
    nl = np.c_[np.cos(t) / a, np.sin(t) / b]  # outward normal in the ellipse's frame
    n = np.c_[nl[:, 0] * c - nl[:, 1] * s, nl[:, 0] * s + nl[:, 1] * c]
    n /= np.linalg.norm(n, axis=1)[:, None]
    profile = np.array([0.05, 0.09, 0.14, 0.19, 0.30, 0.53, 1.16, 0.78, 0.52, 0.35, 0.28, 0.22, 0.17])
    first = int(np.argmin(np.abs(t)))
    off = np.zeros(len(t))
    off[first:first + len(profile)] = bump * profile
    xy = xy + off[:, None] * n
    sigma = np.full(len(t), 0.015)
    bias = 0.03 + 0.10 * np.exp(-(t / 0.15) ** 2)  # the Type B bound grows where the rim fades
    along = np.c_[-n[:, 1], n[:, 0]]
    cov = (sigma ** 2)[:, None, None] * n[:, :, None] * n[:, None, :] + 1e-4 * along[:, :, None] * along[:, None, :]
    ideal = IdealPoints(xy, cov, n, sigma, np.repeat(np.eye(2)[None], len(t), axis=0))
    fit = fit_ellipse(xy, cov, corr_length=1.0, start=true)
    f = ImageFeature("arc", (0,), np.arange(len(t)), xy, cov, ideal, fit, 1.2, 1)
    view = View(xy, sigma, np.eye(3, 4), 1.0, bias, 10.0)
    return f, view, true


def _max_distance(params, true):
    """Largest distance (px) of the ellipse ``params`` from the ellipse ``true`` along the latter."""
    def pts(p, t):
        xc, yc, a, b, th = p
        return np.c_[xc + a * np.cos(t) * np.cos(th) - b * np.sin(t) * np.sin(th),
                     yc + a * np.cos(t) * np.sin(th) + b * np.sin(t) * np.cos(th)]
    ref, other = pts(true, np.linspace(-2.4, 2.4, 500)), pts(params, np.linspace(0, 2 * np.pi, 20000))
    return float(np.sqrt(((ref[:, None] - other[None]) ** 2).sum(-1).min(1)).max())


def test_the_partner_ellipse_leaves_out_points_beyond_their_whole_uncertainty():
    from partinspect.vision.arc_partner import as_fitted

    f, view, true = _tip_arc(1.0)
    bent = _max_distance(f.fit.params, true)
    got = as_fitted(f, view, 1.0)
    # The image fit takes the tip in and bends (as the stress run's ftc_09
    # rim did, by tenths of a pixel); the partner ellipse judged by the
    # points' whole uncertainty leaves the worst out and stays on the rim.
    assert bent > 0.25
    assert _max_distance(got.fit.params, true) < 0.1
    assert len(got.fit.residuals) < len(f.ideal.xy)
    assert len(got.ideal.xy) == len(f.ideal.xy)  # the edge is still seen there


def test_the_partner_ellipse_of_a_clean_arc_keeps_every_point():
    from partinspect.vision.fitting import fit_ellipse
    from partinspect.vision.arc_partner import as_fitted

    f, view, true = _tip_arc(0.0)
    rng = np.random.default_rng(3)
    xy = view.xy + rng.normal(0.0, 0.015, len(view.xy))[:, None] * f.ideal.normal
    view = replace(view, xy=xy)
    got = as_fitted(f, view, 1.0)
    # Weighted by each point's whole uncertainty, as the 3D fit weighs it.
    plain = fit_ellipse(xy, view.total_sigma ** 2, corr_length=1.0, start=f.fit.params)
    assert len(got.fit.residuals) == len(xy)
    assert np.array_equal(got.fit.params, plain.params)
