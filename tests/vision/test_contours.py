import numpy as np
import pytest

from partinspect.vision.contours import chain_edges, segment_contours
from partinspect.vision.edges import edge_points
from tests.vision.synthetic import Disc, rectangle, render


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
