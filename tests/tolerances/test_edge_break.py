"""Sizes measured on broken rims: the wall's size, with the break's Type B."""

import dataclasses

import numpy as np
import pytest

from partinspect.cad.registration import register
from partinspect.simulate.measured import measure_features
from partinspect.tolerances.edge_break import band_offset, size_on_broken_rim
from partinspect.tolerances.evaluate import evaluate
from partinspect.tolerances.resolve import characteristics_for
from partinspect.tolerances.spec import parse_spec


@pytest.mark.parametrize("b_min,b_max", [(0.0, 0.1), (0.1, 0.1), (0.05, 0.3)])
def test_band_offset_is_the_mean_and_spread_of_s_times_b(b_min, b_max):
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, 400_000) * rng.uniform(b_min, b_max, 400_000)
    mean, std = band_offset(b_min, b_max)
    assert mean == pytest.approx(x.mean(), rel=0.01)
    assert std == pytest.approx(x.std(), rel=0.01)


def test_a_hole_is_smaller_than_its_rim_and_a_boss_larger():
    hole = size_on_broken_rim(5.05, 0.001, False, 0.1, 0.1)
    boss = size_on_broken_rim(4.95, 0.001, True, 0.1, 0.1)
    unknown = size_on_broken_rim(5.0, 0.001, None, 0.1, 0.1)
    assert hole[0] == pytest.approx(5.0) and boss[0] == pytest.approx(5.0) and unknown[0] == 5.0
    assert hole[3] == pytest.approx(0.1 / np.sqrt(12))
    assert unknown[3] == pytest.approx(0.1 / np.sqrt(3))  # RMS of s b about zero


def test_spec_break_reaches_rim_sizes_and_circularity_and_a_feature_overrides_it(plate):
    inv = plate[0]
    spec = parse_spec("edge_break: 0.1\nfeatures:\n  circle-4:\n    edge_break: {min: 0.2, max: 0.3}\n"
                      "    diameter: {upper: 0.05, lower: 0}\n", "part.tol.yaml")
    chars = {c.id: c for c in characteristics_for(spec, inv)}
    assert chars["circle-4.diameter"].edge_break == (0.2, 0.3)
    assert chars["circle-2.diameter"].edge_break == (0.0, 0.1)
    assert chars["circle-2.circularity"].edge_break == (0.0, 0.1)
    assert all(c.edge_break is None for c in chars.values() if c.type == "straightness")
    assert chars["circle-4.diameter"].to_dict()["edge_break"] == {"min": 0.2, "max": 0.3}
    sharp = {c.id: c for c in characteristics_for(parse_spec("units: mm\n", "p.tol.yaml"), inv)}
    assert sharp["circle-2.diameter"].edge_break is None


def test_diameters_on_broken_rims_cover_the_wall(plate):
    # Rims seen anywhere across a 0.1 mm break: the rim's radius is the
    # wall's plus s * 0.1 (s uniform). Stated without the break, the
    # diameter is off by up to 0.2 mm at micrometre uncertainty; with it,
    # the wall's diameter within +-U as the coverage claims.
    inv, T, ids = plate
    spec = parse_spec("edge_break: {min: 0.1, max: 0.1}\n", "part.tol.yaml")
    chars = [c for c in characteristics_for(spec, inv) if c.type == "diameter" and c.features[0] in ids]
    rng = np.random.default_rng(5)
    z, z_sharp = [], []
    for draw in range(15):
        m = measure_features(inv, T, ids, rng)
        s = rng.uniform(0, 1, len(m.circles))
        circles = tuple(dataclasses.replace(c, radius=c.radius + si * 0.1) for c, si in zip(m.circles, s))
        reg = register(circles, m.lines, inv, pose_hint=T)
        for e in evaluate(chars, reg, inv, seed=draw, n_mc=200):
            z.append((e.measured - e.characteristic.nominal) / e.standard_uncertainty)
            rim = e.details["edge_break"]["rim"]
            z_sharp.append((rim - e.characteristic.nominal) / (e.standard_uncertainty ** 2 - e.details["edge_break"]["standard_uncertainty"] ** 2) ** 0.5)
            assert "hole" in e.details["edge_break"]["measured_as"]
    z = np.asarray(z)
    assert 0.75 < np.sqrt(np.mean(z * z)) < 1.25
    assert np.mean(np.abs(z) <= 2) > 0.9
    assert np.sqrt(np.mean(np.square(z_sharp))) > 10


def test_apparent_edge_rms_is_the_chamfer_points_rms_distance_from_the_sharp_edge():
    from partinspect.tolerances.edge_break import apparent_edge_rms

    rng = np.random.default_rng(2)
    s, b = rng.uniform(0, 1, 200_000), rng.uniform(0.05, 0.2, 200_000)
    # Points across a 90-degree chamfer: b ((1 - s) u1 + s u2), u1 = x, u2 = y.
    d2 = (b * (1 - s)) ** 2 + (b * s) ** 2
    assert apparent_edge_rms(0.05, 0.2) == pytest.approx(np.sqrt(d2.mean()), rel=0.01)


def test_the_band_is_carried_in_pixels_at_each_cameras_depth_and_left_out_of_the_form():
    from partinspect.vision.fit3d import View
    from partinspect.vision.matching import epipolar_geometry
    from partinspect.vision.band_modes import edge_band
    from partinspect.vision.stereo import _without_band
    from partinspect.simulate.rig import default_rig

    rig = default_rig((2448, 2048))
    geo = epipolar_geometry(rig)
    X = np.array([[0.0, 0.0, 400.0], [10.0, 0.0, 400.0]])
    band = edge_band(X, geo, 0.1)
    left, right = band.left, band.right
    z_right = float(np.median(X @ np.asarray(geo.R)[2] + np.asarray(geo.T).ravel()[2]))
    assert left == pytest.approx(0.1 * rig.K1[0, 0] / 400.0)
    assert right == pytest.approx(0.1 * rig.K2[0, 0] / z_right)
    # The share the cameras see differently: the angle between their lines
    # of sight to the feature over the band normal's quarter turn.
    eye = -np.asarray(geo.R).T @ np.asarray(geo.T).ravel()
    c = np.median(X, axis=0)
    angle = np.arccos(c @ (c - eye) / np.linalg.norm(c) / np.linalg.norm(c - eye))
    assert band.parallax == pytest.approx(angle / (np.pi / 2)) and 0.05 < band.parallax < 0.5
    line = View(np.zeros((3, 2)), np.full(3, 0.01), np.eye(3, 4), 1.0, np.full(3, left))
    assert _without_band(line, band, "line").bias is None
    # A rim carries its band as modes (band_harmonics): the form's view drops
    # them and keeps every other mode and its shading Type B.
    modes = np.arange(18.0).reshape(6, 3)
    names = (("curvature", 1), ("band", 2, 0), ("band", 2, 1), ("band", 2, 0, 0), ("band", 2, 0, 1), "place")
    rim = View(np.zeros((3, 2)), np.full(3, 0.01), np.eye(3, 4), 1.0, np.array([0.02, 0.03, 0.04]), 5.0,
               modes=modes, mode_names=names)
    kept = _without_band(rim, band, "arc")
    np.testing.assert_allclose(kept.bias, [0.02, 0.03, 0.04])
    assert kept.mode_names == (("curvature", 1), "place")
    np.testing.assert_allclose(kept.modes, modes[[0, 5]])


@pytest.mark.parametrize("place", [(0.3, 0.05), (0.8, 0.2)])
def test_band_offset_with_a_predicted_place_is_the_mean_and_spread_of_s_times_b(place):
    rng = np.random.default_rng(2)
    x = rng.normal(place[0], place[1], 400_000) * rng.uniform(0.05, 0.15, 400_000)
    mean, std = band_offset(0.05, 0.15, place)
    assert mean == pytest.approx(x.mean(), rel=0.01)
    assert std == pytest.approx(x.std(), rel=0.01)


def test_a_predicted_band_place_reaches_the_size_and_its_bonus_and_narrows_it(plate):
    from types import SimpleNamespace

    from partinspect.tolerances.edge_break import broken_rims, with_band_places

    inv, T, ids = plate
    spec = parse_spec("edge_break: {min: 0.1, max: 0.1}\nfeatures:\n  circle-4:\n"
                      "    position: {tolerance: 0.05, material: MMC}\n", "part.tol.yaml")
    chars = characteristics_for(spec, inv)
    rims = broken_rims(chars, inv, T)
    # The top rims (seen from their face) are predicted; the bottom rims, seen through their holes, are not.
    assert {"circle-2", "circle-4", "circle-8"} <= set(rims) and "circle-3" not in rims
    center, normal, radius, hole, size = rims["circle-4"]
    assert hole and radius == pytest.approx(6.0) and size == pytest.approx(0.1) and normal @ [0, 0, 1] > 0.99
    placed = {c.id: c for c in with_band_places(chars, {"circle-4": SimpleNamespace(s=0.3, u=0.05)})}
    assert placed["circle-4.diameter"].band_place == (0.3, 0.05)
    assert placed["circle-4.position"].material.size.band_place == (0.3, 0.05)
    assert placed["circle-2.diameter"].band_place is None
    rng = np.random.default_rng(3)
    m = measure_features(inv, T, ids, rng)
    circles = tuple(dataclasses.replace(c, radius=c.radius + 0.3 * 0.1) for c in m.circles)  # every rim at s = 0.3
    reg = register(circles, m.lines, inv, pose_hint=T)
    uniform, predicted = (
        {e.characteristic.id: e for e in evaluate(cs, reg, inv, n_mc=200)}["circle-4.diameter"]
        for cs in ([c for c in chars if c.id == "circle-4.diameter"], [placed["circle-4.diameter"]]))
    assert abs(predicted.measured - 12.0) < 3 * predicted.standard_uncertainty
    assert abs(uniform.measured - 12.0) > 0.03  # the uniform band's mean, s = 0.5, is 0.04 mm off here
    assert predicted.details["edge_break"]["standard_uncertainty"] < 0.3 * uniform.details["edge_break"]["standard_uncertainty"]
    assert predicted.details["edge_break"]["band_place"] == "predicted from the light on the part"


def test_a_rim_whose_wall_the_step_file_splits_in_two_is_still_a_broken_rim():
    from types import SimpleNamespace as NS

    from partinspect.tolerances.edge_break import broken_rims

    # NIST ftc_09's holes: each wall two half cylinders (faces of one material side) and the top plane.
    inv = {"circle-1": NS(center=[0.0, 0.0, 0.0], radius=3.175, faces=("face-1", "face-2", "face-3")),
           "face-1": NS(surface="cylinder", convex=False), "face-2": NS(surface="cylinder", convex=False),
           "face-3": NS(surface="plane", normal=[0.0, 0.0, 1.0], convex=None)}
    c = NS(type="diameter", features=("circle-1",), edge_break=(0.1, 0.1), material=None)
    above = np.eye(4)
    above[:3, :3] = np.diag([1.0, -1.0, -1.0])  # the camera looks down -z at the part's +z face
    above[2, 3] = 300.0
    rims = broken_rims([c], inv, above)
    assert set(rims) == {"circle-1"} and rims["circle-1"][3] is True  # a hole
    inv["face-2"] = NS(surface="cylinder", convex=True)  # a wall of two material sides: not one rim
    assert broken_rims([c], inv, above) == {}


def test_only_external_straight_edges_between_planes_are_broken_lines():
    import cadquery as cq

    from partinspect.cad.features import inventory
    from partinspect.cad.mesh import tessellate
    from partinspect.tolerances.edge_break import broken_lines

    # An L-shaped block, a hole notching one corner: a step cut out of another leaves one internal
    # (concave) edge, along y at x = 5, z = 5; the notch's straight edges bound a cylinder.
    shape = cq.Workplane("XY").box(10, 10, 10, centered=False).cut(
        cq.Workplane("XY").box(5, 10, 5, centered=False).translate((5, 0, 5))).faces("<Z").workplane().hole(2).val()
    inv = inventory(shape)
    lines = broken_lines(inv, tessellate(shape, inventory=inv), [f.id for f in inv.features], 0.1, 0.3)
    all_lines = [f for f in inv.features if f.kind == "line"]
    internal = [f.id for f in all_lines if np.allclose(f.start[[0, 2]], 5.0) and np.allclose(f.end[[0, 2]], 5.0)]
    assert len(internal) == 1 and internal[0] not in lines
    planar = {f.id for f in all_lines if all(inv[x].surface == "plane" for x in f.faces)}
    assert len(planar) == len(all_lines) - 2
    assert set(lines) == planar - set(internal)
    for start, end, faces, (n1, n2), (t1, t2), size in lines.values():
        # the inward directions lie in their faces, across the edge, each turned from the other face
        e = end - start
        assert abs(t1 @ e) < 1e-9 and abs(t1 @ n1) < 1e-9 and t1 @ n2 < 0
        assert abs(t2 @ e) < 1e-9 and abs(t2 @ n2) < 1e-9 and t2 @ n1 < 0
        assert size == pytest.approx(0.2)
