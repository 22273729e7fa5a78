"""Lines measured on the stretch of a longer image line that a CAD edge's image covers."""

import numpy as np
import pytest

from partinspect.vision.guided import guided_lines, line_stretch, stretch_along
from tests.vision import stereo_scenes as S


def test_stretch_along_takes_points_near_the_polyline_between_its_trimmed_ends():
    poly = np.c_[np.linspace(0.0, 100.0, 201), np.zeros(201)]
    x = np.linspace(-10.0, 110.0, 121)
    uv = np.r_[np.c_[x, np.full_like(x, 1.5)], np.c_[x, np.full_like(x, 2.5)]]
    inside, s = stretch_along(uv, poly, trim=4.0)
    near = np.abs(uv[:, 1]) <= 2.0
    assert np.array_equal(inside, near & (uv[:, 0] >= 4.0) & (uv[:, 0] <= 96.0))
    assert np.allclose(s[inside], uv[inside, 0], atol=0.25)
    # A polyline behind the camera (NaN) has no stretch.
    assert not stretch_along(uv, np.full((5, 2), np.nan))[0].any()


@pytest.fixture(scope="module")
def plate_lines():
    """The plate's longest measured 3D line and the measurement it came from."""
    from partinspect.vision.stereo import measure_stereo

    rig, pose, left, right = S.render("plate", 2.0, 0)
    stereo = measure_stereo(left, right, rig)
    lines = [k for k, f in enumerate(stereo.features) if f.kind == "line"]
    k = max(lines, key=lambda i: len(stereo.features[i].correspondences))
    return rig, stereo, k


def _images(rig, a, b):
    from partinspect.vision.calibration import project_points

    s = np.linspace(0.0, 1.0, 2000)[:, None]
    X = a + s * (b - a)
    return (project_points(X, rig.K1, rig.D1, np.eye(3), np.zeros(3)),
            project_points(X, rig.K2, rig.D2, rig.R, rig.T))


def test_line_stretch_is_the_fit_of_the_kept_points_alone(plate_lines):
    from partinspect.vision.fitting import fit_line

    rig, stereo, k = plate_lines
    f = stereo.left.features[stereo.features[k].left]
    keep = np.arange(10, len(f) // 2)
    part = line_stretch(f, keep, 1.0)
    ref = fit_line(f.ideal.xy[keep], f.ideal.cov[keep], corr_length=1.0)
    assert np.allclose(part.fit.params, ref.params) and np.allclose(part.fit.cov, ref.cov)
    assert np.array_equal(part.index, f.index[keep]) and np.array_equal(part.edge_normal, f.edge_normal[keep])
    assert part.fit.cov[0, 0] > f.fit.cov[0, 0]  # fewer points, less certain


def test_two_collinear_edges_in_one_image_line_are_measured_each_on_its_own_stretch(plate_lines):
    """A measured line taken as two collinear CAD edges with a gap between: each gets the points
    of its stretch (less the trim at its ends), the whole line's 3D feature gives way to them, and
    each lies on the whole line within their uncertainties."""
    rig, stereo, k = plate_lines
    whole = stereo.features[k]
    a, b = whole.start, whole.end
    first = (a, a + 0.4 * (b - a))
    second = (a + 0.6 * (b - a), b)
    expected = {"edge-a": _images(rig, *first), "edge-b": _images(rig, *second)}
    more, found, failed = guided_lines(stereo, rig, expected, owned=set())

    assert set(found) == {"edge-a", "edge-b"} and not failed
    assert len(more.features) == len(stereo.features) + 1  # two in, the whole line out
    assert not any(f.left == whole.left for f in more.features[:-2])
    n = len(whole.correspondences)
    d = (b - a) / np.linalg.norm(b - a)
    for cid, (s0, s1) in (("edge-a", first), ("edge-b", second)):
        f = more.features[found[cid]]
        assert f.guided == cid and f.kind == "line"
        # Its extent lies within its stretch, and covers most of it.
        t = [(p - a) @ d for p in (f.start, f.end)]
        lo, hi = sorted(((s0 - a) @ d, (s1 - a) @ d))
        assert lo - 0.05 <= min(t) and max(t) <= hi + 0.05 and max(t) - min(t) > 0.8 * (hi - lo)
        assert 0.3 * n < len(f.correspondences) < 0.45 * n
        # On the whole line: the point's offset across it within 3 u of the two fits.
        off = (f.point - whole.point) - ((f.point - whole.point) @ d) * d
        cov = f.covariance + whole.covariance
        assert off @ np.linalg.solve(cov + np.outer(d, d), off) < 9.0
        assert np.degrees(np.arccos(min(1.0, abs(f.direction @ whole.direction)))) < 0.5
    # Each image point is used once.
    la, lb = (more.left.features[more.features[found[c]].left].index for c in ("edge-a", "edge-b"))
    assert not np.intersect1d(la, lb).size


def test_an_owned_image_line_or_a_stretch_off_every_line_gives_nothing(plate_lines):
    rig, stereo, k = plate_lines
    whole = stereo.features[k]
    a, b = whole.start, whole.end
    expected = {"edge-a": _images(rig, a, a + 0.5 * (b - a))}
    owned = {("left", whole.left), ("right", whole.right)}
    more, found, _ = guided_lines(stereo, rig, expected, owned)
    assert more is stereo and not found
    shifted = {"edge-a": _images(rig, a + [0.0, 0.0, 5.0], b + [0.0, 0.0, 5.0])}
    more, found, _ = guided_lines(stereo, rig, shifted, set())
    assert not found


def test_points_near_another_edges_image_are_not_taken(plate_lines):
    """Two edges on one image line (a face seen edge-on): neither may take the points."""
    rig, stereo, k = plate_lines
    whole = stereo.features[k]
    a, b = whole.start, whole.end
    images = _images(rig, a, a + 0.5 * (b - a))
    more, found, _ = guided_lines(stereo, rig, {"edge-a": images}, set(), others={"edge-b": images})
    assert not found and more is stereo
    far = _images(rig, a + [0.0, 30.0, 0.0], b + [0.0, 30.0, 0.0])
    more, found, _ = guided_lines(stereo, rig, {"edge-a": images}, set(), others={"edge-b": far})
    assert set(found) == {"edge-a"}


def test_line_ends_near_another_edges_image_are_left_out_and_refitted(plate_lines):
    """An edge's image running beside a measured line's first 30 % (2 px away: a faint edge the
    segmentation saw no points of) takes that end run out of the line in that image; the line is
    refitted from the rest. The same edge beside the middle of the line takes the middle out."""
    from partinspect.vision.guided import clear_line_ends

    rig, stereo, k = plate_lines
    whole = stereo.features[k]
    fl = stereo.left.features[whole.left]
    order = np.argsort(fl.ideal.xy @ fl.fit.direction)
    uv = fl.uv[order]
    n = np.array([-fl.fit.direction[1], fl.fit.direction[0]])
    own = _images(rig, whole.start, whole.end)

    def beside(lo, hi):
        i0, i1 = int(lo * len(uv)), int(hi * len(uv))
        return uv[i0:i1] + 2.0 * n, np.full((2, 2), np.nan)

    out, cleared, covered = clear_line_ends(stereo, rig, {k: "edge"}, {"edge": own, "faint": beside(0.0, 0.3)})
    assert covered == {}
    lost_l, lost_r = cleared["edge"]
    assert lost_r == 0 and 0.25 * len(uv) < lost_l < 0.4 * len(uv)
    g = out.left.features[whole.left]
    assert len(g) == len(fl) - lost_l and out.right.features[whole.right] is stereo.right.features[whole.right]
    # The points left out are the end beside the faint edge: the first ones along the line.
    kept = np.isin(fl.index[order], g.index)
    assert not kept[:lost_l].any() and kept[lost_l:].all()
    new = out.features[k]
    assert new.kind == "line" and len(new.correspondences) < len(whole.correspondences)
    assert all(a is b for i, (a, b) in enumerate(zip(out.features, stereo.features)) if i != k)
    # Beside the middle only: the middle is taken, both ends kept.
    mid, cleared, covered = clear_line_ends(stereo, rig, {k: "edge"}, {"edge": own, "faint": beside(0.35, 0.65)})
    lost_l, lost_r = cleared["edge"]
    assert covered == {} and lost_r == 0 and 0.25 * len(uv) < lost_l < 0.35 * len(uv)
    kept = np.isin(fl.index[order], mid.left.features[whole.left].index)
    i0, i1 = np.flatnonzero(~kept)[[0, -1]]
    assert kept[:i0].all() and not kept[i0:i1 + 1].any() and kept[i1 + 1:].all()
    assert 0.3 * len(uv) < i0 < 0.36 * len(uv) and 0.64 * len(uv) < i1 < 0.7 * len(uv)
    # Beside all of it, in the left image: left as it was, and named as covered by that edge.
    same, none, covered = clear_line_ends(stereo, rig, {k: "edge"}, {"edge": own, "faint": beside(0.0, 1.0)})
    assert none == {} and same is stereo and covered == {"edge": ("left", "faint")}


def test_cleared_line_keeps_its_own_filter_scale(plate_lines):
    """A line added from an adaptive round with a wider filter is refitted with that round's
    correlation length, not the base round's."""
    from dataclasses import replace

    from partinspect.vision.fitting import fit_line
    from partinspect.vision.guided import clear_line_ends

    rig, stereo, k = plate_lines
    whole = stereo.features[k]
    lefts, rights = list(stereo.left.features), list(stereo.right.features)
    lefts[whole.left] = replace(lefts[whole.left], corr_length=1.5)
    rights[whole.right] = replace(rights[whole.right], corr_length=1.5)
    wide = replace(stereo, left=replace(stereo.left, features=lefts), right=replace(stereo.right, features=rights))
    fl = lefts[whole.left]
    uv = fl.uv[np.argsort(fl.ideal.xy @ fl.fit.direction)]
    n = np.array([-fl.fit.direction[1], fl.fit.direction[0]])
    faint = (uv[: len(uv) // 4] + 2.0 * n, np.full((2, 2), np.nan))
    out, cleared, _ = clear_line_ends(wide, rig, {k: "edge"}, {"edge": _images(rig, whole.start, whole.end), "faint": faint})
    g = out.left.features[whole.left]
    assert cleared and g.corr_length == 1.5
    ref = fit_line(g.ideal.xy, g.ideal.cov, corr_length=1.5)
    assert np.allclose(g.fit.cov, ref.cov) and not np.allclose(g.fit.cov, fit_line(g.ideal.xy, g.ideal.cov, corr_length=1.0).cov)
    # So is a stretch of it.
    a, b = whole.start, whole.end
    more, found, _ = guided_lines(wide, rig, {"edge-a": _images(rig, a, a + 0.4 * (b - a))}, owned=set())
    h = more.left.features[more.features[found["edge-a"]].left]
    assert h.corr_length == 1.5 and np.allclose(h.fit.cov, fit_line(h.ideal.xy, h.ideal.cov, corr_length=1.5).cov)


def test_a_stretch_found_but_not_measured_keeps_its_reason(plate_lines):
    """Stretches found in both images that do not correspond (here: the left image's from one end
    of the line, the right image's from the other) give no 3D line; the edge and why are kept on
    the result for the report."""
    rig, stereo, k = plate_lines
    whole = stereo.features[k]
    a, b = whole.start, whole.end
    left, _ = _images(rig, a, a + 0.35 * (b - a))
    _, right = _images(rig, a + 0.65 * (b - a), b)
    more, found, failed = guided_lines(stereo, rig, {"edge-x": (left, right)}, owned=set())
    assert not found and "corresponding points" in failed["edge-x"]
    assert dict(more.guided_failed) == failed and more.features is stereo.features


def test_a_rim_seen_only_crowded_in_one_image_is_refused_not_kept_whole():
    """Issue 38, NIST ftc_09 circle-59 (exact render): a countersink's lower rim seen from below.

    In the left image the cone between it and the upper rim is edge-on, and the upper rim's
    image runs 2 px inside the lower one's along the whole arc seen: every point of the arc
    is crowded (the two steps smoothed into one, the points 0.2-0.7 px off the rim). Clearing
    would leave none, and the arc was kept whole and measured (diameter 4.1 u off: a false
    reject). It is now refused, naming the edge that crowds it; a rim crowded at a few points
    only is not, and the right image's arc, clear, does not make it so.
    """
    from types import SimpleNamespace as NS

    from partinspect.vision.guided import clear_arc_ends

    t = np.radians(np.arange(0.0, 360.0, 0.5))
    ring = lambda c, r: np.c_[c[0] + r * np.cos(t), c[1] + r * np.sin(t)]  # noqa: E731
    a = np.radians(np.arange(300.0, 370.0, 2.7))  # the 26 points of the arc seen, as in ftc_09
    arc = np.c_[200 + 25 * np.cos(a), 150 + 25 * np.sin(a)]
    edges = NS(sigma=1.0, width=np.full(10, 1.2))
    images = {"lower": (ring((200, 150), 25.0), ring((600, 150), 25.0)),
              "upper": (ring((200, 150), 23.0), ring((600, 150), 45.0))}
    left = NS(edges=edges, features=[NS(uv=arc)])
    right = NS(edges=edges, features=[NS(uv=arc + [400.0, 0.0])])
    stereo = NS(left=left, right=right, geometry=None, features=[NS(kind="arc", left=0, right=0)])
    out, cleared, crowded = clear_arc_ends(stereo, None, {0: "lower"}, images)
    assert out is stereo and cleared == {}
    assert list(crowded) == ["lower"]
    assert "left image 26 of its 26 points" in crowded["lower"] and "upper's image" in crowded["lower"]
    # The upper rim 2 px away only over a few degrees: the arc keeps enough clear points.
    far = ring((200, 150), 45.0)
    far[(t > np.radians(300)) & (t < np.radians(310))] = ring((200, 150), 23.0)[(t > np.radians(300))
                                                                                & (t < np.radians(310))]
    images["upper"] = (far, images["upper"][1])
    _, _, crowded = clear_arc_ends(stereo, None, {0: "lower"}, images, min_points=1000)
    assert crowded == {}
