import numpy as np
import pytest

from partinspect.vision.contours import chain_edges, segment_contours
from partinspect.vision.edges import edge_points
from tests.vision.synthetic import Disc, Slot, rectangle, render


def _segments(shapes, H, W, seed):
    ep = edge_points(render(shapes, H, W, noise=2.0, seed=seed), 1.0)
    cs = chain_edges(ep)
    return ep, cs, segment_contours(ep, cs)


def test_chaining_orders_a_closed_circle():
    ep, cs, _ = _segments([(Disc(100.3, 99.6, 50), 170.0)], 200, 200, 0)
    assert len(cs) == 1 and cs[0].closed and len(cs[0]) == len(ep)
    xy = ep.xy[cs[0].index]
    step = np.linalg.norm(np.diff(np.vstack([xy, xy[:1]]), axis=0), axis=1)
    assert step.max() < 2.25  # 8-neighbour pixels, offsets within half a pixel
    ang = np.unwrap(np.arctan2(xy[:, 1] - 99.6, xy[:, 0] - 100.3))
    assert np.all(np.diff(ang) > 0) or np.all(np.diff(ang) < 0)


def test_circle_gives_one_arc():
    for seed in range(3):
        ep, cs, segs = _segments([(Disc(100.3, 99.6, 50), 170.0)], 200, 200, seed)
        assert [s.kind for s in segs] == ["arc"]
        a, b = segs[0].fit.axes
        assert abs(a - 50) < 0.05 and abs(b - 50) < 0.05
        assert np.allclose(segs[0].fit.center, [100.3, 99.6], atol=0.05)


def test_square_gives_four_lines():
    for seed in range(3):
        _, _, segs = _segments([(rectangle(100.2, 99.7, 110, 110, 0.2), 170.0)], 200, 200, seed)
        assert [s.kind for s in segs] == ["line"] * 4
        normals = np.array([s.fit.normal for s in segs])
        cosines = np.abs(normals @ normals.T)
        assert np.all((cosines < 1e-2) | (cosines > 1 - 1e-4))


def test_rectangle_and_circle():
    for seed in range(3):
        _, _, segs = _segments([(rectangle(120.2, 99.7, 150, 90, -0.1), 170.0), (Disc(260, 110, 45), 180.0)],
                               220, 340, seed)
        kinds = [s.kind for s in segs]
        assert kinds.count("line") == 4 and kinds.count("arc") == 1
        arc = segs[kinds.index("arc")].fit
        assert np.allclose(arc.center, [260, 110], atol=0.05) and np.all(np.abs(arc.axes - 45) < 0.05)
        for s in segs:
            # The corners' points are left out of the line fits.
            assert len(s.fit_index) < len(s.index) or s.kind == "arc"


def test_contours_segmented_together_as_one_by_one():
    # segment_contours runs the contours' split and merge side by side and
    # their trial fits together; each contour must come out as
    # segment_contour makes it alone.
    from partinspect.vision.contours import segment_contour

    shapes = [(rectangle(120.2, 99.7, 150, 90, -0.1), 170.0), (Disc(260, 110, 45), 180.0),
              (Disc(90, 170, 22), 60.0), (rectangle(250, 180, 60, 25, 0.5), 200.0)]
    for seed in range(2):
        ep, cs, segs = _segments(shapes, 220, 340, seed)
        alone = [s for k, c in enumerate(cs) if len(c) >= 10 for s in segment_contour(ep, c, contour_id=k)]
        assert len(cs) >= 4 and len(segs) == len(alone)
        for a, b in zip(alone, segs):
            assert a.kind == b.kind and a.contour == b.contour
            assert np.array_equal(a.index, b.index) and np.array_equal(a.fit_index, b.fit_index)
            assert np.allclose(a.fit.params, b.fit.params, rtol=0, atol=1e-7)
    # The options reach every contour, and unknown ones are refused.
    loose = segment_contours(ep, cs, alpha=1e-6, refit=False)
    assert [s.kind for s in loose] == [s.kind for k, c in enumerate(cs) if len(c) >= 10
                                       for s in segment_contour(ep, c, contour_id=k, alpha=1e-6, refit=False)]
    with pytest.raises(TypeError):
        segment_contours(ep, cs, contour_id=3)


def test_line_ends_beside_a_junction_keep_clear_of_the_other_edge():
    """The plate's short edge line-16 ends (left image) where line-17 turns away from it and
    line-13 comes in 32 deg from it on a contour of its own; the arc-length trim at its end
    left points 2.3 px from line-13, which the smoothing had pulled 4-5 standard uncertainties
    off the true edge, and they alone set the edge's straightness. Those points are left out:
    over eight noise draws the two points nearest the junction lie on the true edge within the
    noise."""
    from partinspect.simulate.render import render_radiance_pair
    from partinspect.simulate.render import sensor
    from partinspect.vision.ideal import camera_matrices
    from partinspect.vision.stereo import measure_images
    from tests.vision import stereo_scenes as S
    from tests.vision.stereo_scenes import project

    p = S.part("plate")
    rig = p.rig(False, S.SIZE)
    pose = p.pose(rig)
    left, _ = render_radiance_pair(p.scene, rig, pose)
    truths = S.truth_in_rig("plate")
    line = next(t for t in truths if t["id"] == "line-16")
    P1, _ = camera_matrices(rig)
    a, b = project(P1, np.array([line["start"], line["end"]]))
    d = (b - a) / np.linalg.norm(b - a)
    n = np.array([-d[1], d[0]])
    # The junction with line-13 is the end at b.
    assert any(np.linalg.norm(project(P1, np.array([t["end"]])) - b) < 1 for t in truths if t["id"] == "line-13")
    rng = np.random.default_rng(5)
    z_end = []
    for _ in range(8):
        res = measure_images(sensor(left, 2.0, rng), rig.K1, rig.D1)
        f = next(f for f in res.features
                 if f.kind == "line" and S.label_image_feature(f.ideal.xy, truths, P1) == "line-16")
        xy, cov = f.ideal.xy, f.ideal.cov
        z = ((xy - a) @ n) / np.sqrt(np.einsum("i,nij,j->n", n, cov, n))
        z_end.append(z[np.argsort((xy - a) @ d)[-2:]])
    # Before the change: -2.7 (points to -5.1); now -0.45. Correlated along the edge, the
    # two points count as about one: the noise alone puts the mean of 8 within +-0.7 (2 sd).
    assert abs(np.mean(z_end)) < 1.5, np.round(z_end, 1)


def _short_side(length, turn):
    """A silhouette whose side from a to b (``length`` px) meets its two neighbours at ``turn`` deg."""
    from tests.vision.synthetic import Polygon

    a = np.array([150.0, 100.0])
    d = np.array([0.3, 1.0]) / np.hypot(0.3, 1.0)
    b = a + length * d

    def turned(t):
        t = np.deg2rad(t)
        return np.array([np.cos(t) * d[0] - np.sin(t) * d[1], np.sin(t) * d[0] + np.cos(t) * d[1]])

    return Polygon((tuple(a - 80 * turned(-turn)), tuple(a), tuple(b), tuple(b + 80 * turned(turn)))), a, d


def test_a_short_line_between_two_corners_keeps_clear_of_them():
    """The split at a corner can fall past it: the short side's piece then ends with the corner's
    rounded points, which the end trim kept out of its fit but which, being its own, did not keep
    its fitted points clear of the corner. Its last fitted points lay up to 8 standard uncertainties
    off the true side (14 px sides, corners of 40 and 60 deg; the plate's 4 mm edge line-19 read
    straightness 2 to 7 u above its true 0). Now every fitted point lies on the side within the
    noise, or the side is too short to be fitted clear of its corners; 20 px sides still are."""
    measured = {14: 0, 20: 0}
    for length in (14, 20):
        for turn in (40, 60):
            shape, a, d = _short_side(length, turn)
            n = np.array([-d[1], d[0]])
            for seed in range(6):
                ep = edge_points(render([(shape, 170.0)], 220, 260, noise=2.0, seed=seed), 1.0)
                for seg in segment_contours(ep, chain_edges(ep)):
                    xy = ep.xy[seg.fit_index]
                    t, e = (xy - a) @ d, (xy - a) @ n
                    if seg.kind != "line" or np.any(np.abs(e) > 1) or np.any((t < -1) | (t > length + 1)):
                        continue
                    z = e / np.sqrt(np.einsum("i,nij,j->n", n, ep.cov[seg.fit_index], n))
                    assert np.abs(z).max() < 4.0, (length, turn, seed, np.round(z, 1))
                    measured[length] += 1
    assert measured[20] == 12, measured


def test_arcs_tangent_to_lines_reach_their_junctions():
    # A slot: two half-circles of 30 px, each tangent to the two straight
    # sides. Where the splits fell, a side ran on into the arc untested (its
    # trimmed end) and the arc lost that and its own trim again: 138-157 deg
    # of the 180 fitted on seeds 0-3 without the breaks' adjustment. With the
    # breaks at the junctions the arcs lose their trim (4 px, 7.6 deg) at
    # each end and about a point more: 156-164 deg. The planner predicts
    # its arcs with that trim (DetectorModel.arc_trim): 164.7 deg here.
    from partinspect.planning.edge_model import DetectorModel

    expected = 180.0 - 2.0 * np.degrees(DetectorModel().arc_trim / 30.0)
    slot = Slot(80.3, 90.2, 160.1, 118.7, 30.0)
    centres = np.array([[slot.x0, slot.y0], [slot.x1, slot.y1]])
    for seed in range(4):
        ep, _, segs = _segments([(slot, 170.0)], 200, 240, seed)
        assert sorted(s.kind for s in segs) == ["arc", "arc", "line", "line"]
        for s in segs:
            if s.kind != "arc":
                continue
            xy = ep.xy[s.fit_index]
            c = centres[np.argmin([np.median(np.abs(np.linalg.norm(xy - c, axis=1) - 30.0)) for c in centres])]
            extent = np.degrees(np.ptp(np.unwrap(np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0]))))
            assert expected - 10.0 < extent < expected + 3.0, (seed, extent)
            assert abs(s.fit.params[2] - 30.0) < 0.15 and abs(s.fit.params[3] - 30.0) < 0.15


def _rendered_arcs(part, seed, fids):
    """Per image of a rendered pair (left, right): the 2D chain's result and, per id in ``fids``,
    its arc features labelled with that id."""
    from partinspect.vision.ideal import camera_matrices
    from partinspect.vision.stereo import measure_images
    from tests.vision import stereo_scenes as S

    truths = {t["id"]: [t] for t in S.truth_in_rig(part) if t["id"] in fids}
    rig, _, left, right = S.render(part, 2.0, seed)
    out = []
    for image, K, D, P in zip((left, right), (rig.K1, rig.K2), (rig.D1, rig.D2), camera_matrices(rig)):
        res = measure_images(image, K, D)
        out.append((res, {fid: [f for f in res.features
                                if f.kind == "arc" and S.label_image_feature(f.ideal.xy, truth, P) == fid]
                          for fid, truth in truths.items()}))
    return out


def test_a_rim_beside_its_shaded_wall_stays_whole():
    # The plate's 4 mm hole (18 px across at this size): the shading of its
    # inner wall displaces some rim points beyond their noise, so the whole
    # rim failed its test and was split, and each split cost two trims of
    # points: a gap of 34-39 deg in all four images of seeds 0 and 1 (and
    # of 35-70 deg in those of seeds 2 and 3). Tested with the points'
    # Type B (EDGE_BIAS_FACTOR x background_bound), the closed rim passes
    # whole in two of the four (9 of the 12 images of seeds 0-5; 10 of 12
    # when the renderer blurred the pixels digitally), largest gaps 5-7 deg.
    largest = []
    for seed in (0, 1):
        for _, arcs in _rendered_arcs("plate", seed, ["circle-6"]):
            rim = arcs["circle-6"]
            assert len(rim) == 1
            c = rim[0].fit.params[:2]
            ang = np.sort(np.degrees(np.arctan2(*(rim[0].ideal.xy - c).T[::-1])))
            largest.append(np.diff(np.r_[ang, ang[0] + 360.0]).max())
    assert sum(g < 15.0 for g in largest) >= 2, largest


def test_a_slot_end_comes_as_one_piece_of_its_contour():
    # The bracket's slot ends (4 mm half-circles, tangent to the slot's
    # sides) beside their shaded walls: two arcs of one contour whose union
    # failed the test with the noise alone stayed two pieces, each trimmed at
    # the split (seed 1, right image, arc-2). Their union is tested with the
    # points' Type B, as the whole of a closed contour is.
    for seed in (0, 1):
        for res, arcs in _rendered_arcs("bracket", seed, ["arc-2", "arc-4"]):
            for fid, found in arcs.items():
                assert len(found) == 1
                contours = [res.segments[s].contour for s in found[0].segments]
                assert len(set(contours)) == len(contours), (seed, fid, contours)


def test_tangent_point_of_a_line_and_an_ellipse():
    from types import SimpleNamespace

    from partinspect.vision.contours import _tangent_point

    theta = np.radians(30.0)
    ellipse = SimpleNamespace(params=np.array([5.0, -3.0, 20.0, 10.0, theta]))
    # The end of the major axis, x = centre + 20 (cos, sin)(theta), with the tangent line there.
    end = np.array([5.0, -3.0]) + 20.0 * np.array([np.cos(theta), np.sin(theta)])
    normal = np.array([np.cos(theta), np.sin(theta)])
    for offset in (0.0, 0.7):
        line = SimpleNamespace(params=np.r_[normal, -(normal @ end) - offset])
        touch, dist = _tangent_point(line, ellipse)
        np.testing.assert_allclose(touch, end, atol=1e-9)
        assert abs(dist - offset) < 1e-9


def test_slot_ends_reach_the_points_where_the_sides_touch_them():
    # The bracket's slot ends (4 mm half-circles seen 35 px wide, tangent to
    # the slot's sides) in the images of seeds 0-3. At a tangent junction the
    # least-cost break between the side's line and the arc followed the
    # noise and the shading's displacement of the points: 2-5 px into the
    # arc, and where the arc re-tested with the noise alone failed, a
    # stretch of 20-50 deg was lost. Extent about the fitted centre, of the
    # 16 arcs: median 155.5 deg, two under 150 (105 and 137) before; with
    # the break where the side touches the arc's ellipse and the re-test
    # with the points' Type B, median 162, one under 150.
    extents = []
    for seed in range(4):
        for _, arcs in _rendered_arcs("bracket", seed, ["arc-2", "arc-4"]):
            for fid, found in arcs.items():
                assert len(found) == 1, (seed, fid)
                c = found[0].fit.params[:2]
                a = np.sort(np.degrees(np.arctan2(*(found[0].ideal.xy - c).T[::-1])) % 360.0)
                extents.append(360.0 - np.diff(np.r_[a, a[0] + 360.0]).max())
    assert np.median(extents) > 159.0, np.round(extents)
    assert sum(e < 150.0 for e in extents) <= 1, np.round(extents)


def _spur_and_arc(seed, sd=0.05):
    """Edge points of a straight weak edge (9 points) running into a rim
    stretch (26 points, 75 deg of a circle of radius 20 px) at a right-angled
    corner, as one contour: how a hole's inner edge joins its rim."""
    from partinspect.vision.contours import Contour
    from partinspect.vision.edges import EdgePoints

    rng = np.random.default_rng(seed)
    c, r = np.array([100.0, 100.0]), 20.0
    phi = np.deg2rad(np.linspace(200.0, 275.0, 26))
    arc_n = np.column_stack([np.cos(phi), np.sin(phi)])
    arc = c + r * arc_n
    # The spur leaves the arc's first point along the arc's normal, inward.
    inward = -arc_n[0]
    spur = arc[0] + np.outer(np.arange(9, 0, -1), inward)
    spur_n = np.tile([-inward[1], inward[0]], (9, 1))
    normal = np.vstack([spur_n, arc_n])
    xy = np.vstack([spur, arc]) + rng.normal(0.0, sd, (35, 1)) * normal
    t = np.column_stack([-normal[:, 1], normal[:, 0]])
    cov = sd**2 * np.einsum("ni,nj->nij", normal, normal) + np.einsum("ni,nj->nij", t, t) / 12.0
    n = len(xy)
    edges = EdgePoints(xy, normal, np.full(n, 20.0), cov, np.round(xy[:, ::-1]).astype(np.int32), np.full(n, 1.2),
                       (200, 200), 1.0, 2.0, 0.5, None, None)
    return edges, Contour(np.arange(n), False)


def test_a_rim_stretch_joined_by_another_edge_at_a_corner_is_kept():
    # The bracket's 4.5 mm hole (40 px across) in some noise draws: a weak
    # edge inside the hole joined 75 deg of its rim through a corner, the
    # contour failed its test and Ramer's rule halved the rim stretch into
    # two pieces too short for an arc after their trims: the stretch was
    # lost. Split at the corner, the rim stretch is one arc.
    from partinspect.vision import contours as C

    for seed in range(3):
        edges, contour = _spur_and_arc(seed)
        segs = C.segment_contour(edges, contour)
        arcs = [s for s in segs if s.kind == "arc"]
        assert len(arcs) == 1, [(s.kind, len(s.index)) for s in segs]
        # Its fit takes rim points only, most of them (75 deg of arc is too
        # short to fix an ellipse's shape: its parameters are not tested).
        fitted = arcs[0].fit_index
        assert fitted.min() >= 9 and len(fitted) >= 18
        assert np.abs(np.linalg.norm(edges.xy[fitted] - 100.0, axis=1) - 20.0).max() < 0.25


def test_split_position_prefers_a_corner_over_the_farthest_point():
    from partinspect.vision.contours import CORNER_TURN, _split_position

    edges, _ = _spur_and_arc(0, sd=0.0)
    assert _split_position(edges.xy, edges.normal, 4) in (8, 9)
    # A smooth arc (turning 7.5 deg per point) has no corner: Ramer's farthest point.
    phi = np.deg2rad(np.linspace(0.0, 180.0, 25))
    n = np.column_stack([np.cos(phi), np.sin(phi)])
    assert _split_position(20.0 * n, n, 4) == 12
    assert 2 * np.deg2rad(7.5) < CORNER_TURN
