"""Epipolar matching of image features: synthetic features and a rendered part."""

import numpy as np
import pytest

from partinspect.simulate.rig import default_rig
from partinspect.vision.fitting import fit_ellipse, fit_line
from partinspect.vision.ideal import camera_matrices, ideal_points
from partinspect.vision.imagefeatures import ImageFeature
from partinspect.vision.matching import REASONS, epipolar_geometry, match_features
from tests.vision import stereo_scenes as S

RIG = default_rig((1224, 1024))
P1, P2 = camera_matrices(RIG)
SIGMA = 0.05


def project(P, X):
    x = np.c_[X, np.ones(len(X))] @ P.T
    return x[:, :2] / x[:, 2:]


def feature(kind, X, P, polarity_sign=1.0):
    """An ImageFeature of 3D points X seen by camera P (no distortion, no noise)."""
    uv = project(P, X)
    t = np.gradient(uv, axis=0)
    t /= np.linalg.norm(t, axis=1)[:, None]
    n = polarity_sign * np.c_[-t[:, 1], t[:, 0]]
    cov = SIGMA**2 * np.einsum("ni,nj->nij", n, n) + 1e-6 * np.einsum("ni,nj->nij", t, t)
    ideal = ideal_points(uv, cov, RIG.K1 if P is P1 else RIG.K2, np.zeros(5), n)
    fit = fit_line(uv, cov, corr_length=1.0) if kind == "line" else fit_ellipse(uv, cov, corr_length=1.0)
    pol = 0
    if kind == "arc":
        from partinspect.vision.fitting import ellipse_geometry

        _, nout, _ = ellipse_geometry(uv, fit.params, fit.phases)
        pol = 1 if np.mean(np.einsum("ni,ni->n", nout, n)) > 0 else -1
    return ImageFeature(kind, (0,), np.arange(len(uv)), uv, cov, ideal, fit, 1.2, pol)


def circle(center, normal, r, n=200):
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    ph = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.asarray(center) + r * (np.cos(ph)[:, None] * u + np.sin(ph)[:, None] * v)


def segment(a, b, n=200):
    s = np.linspace(0, 1, n)[:, None]
    return np.asarray(a) + s * (np.asarray(b) - np.asarray(a))


@pytest.fixture(scope="module")
def scene():
    """Two parallel slanted lines, a circle, and a line along the epipolar lines."""
    objs = [
        ("line", segment([-20, -15, 400], [-5, 15, 405])),
        ("line", segment([-12, -15, 402], [3, 15, 407])),
        ("arc", circle([15, 5, 395], [0.2, -0.5, -0.8], 5.0)),
        ("line", segment([-20, 25, 400], [20, 25, 402])),  # nearly horizontal: epipolar
    ]
    left = [feature(k, X, P1) for k, X in objs]
    right = [feature(k, X, P2) for k, X in objs]
    return left, right


def test_synthetic_pairs_found_and_degenerate_line_flagged(scene):
    left, right = scene
    m = match_features(left, right, epipolar_geometry(RIG))
    assert sorted((x.left, x.right) for x in m.matches) == [(0, 0), (1, 1), (2, 2)]
    deg = [u for u in m.unmatched if u.reason == "degenerate"]
    assert {(u.side, u.feature) for u in deg} == {("left", 3), ("right", 3)}
    assert all(u.epipolar_angle < np.deg2rad(8) for u in deg) and "deg" in deg[0].detail


def test_kind_mismatch_and_polarity_are_reported(scene):
    left, right = scene
    geo = epipolar_geometry(RIG)
    # The right circle removed and replaced by a line through the same band.
    X = circle([15, 5, 395], [0.2, -0.5, -0.8], 5.0)
    fake = feature("line", segment(X[np.argmin(X[:, 1])], X[np.argmax(X[:, 1])]), P2)
    m = match_features(left, [right[0], right[1], fake], geo)
    reasons = {(u.side, u.feature): u.reason for u in m.unmatched}
    assert reasons[("left", 2)] == "kind_mismatch"
    # The same lines with the opposite polarity in the right image cannot match.
    flipped = [feature("line", segment([-20, -15, 400], [-5, 15, 405]), P2, -1.0)]
    m = match_features(left[:1], flipped, geo)
    assert not m.matches and m.unmatched[0].reason == "shape_mismatch"


def test_radii_of_short_arcs_are_judged_against_what_their_fits_leave_uncertain():
    # The same hole's rim, its radius 12 % larger in the right image: whole
    # rims disagree beyond doubt, quarter rims (whose ellipses leave the
    # semi-major axis uncertain by about 6 % at this noise) do not; a
    # gross disagreement stays one, and so does 18 % on a rim so short that
    # its radius tells nothing (the widening stops at 20 %).
    geo = epipolar_geometry(RIG)
    centre, normal = [15, 5, 395], [0.2, -0.5, -0.8]

    def pair(r_right, n):
        return ([feature("arc", circle(centre, normal, 5.0, 240)[:n], P1)],
                [feature("arc", circle(centre, normal, r_right, 240)[:n], P2)])

    def rejected(m):
        return not m.matches and {u.reason for u in m.unmatched} == {"shape_mismatch"}

    assert rejected(match_features(*pair(5.6, 240), geo))
    left, right = pair(5.6, 60)
    assert 0.04 < np.sqrt(left[0].fit.cov[2, 2]) / left[0].fit.params[2] < 0.08
    short = match_features(left, right, geo)
    assert [(x.left, x.right) for x in short.matches] == [(0, 0)]
    assert short.matches[0].shape_cost < 1.0
    assert rejected(match_features(*pair(8.0, 60), geo))
    left, right = pair(5.9, 40)
    assert np.sqrt(left[0].fit.cov[2, 2]) / left[0].fit.params[2] > 0.2
    assert rejected(match_features(left, right, geo))


def test_every_feature_is_matched_or_explained(scene):
    left, right = scene
    m = match_features(left, right, epipolar_geometry(RIG))
    seen = {("left", x.left) for x in m.matches} | {("right", x.right) for x in m.matches}
    seen |= {(u.side, u.feature) for u in m.unmatched}
    assert seen == {(s, k) for s, n in (("left", len(left)), ("right", len(right))) for k in range(n)}
    assert all(u.reason in REASONS for u in m.unmatched)


def test_rendered_plate_matches_agree_with_truth():
    from partinspect.vision.stereo import measure_images

    rig, pose, L, R = S.render("plate", 2.0, 0)
    truths = S.truth_in_rig("plate")
    Lr = measure_images(L, rig.K1, rig.D1)
    Rr = measure_images(R, rig.K2, rig.D2)
    m = match_features(Lr.features, Rr.features, epipolar_geometry(rig))
    P1r, P2r = camera_matrices(rig)
    wrong = []
    for x in m.matches:
        a = S.label_image_feature(Lr.features[x.left].ideal.xy, truths, P1r)
        b = S.label_image_feature(Rr.features[x.right].ideal.xy, truths, P2r)
        if a is None or a != b:
            wrong.append((a, b))
    assert not wrong
    assert len(m.matches) >= 15
    # The five top-face holes are all matched.
    ids = {S.label_image_feature(Lr.features[x.left].ideal.xy, truths, P1r) for x in m.matches}
    assert {"circle-2", "circle-4", "circle-6", "circle-8", "circle-10"} <= ids
