"""Ideal-pixel mapping and triangulated correspondences with their covariances."""

import numpy as np

from partinspect.simulate.rig import default_rig
from partinspect.vision.calibration import project_points
from partinspect.vision.correspondences import correspond
from partinspect.vision.ideal import ideal_points, to_ideal
from partinspect.vision.matching import epipolar_geometry
from tests.vision.test_matching import P1, P2, RIG, circle, feature, segment


def test_ideal_covariance_is_the_first_order_image():
    rig = default_rig((1224, 1024), distortion=True)
    X = np.array([[40.0, -30, 400], [0, 0, 400], [-45, 35, 380]])
    uv = project_points(X, rig.K1, rig.D1)
    cov = np.array([[[0.04, 0.01], [0.01, 0.02]]] * 3)
    ip = ideal_points(uv, cov, rig.K1, rig.D1)
    # Ideal pixels are the pinhole projection.
    pin = X[:, :2] / X[:, 2:] * rig.K1[0, 0] + rig.K1[:2, 2]
    assert np.abs(ip.xy - pin).max() < 1e-6
    # Jacobian against central differences.
    h = 1e-3
    for k in range(2):
        d = np.zeros(2)
        d[k] = h
        num = (to_ideal(uv + d, rig.K1, rig.D1) - to_ideal(uv - d, rig.K1, rig.D1)) / (2 * h)
        assert np.abs(num - ip.jacobian[:, :, k]).max() < 1e-6
    assert not np.allclose(ip.cov, cov)  # the corners are distorted by several px


def test_noiseless_correspondences_lie_on_the_3d_curves():
    geo = epipolar_geometry(RIG)
    C = circle([15, 5, 395], [0.2, -0.5, -0.8], 5.0)
    Lx = segment([-20, -15, 400], [-5, 15, 405])
    for kind, X in (("arc", C), ("line", Lx)):
        c = correspond(feature(kind, X, P1), feature(kind, X, P2), geo)
        assert len(c) > 0.7 * len(X)
        if kind == "line":
            d = np.linalg.norm(np.cross(c.points - X[0], X[-1] - X[0]), axis=1) / np.linalg.norm(X[-1] - X[0])
        else:
            n = np.array([0.2, -0.5, -0.8]) / np.linalg.norm([0.2, -0.5, -0.8])
            q = c.points - [15, 5, 395]
            d = np.hypot(q @ n, np.linalg.norm(q - np.outer(q @ n, n), axis=1) - 5.0)
        assert d.max() < 1e-4  # mm


def test_point_covariances_match_simulation_and_depth_dominates():
    rng = np.random.default_rng(3)
    geo = epipolar_geometry(RIG)
    X = circle([15, 5, 395], [0.2, -0.5, -0.8], 5.0, n=120)
    fl0, fr0 = feature("arc", X, P1), feature("arc", X, P2)
    c0 = correspond(fl0, fr0, geo)
    pts = []
    for _ in range(150):
        fl = feature("arc", X, P1)
        fr = feature("arc", X, P2)
        # Independent noise across the edge (the features were built noiseless).
        from partinspect.vision.fitting import fit_ellipse
        from dataclasses import replace

        nl = fl.ideal.normal * (0.05 * rng.standard_normal(len(X)))[:, None]
        nr = fr.ideal.normal * (0.05 * rng.standard_normal(len(X)))[:, None]
        fl = replace(fl, ideal=replace(fl.ideal, xy=fl.ideal.xy + nl))
        fr = replace(fr, fit=fit_ellipse(fr.ideal.xy + nr, fr.ideal.cov))
        c = correspond(fl, fr, geo)
        common = np.intersect1d(c.left_index, c0.left_index)
        pts.append(c.points[np.searchsorted(c.left_index, common)][:5])
    pts = np.array(pts)
    sd_mc = pts.std(axis=0)
    sd_fo = np.sqrt(np.einsum("nii->ni", c0.cov[:5]))
    assert np.all(np.abs(sd_mc / sd_fo - 1) < 0.3)
    assert np.all(sd_fo[:, 2] > sd_fo[:, 0]) and np.all(sd_fo[:, 2] > sd_fo[:, 1])


def test_arc_partners_only_where_the_right_image_sees_the_rim():
    """A rim seen whole on the left and half on the right: no partner on the right ellipse's extrapolation."""
    geo = epipolar_geometry(RIG)
    X = circle([15, 5, 395], [0.2, -0.5, -0.8], 5.0, n=200)
    fr = feature("arc", X[:100], P2)
    c = correspond(feature("arc", X, P1), fr, geo)
    d = np.min(np.linalg.norm(c.right[:, None] - fr.ideal.xy[None], axis=2), axis=1)
    assert d.max() <= 2.0
    assert 0.3 * len(X) < len(c) < 0.6 * len(X)


def test_a_point_off_the_rim_where_the_epipolar_line_touches_it_gets_no_partner():
    """A left rim point 1 px off its ellipse at the epipolar tangent point: its
    epipolar line then crosses the right ellipse twice at steeper angles, and
    the partner found there lies far along the rim. It is dropped, judged on
    the left ellipse; every 3D point kept lies on the circle."""
    from partinspect.vision.correspondences import _left_crossing_sin

    geo = epipolar_geometry(RIG)
    centre, normal, r = np.array([15.0, 5.0, 395.0]), np.array([0.2, -0.5, -0.8]), 5.0
    X = circle(centre, normal, r, n=400)
    fl, fr = feature("arc", X, P1), feature("arc", X, P2)
    x = fl.ideal.xy.copy()
    sin_l = _left_crossing_sin(geo, x, np.asarray(fl.fit.params))
    for k in np.argsort(sin_l)[:2]:  # the two tangent points, one on each side
        # Inward (outward, the epipolar line misses the right ellipse and
        # the point has no partner anyway): the partner found lies 10 px
        # along the right ellipse, where the line crosses it at 11 deg.
        inward = fl.fit.params[:2] - x[k]
        x[k] += 1.0 * inward / np.linalg.norm(inward)
    c = correspond(fl, fr, geo, xy=x)
    n = normal / np.linalg.norm(normal)
    q = c.points - centre
    d = np.hypot(q @ n, np.linalg.norm(q - np.outer(q @ n, n), axis=1) - r)
    assert len(c) > 0.6 * len(X)
    assert d.max() < 0.02, d.max()  # mm; a wrong partner puts the point tenths of a mm off
