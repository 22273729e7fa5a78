"""Step edges told from the crests of shading ramps (vision/ramps.py) and kept out of the matching."""

from dataclasses import fields

import numpy as np

from partinspect.vision.imagefeatures import ImageFeature
from partinspect.vision.matching import epipolar_geometry, match_features
from partinspect.vision.ramps import RAMP_SHARE, ramp_share
from partinspect.vision.stereo import EdgeFeature, measure_images
from tests.vision.synthetic import render_profile
from tests.vision.test_matching import P1, P2, RIG, feature, segment

K = np.array([[1000.0, 0.0, 120.0], [0.0, 1000.0, 80.0], [0.0, 0.0, 1.0]])
NORMAL = np.array([np.cos(0.3), np.sin(0.3)])


def _longest_feature(profile, noise=1.0, seed=0, blur=0.6):
    image = render_profile(profile, (120.0, 80.0), NORMAL, (240, 160), blur=blur)
    image = image + np.random.default_rng(seed).normal(0.0, noise, image.shape)
    result = measure_images(image, K, np.zeros(5))
    return max(result.features, key=len), result.edges, image


def test_a_step_is_not_a_ramp_and_a_shading_crest_is():
    # A step of 80 grey levels between uniform faces; the same step with its
    # bright face rising 4 grey levels / px over 12 px (a sixth of the peak
    # gradient); the step out of focus (a blur of 2 px, most of the way to
    # MAX_STEP_WIDTH); and a smooth change of 80 grey levels over about
    # 15 px whose gradient peaks at 8 grey levels / px, a ramp's crest.
    step = _longest_feature(lambda u: 60.0 + 80.0 * (u > 0))
    shaded = _longest_feature(lambda u: 60.0 + 80.0 * (u > 0) + 4.0 * np.clip(u, 0.0, 12.0))
    defocused = _longest_feature(lambda u: 60.0 + 80.0 * (u > 0), blur=2.0)
    crest = _longest_feature(lambda u: 100.0 + 40.0 * np.tanh(u / 5.0))
    for f, edges, _ in (step, shaded, defocused, crest):
        assert f.kind == "line" and len(f) > 90
    assert abs(step[0].ramp_share) < 0.05
    assert 0.0 <= shaded[0].ramp_share < 0.05  # its dark side is flat
    assert 0.05 < defocused[0].ramp_share < 0.2
    assert 0.45 < crest[0].ramp_share < 0.6
    assert 0.3 < RAMP_SHARE < 0.35
    # The share as ramp_share reads it from the points, peak and image.
    f, edges, image = crest
    assert ramp_share(image, edges.xy[f.index], edges.normal[f.index], edges.strength[f.index]) \
        == f.ramp_share
    assert np.isnan(ramp_share(image, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)))


def _with_share(f, share):
    return EdgeFeature(**{k.name: getattr(f, k.name) for k in fields(ImageFeature)}, ramp_share=share)


def test_a_ramps_crest_takes_part_in_no_pair():
    # One edge seen in both images pairs; the right image's feature marked as
    # a ramp's crest (it would pair: a line pair always triangulates) does
    # not, and both sides say why.
    X = segment([-20, -15, 400], [-5, 15, 405])
    left, right = feature("line", X, P1), feature("line", X, P2)
    geo = epipolar_geometry(RIG)
    m = match_features([_with_share(left, 0.02)], [_with_share(right, 0.3)], geo)
    assert [(x.left, x.right) for x in m.matches] == [(0, 0)]
    m = match_features([_with_share(left, 0.02)], [_with_share(right, 0.8)], geo)
    assert not m.matches
    reasons = {(u.side, u.feature): (u.reason, u.detail) for u in m.unmatched}
    assert reasons[("right", 0)] == ("ramp", "the grey-level slope on either side keeps 80 % of its peak gradient")
    assert reasons[("left", 0)][0] == "no_candidate"
