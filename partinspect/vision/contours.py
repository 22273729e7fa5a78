"""Chaining of edge points into contours, and their segmentation into lines and arcs.

Chaining follows Devernay [1]_: each edge point links forward to the
nearest 8-neighbour ahead of it along the edge (the gradient turned by +90
deg) with a compatible gradient, and backward likewise; a link is kept when
both ends agree. Chains are ordered by pointer jumping, without a per-point
Python loop.

Segmentation (paper, section 3 [2]_) is split-and-merge [4]_ with a
statistical test: a piece is accepted as a line, else as an elliptical arc,
when the chi-square of its orthogonal residuals against the points' own
standard uncertainties (correlation along the edge included) is not
significant at level ``alpha``; otherwise it is split at its sharpest
corner, else at the point farthest from its chord [3]_. Pieces too short to
split that pass no test stay pending until the merge of adjacent pieces
(while their union passes) takes them in or drops them. Each break between
two accepted neighbours is then moved to where their fitted models meet,
since a split falls where a chord is farthest, not at the junction of two
primitives. A piece's fit leaves out ``trim`` px (arc length) at its open
ends, and a line's end points within ``CLEARANCE`` edge widths of another
edge: there the Gaussian smoothing mixes two edges (corners, junctions of
three edges) and the points are displaced.

Points in px, distorted image (as detected).

References
----------
.. [1] Devernay, F. (1995). A non-maxima suppression method for edge
       detection with sub-pixel accuracy. INRIA RR-2724 (chaining).
.. [2] Paper of this project, section 3.
.. [3] Ramer, U. (1972). An iterative procedure for the polygonal
       approximation of plane curves. CGIP 1, 244-256 (split at the
       farthest point).
.. [4] Pavlidis, T., Horowitz, S. L. (1974). Segmentation of plane curves.
       IEEE Trans. Computers C-23(8), 860-870 (split and merge).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from partinspect.vision.edges import EDGE_BIAS_FACTOR
from partinspect.vision.fitting import (
    EllipseJob,
    as_points,
    axis_bound,
    direct_residuals,
    ellipse_geometry,
    ellipse_points,
    ellipse_with_covariance,
    fit_ellipses,
    fit_line,
    foot_phases,
    line_with_covariance,
    std_along,
)

__all__ = ["Contour", "Segment", "chain_edges", "segment_contour", "segment_contours"]

# Convergence of the trial ellipse fits, in standard uncertainties of their
# parameters (see fitting._lm_ellipses): a fit is done when the remaining
# Gauss-Newton step is below a tenth of the uncertainty in every direction,
# its chi-square then within about 0.01 of the minimum's, a hundredth of a
# standard deviation of the chi-square itself (sqrt(2 dof) >= 3.7 for the
# 12 points of the shortest piece tried). A test needs no more; the pieces
# kept are refitted (_make_segments).
_SIGMA_TOL = 0.1
# Iterations of a trial fit at most (see _test_pieces).
_TEST_ITERATIONS = 30
# The refits of the pieces kept (measurements, no longer tests) stop at a
# thousandth of a standard uncertainty, or at fit_ellipse's pixel tolerance,
# or after as many iterations as the test's fit: those of a piece whose
# ellipse its points hardly fix (the test's fit did not converge either)
# move it along its flat valley, within its uncertainty.
_SIGMA_TOL_REFIT = 1e-3

# A line's end points closer than this many edge widths w (the standard
# deviation of the edge's whole blur, filter and optics, EdgePoints.width) to
# another edge are left out of its fit (_crowded). A parallel step at
# distance d displaces an edge point by up to about d exp(-d^2 / 2 w^2) times
# the ratio of the two contrasts: 0.3 px at 2 w, 0.04 px at 3 w, no more
# than a point's noise.
CLEARANCE = 3.0

# A line piece's own end point this many of its standard uncertainties off
# the fitted line is on another edge (see _off_line); noise alone puts an
# on-line point there with probability 6e-7.
OFF_LINE_Z = 5.0

# px: a line meets an arc tangentially when the point of the arc's ellipse
# whose tangent is parallel to the line lies this close to it. A corner of
# angle a on an arc of radius r leaves r (1 - cos a) there (1 px for a = 14
# deg at r = 35 px); a tangent junction leaves only the points' displacement
# by the shading beside them, a fraction of a pixel.
TANGENT_TOLERANCE = 1.0

_NEIGHBOURS = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)])


@dataclass(frozen=True)
class Contour:
    """An ordered chain of edge points.

    Attributes
    ----------
    index : ndarray, shape (K,)
        Indices into the EdgePoints, in order along the edge (the
        direction keeps the bright side on the left in the image, y down).
    closed : bool
        The last point links back to the first.
    """

    index: np.ndarray
    closed: bool

    def __len__(self):
        return len(self.index)


@dataclass(frozen=True)
class Segment:
    """A piece of a contour fitted by one primitive.

    Attributes
    ----------
    kind : str
        "line" or "arc" (an elliptical arc).
    index : ndarray, shape (K,)
        Indices into the EdgePoints of all points of the piece, in order.
    fit_index : ndarray, shape (L,)
        The subset used in the fit (ends near corners left out).
    fit : LineFit or EllipseFit
    contour : int
        Number of the contour the segment comes from.
    """

    kind: str
    index: np.ndarray
    fit_index: np.ndarray
    fit: object
    contour: int


def chain_edges(edges, *, min_cos=0.5):
    """Link edge points into ordered contours.

    Parameters
    ----------
    edges : EdgePoints
    min_cos : float
        Smallest cosine between the gradients of two linked points.

    Returns
    -------
    list of Contour
        Longest first.
    """
    N = len(edges)
    if N == 0:
        return []
    H, W = edges.shape
    grid = np.full(H * W, -1, np.int64)
    r, c = edges.pixel[:, 0].astype(np.int64), edges.pixel[:, 1].astype(np.int64)
    grid[r * W + c] = np.arange(N)
    nr = r[:, None] + _NEIGHBOURS[None, :, 0]
    nc = c[:, None] + _NEIGHBOURS[None, :, 1]
    inside = (nr >= 0) & (nr < H) & (nc >= 0) & (nc < W)
    nb = np.where(inside, grid[np.clip(nr, 0, H - 1) * W + np.clip(nc, 0, W - 1)], -1)
    valid = nb >= 0
    nbs = np.where(valid, nb, 0)
    xy, n = edges.xy, edges.normal
    t = np.column_stack([-n[:, 1], n[:, 0]])
    dxy = xy[nbs] - xy[:, None, :]
    along = (dxy * t[:, None, :]).sum(axis=2)
    dist = np.hypot(dxy[..., 0], dxy[..., 1])
    agree = (n[nbs] * n[:, None, :]).sum(axis=2) >= min_cos
    ok = valid & agree
    big = np.inf
    fwd_score = np.where(ok & (along > 0), dist, big)
    bwd_score = np.where(ok & (along < 0), dist, big)
    fj, bj = fwd_score.argmin(axis=1), bwd_score.argmin(axis=1)
    ar = np.arange(N)
    fwd = np.where(np.isfinite(fwd_score[ar, fj]), nbs[ar, fj], -1)
    bwd = np.where(np.isfinite(bwd_score[ar, bj]), nbs[ar, bj], -1)
    # Keep a link only when both ends agree on it.
    fwd = np.where((fwd >= 0) & (bwd[np.maximum(fwd, 0)] == ar), fwd, -1)
    bwd = np.full(N, -1)
    has = fwd >= 0
    bwd[fwd[has]] = ar[has]

    src, dst = ar[has], fwd[has]
    graph = coo_matrix((np.ones(len(src)), (src, dst)), shape=(N, N))
    n_comp, label = connected_components(graph, directed=False)
    # Components without a start (no point lacks a predecessor) are cycles:
    # cut each before its smallest index.
    starts = np.bincount(label[bwd < 0], minlength=n_comp)
    closed = starts == 0
    first = np.full(n_comp, N)
    np.minimum.at(first, label, ar)
    cut = first[closed]
    pred = bwd[cut]
    fwd[pred] = -1
    bwd[cut] = -1
    # Pointer jumping: number of links to the end of the chain.
    # A chain's last point points to itself with distance 0, so adding the
    # distance of the point jumped to is right even once the end is reached.
    nxt = np.where(fwd >= 0, fwd, ar)
    dist_end = (fwd >= 0).astype(np.int64)
    while True:
        nn = nxt[nxt]
        if np.array_equal(nn, nxt):
            break
        dist_end = dist_end + dist_end[nxt]
        nxt = nn
    order = np.lexsort((-dist_end, label))
    bounds = np.flatnonzero(np.diff(label[order])) + 1
    out = [Contour(idx, bool(closed[label[idx[0]]])) for idx in np.split(order, bounds)]
    out.sort(key=len, reverse=True)
    return out


def arc_length(xy):
    """Arc length along a polyline at each of its points, from 0 at the first.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        The points in order along the curve, px.

    Returns
    -------
    ndarray, shape (N,)
        Cumulative chord lengths, px: the trims at a piece's ends and the
        clearances from other edges are distances along the edge.
    """
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])


def _ellipse_plausible(xy, cov, factor=9.0):
    """Cheap screen before the iterative fit: the direct algebraic fit's
    orthogonal residuals must not exceed the point noise by far (their mean
    square within ``factor`` times the expected); the geometric fit improves
    on the algebraic one by much less than that for data that are not an
    ellipse, and skipping it keeps the merge tests on corners cheap.

    Returns
    -------
    tuple or None
        (params, phases): the algebraic fit and its foot phases, the start
        of the geometric fit (computed here already), or None if the
        points fail the screen.
    """
    direct = direct_residuals(xy)
    if direct is None:
        return None
    p, phi, r, n = direct
    s2 = std_along(cov, n) ** 2
    return (p, phi) if float((r * r / s2).mean()) < factor else None


def _test_pieces(requests, min_arc=12, max_iter=_TEST_ITERATIONS):
    """The statistical test of several pieces at once.

    Each piece is tried as a line, else (with ``"arc"`` in its kinds) as an
    elliptical arc; the ellipse fits of all the pieces run together
    (:func:`partinspect.vision.fitting.fit_ellipses`), each exactly as it
    would alone.

    An arc is accepted when an ellipse of plausible size (semi-major axis
    at most ``fitting.MAX_AXIS_SPANS`` times the piece's extent, minor semi-axis
    at least the edge filter's sigma) passes the chi-square test of its
    residuals: on that test, not on how many iterations the fit took. The
    fit stops when converged to a tenth of its parameters' standard
    uncertainties (``_SIGMA_TOL``: on a short arc they are pixels, and the
    cost is flat along a curved valley that a pixel tolerance would follow
    for hundreds of iterations), before a step beyond the size bound (the
    best ellipse is larger, the piece's best conic a parabola or a
    hyperbola: the iterate within the bound is kept), or after
    ``max_iter`` iterations. The iterate it stops at is tested: the cost
    only decreases along the iteration, so an iterate that passes shows an
    ellipse consistent with the points, and the minimum would pass too.
    Where the fit has not converged the cost is flat (a short piece, whose
    ellipse the points hardly fix) and its chi-square settled, so more
    iterations would not change the decision.

    Parameters
    ----------
    requests : list of tuple
        (xy, cov, corr_length, alpha, floor, kinds) per piece; floor (px)
        one value or one per point; kinds is ("line", "arc") or ("arc",).

    Returns
    -------
    list
        Per piece, (kind, fit, p_value) of the first primitive accepted, or
        None.
    """
    out = [None] * len(requests)
    jobs, where = [], []
    # The fits are made without their covariances (cov and ci95 None): a
    # test needs only the consistency, most pieces tested are not kept, and
    # the kept ones are refitted (_make_segments, which completes them
    # without the refit).
    for k, (xy, cov, corr_length, alpha, floor, kinds) in enumerate(requests):
        floor = np.asarray(floor, float)
        cov_t = cov + (floor * floor)[..., None, None] * np.eye(2) if np.any(floor) else cov
        if "line" in kinds:
            try:
                fit = fit_line(xy, cov_t, corr_length=corr_length, with_cov=False)
            except (ValueError, np.linalg.LinAlgError):
                fit = None
            if fit is not None and fit.consistency.p_value >= alpha:
                out[k] = ("line", fit, fit.consistency.p_value)
                continue
        if "arc" not in kinds or len(xy) < min_arc:
            continue
        try:
            init = _ellipse_plausible(xy, cov_t)
        except (ValueError, np.linalg.LinAlgError):
            init = None
        if init is not None:
            jobs.append(EllipseJob(xy, cov_t, corr_length, init=init, max_axis=axis_bound(xy)))
            where.append(k)
    fits = fit_ellipses(jobs, max_iter, None, with_cov=False, sigma_tol=_SIGMA_TOL)
    for k, job, fit in zip(where, jobs, fits):
        if fit is None or not np.all(np.isfinite(fit.params)) or fit.params[2] > job.max_axis:
            continue
        # An ellipse narrower than the edge filter resolves is no rim the
        # detector can see: its two sides, 2 b apart, would merge into one
        # edge under the smoothing (sigma, which is the correlation length
        # of the points). A fit that goes there has bent a straight piece
        # round a hairpin at its end (a line, or a corner, in disguise).
        if job.corr_length and fit.params[3] < job.corr_length:
            continue
        p = fit.consistency.p_value
        if p >= requests[k][3]:
            out[k] = ("arc", fit, p)
    return out


CORNER_TURN = np.deg2rad(60.0)
"""A failing piece is split where its edge direction turns by at least this
across one point (between the gradients of the points either side), rather
than at the point farthest from its chord. The chaining links points whose
gradients differ by up to 60 deg, so a weak edge meeting a rim ends up in the
rim's contour through a corner; Ramer's rule would then halve a short rim
stretch into two pieces too short for an arc after their trims, instead of
cutting the other edge off. A smooth edge turns across a point by 2 / rho
rad (rho its radius of curvature, px): 60 deg takes rho under 2 px, sharper
than the tip of any ellipse the segmentation keeps but the flattest."""


def _split_position(xy, normal, margin):
    """Where to split a piece that failed its test.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        The piece's points in order, px.
    normal : ndarray, shape (N, 2)
        Their unit gradient directions.
    margin : int
        Positions this close to either end are not split at.

    Returns
    -------
    int
        Position in the piece: its sharpest corner when the edge turns there
        by ``CORNER_TURN`` or more (see there), else the point farthest from
        the chord (Ramer [3]).
    """
    n = len(xy)
    turn = np.full(n, -1.0)
    if n >= 3:
        turn[1:-1] = np.arccos(np.clip(np.einsum("ij,ij->i", normal[:-2], normal[2:]), -1.0, 1.0))
    turn[:margin] = turn[n - margin:] = -1.0
    k = int(np.argmax(turn))
    if turn[k] >= CORNER_TURN:
        return k
    chord = xy[-1] - xy[0]
    L = np.hypot(*chord)
    if L > 1e-9:
        v = xy - xy[0]
        d = np.abs(chord[0] * v[:, 1] - chord[1] * v[:, 0]) / L
    else:
        d = np.linalg.norm(xy - xy[0], axis=1)
    d[:margin] = d[n - margin:] = -1
    return int(np.argmax(d))


def _trimmed(idx_local, s, trim, open_start, open_end):
    """Positions of the piece used in its fit: drop `trim` px at open ends."""
    keep = np.ones(len(idx_local), bool)
    if open_start:
        keep &= s - s[0] >= trim
    if open_end:
        keep &= s[-1] - s >= trim
    return keep


def segment_contour(edges, contour, *, alpha=0.01, trim=None, min_points=8, floor=0.01,
                    contour_id=0, refit=True):
    """Split one contour into line segments and elliptical arcs.

    Parameters
    ----------
    edges : EdgePoints
    contour : Contour
    alpha : float
        Significance level of the chi-square test of a piece's residuals.
    trim : float, optional
        Arc length left out of the fit at each open end of a piece, px;
        default 3 sigma + 1 (sigma the edge filter scale): where the
        smoothing of a neighbouring edge reaches.
    min_points : int
        Pieces with fewer fitted points are dropped.
    floor : float
        Standard uncertainty added in quadrature to the points' normal
        uncertainty for the test only, px: a floor above the residual
        systematic error of the sub-pixel estimator, so that very clean
        images are not cut into pieces by it. The whole of a closed
        contour, and the union of two arcs, are tested with the Type B of
        their points beside a shaded surface too (in quadrature,
        ``EDGE_BIAS_FACTOR`` times ``background_bound``, as the 3D fits of
        rims take it): the shading of a hole's inner wall displaces some of
        its rim's points beyond their noise, and a rim that failed on them
        was split, each split costing two trims of its points. The returned
        fits use the points' own covariances.
    refit : bool
        Refit each accepted piece with the points' own covariances.

    Returns
    -------
    list of Segment
    """
    steps = _segment_steps(edges, contour, alpha, trim, min_points, floor)
    return _make_segments(edges, [contour], [contour_id], _run_steps([steps]), refit, min_points)


def _segment_steps(edges, contour, alpha, trim, min_points, floor):
    """The split and merge of :func:`segment_contour`, as a generator.

    It yields lists of the tests it needs, ``(xy, cov, corr_length, alpha,
    floor, kinds)`` (see :func:`_test_pieces`), is sent their results, and
    returns the accepted pieces, [(positions, (kind, fit, p_value,
    fitted positions))]: so that :func:`segment_contours` can run the tests
    of all the contours together (:func:`_run_steps`). Within a contour,
    the pieces of one split level and the unions of one merge round are
    tested together; no decision depends on the order of the tests.
    """
    if trim is None:
        trim = 3.0 * edges.sigma + 1.0
    idx = contour.index
    n = len(idx)
    if n < min_points:
        return []
    xy_all, cov_all, normal_all = edges.xy[idx], edges.cov[idx], edges.normal[idx]
    std_all = std_along(cov_all, normal_all)
    bound = edges.background_bound[idx] if edges.background_bound is not None else 0.0
    rim_floor = np.hypot(floor, EDGE_BIAS_FACTOR * bound) * np.ones(n)
    cl = edges.sigma

    # The merge pass re-tests the unions of every adjacent pair in each
    # round although only the pairs next to the last merge changed.
    cache = {}

    def fit_ranges(ranges):
        """Test results of pieces (lo, hi, open_start, open_end, kinds), the
        ones not tested yet in one request."""
        keys = [(lo % n, hi - lo, o_s, o_e, kinds) for lo, hi, o_s, o_e, kinds in ranges]
        todo = {}
        for key, (lo, hi, o_s, o_e, kinds) in zip(keys, ranges):
            if key in cache or key in todo:
                continue
            pos = np.arange(lo, hi) % n
            xy = xy_all[pos]
            keep = _trimmed(pos, arc_length(xy), trim, o_s, o_e)
            if keep.sum() < min_points:
                cache[key] = None
                continue
            # The whole of a closed contour, or two arcs together, with the
            # Type B of their points beside a shaded surface (see segment_contour).
            rim = kinds == ("arc",) or (contour.closed and not (o_s or o_e))
            fl = rim_floor[pos[keep]] if rim else floor
            todo[key] = (pos[keep], (xy[keep], cov_all[pos[keep]], cl, alpha, fl, kinds))
        if todo:
            results = yield [req for _, req in todo.values()]
            for (key, (fit_pos, _)), res in zip(todo.items(), results):
                cache[key] = None if res is None else res + (fit_pos,)
        return [cache[key] for key in keys]

    # Split: a work list of (lo, hi) ranges in cyclic positions.
    pieces = []  # (lo, hi, result)
    if contour.closed:
        whole, = yield from fit_ranges([(0, n, False, False, ("arc",))])
        if whole is not None:
            return [(np.arange(n), whole)]
        far = int(np.argmax(np.linalg.norm(xy_all - xy_all[0], axis=1)))
        stack = [(far, n), (0, far)] if far > 0 else [(0, n)]
    else:
        stack = [(0, n)]
    while stack:
        level, stack = stack, []
        results = yield from fit_ranges([(lo, hi, True, True, ("line", "arc")) for lo, hi in level])
        for (lo, hi), res in zip(level, results):
            if res is not None:
                pieces.append((lo, hi, res))
                continue
            if hi - lo < 2 * min_points:
                # Failed its test and too short to split further: kept
                # pending, for the merge pass to test together with a
                # neighbour, and dropped if none takes it. Dropping it
                # here would lose the short stretches of a rim next to a
                # displaced one, which one ellipse fits together.
                pieces.append((lo, hi, None))
                continue
            k = lo + _split_position(xy_all[np.arange(lo, hi) % n], normal_all[np.arange(lo, hi) % n],
                                     min_points // 2)
            stack.append((k - n, hi - n) if k >= n else (k, hi))
            stack.append((lo, k))
    pieces.sort(key=lambda t: t[0])

    # Merge neighbours while the union still passes; best p-value first.
    # A piece is (lo, hi): cyclic positions lo .. hi - 1, 0 <= lo < n.
    while len(pieces) > 1:
        m = len(pieces)
        pairs = []
        for i in range(m if contour.closed else m - 1):
            j = (i + 1) % m
            a, b = pieces[i], pieces[j]
            if a[1] % n != b[0]:
                continue  # a dropped piece lies between them
            hi = a[1] + (b[1] - b[0])
            if hi - a[0] > n:
                continue
            whole_loop = contour.closed and hi - a[0] == n
            arcs = a[2] is not None and b[2] is not None and a[2][0] == b[2][0] == "arc"
            pairs.append((i, a[0], hi, not whole_loop, ("arc",) if arcs else ("line", "arc")))
        results = yield from fit_ranges([(lo, hi, o, o, kinds) for _, lo, hi, o, kinds in pairs])
        best = None
        for (i, lo, hi, _, _), res in zip(pairs, results):
            if res is not None and (best is None or res[2] > best[1][2][2]):
                best = (i, (lo, hi, res))
        if best is None:
            break
        i, merged = best
        j = (i + 1) % m
        pieces = [p for k, p in enumerate(pieces) if k not in (i, j)] + [merged]
        pieces.sort(key=lambda t: t[0])
    # A pending piece taken by no neighbour is dropped. Two pending
    # neighbours are tried together too: a stretch between a tangent line
    # and a junction can come as two pieces too short to pass alone.
    pieces = [p for p in pieces if p[2] is not None]
    pieces = yield from _adjust_breaks(pieces, n, contour.closed, xy_all, std_all, trim, min_points, fit_ranges)
    return [(np.arange(lo, hi) % n, res) for lo, hi, res in pieces]


def _model_residuals(kind, fit, xy):
    """Signed orthogonal distances of points from a piece's line or ellipse, px."""
    if kind == "line":
        A, B, C = fit.params
        return A * xy[:, 0] + B * xy[:, 1] + C
    r, _, _ = ellipse_geometry(xy, fit.params, foot_phases(xy, fit.params))
    return r


def _best_break(xy, std, a, b, k0):
    """Where two fitted neighbours on one stretch of edge should meet.

    The points ``xy`` run from inside the first piece to inside the
    second; each candidate break ``k`` (0 < k < len) gives the points
    before it to the first model and the rest to the second, at the cost
    of the sum of their squared normalised residuals. Returns the ``k`` of
    least cost, the one nearest ``k0`` among equals.
    """
    za = (_model_residuals(a[0], a[1], xy) / std) ** 2
    zb = (_model_residuals(b[0], b[1], xy) / std) ** 2
    if not (np.all(np.isfinite(za)) and np.all(np.isfinite(zb))):
        return k0
    k = np.arange(1, len(xy))
    cost = np.cumsum(za)[:-1] + (zb.sum() - np.cumsum(zb)[:-1])
    best = np.flatnonzero(cost <= cost.min() * (1 + 1e-12))
    return int(k[best[np.argmin(np.abs(best + 1 - k0))]])


def _tangent_point(line, ellipse):
    """Where a line touches an ellipse.

    Parameters
    ----------
    line : LineFit
        Parameters (A, B, C), ``A x + B y + C = 0`` with ``A^2 + B^2 = 1``.
    ellipse : EllipseFit
        Parameters (xc, yc, a, b, theta).

    Returns
    -------
    point : ndarray, shape (2,)
        The point of the ellipse whose tangent is parallel to the line, of
        the two such points the one nearer the line, px.
    distance : float
        Its distance from the line, px: zero where the line touches the
        ellipse.
    """
    A, B, _ = line.params
    _, _, a, b, theta = ellipse.params[:5]
    c, s = np.cos(theta), np.sin(theta)
    # The ellipse x(phi) = centre + Q(theta) (a cos phi, b sin phi) has its
    # tangent normal to the line's normal m where m . dx/dphi = 0, i.e. with
    # m' = Q^T m: tan phi = b m'_y / (a m'_x).
    m1, m2 = c * A + s * B, -s * A + c * B
    pts = ellipse_points(ellipse.params[:5], np.arctan2(b * m2, a * m1) + np.array([0.0, np.pi]))
    d = np.abs(_model_residuals("line", line, pts))
    k = int(np.argmin(d))
    return pts[k], float(d[k])


def _adjust_breaks(pieces, n, closed, xy_all, std_all, trim, min_points, fit_ranges):
    """Move each break between two accepted neighbours to where their models meet.

    The split falls at the point farthest from a chord, not at the
    junction of two primitives, and the test of a piece does not see the
    ``trim`` px at its open ends: a line running into a tangent arc keeps
    up to ``trim`` px of the arc untested, and the arc loses those and its
    own ``trim`` again, by an amount that changes from image to image with
    where the splits fall. Each break is moved, within ``3 trim`` points
    either way, to where the two pieces' fitted models (fitted on the
    pieces' cores, away from the break) explain the points between them
    best (:func:`_best_break`); or, where a line meets an arc tangentially
    (``TANGENT_TOLERANCE``), to the point nearest where the line touches the
    arc's ellipse (:func:`_tangent_point`): there the two models part by
    only s^2 / 2r at a distance s, less than the points' noise over several
    px, so the least-cost break would follow the noise and the shading,
    while the touching point is as certain as the models. The moved pieces
    are tested again, an arc with its points' Type B beside a shaded
    surface (as two arcs together are: the shading's displacement would
    otherwise fail an arc that took in a stretch the split had dropped); a
    piece that no longer passes keeps its old ends (as do its neighbours,
    then, on that side). A generator, like :func:`_segment_steps`.

    Parameters
    ----------
    pieces : list of (lo, hi, result)
        Accepted pieces in cyclic positions, sorted by ``lo``; a moved
        ``lo`` may leave ``0 <= lo < n``, its points are ``arange(lo, hi) % n``.
    n : int
        Points of the contour.
    closed : bool
    xy_all, std_all : ndarray, shapes (n, 2), (n,)
        The contour's points and their standard uncertainties along the
        edge normal, px.

    References
    ----------
    .. [1] Pavlidis, T., Horowitz, S. L. (1974). Segmentation of plane
           curves. IEEE Trans. Computers C-23(8), 860-870 (the adjustment
           of breakpoints after split and merge).
    """
    m = len(pieces)
    if m < 2:
        return pieces
    reach = int(np.ceil(3 * trim))
    ends = [[lo, hi] for lo, hi, _ in pieces]
    old = [list(e) for e in ends]
    for i in range(m if closed else m - 1):
        j = (i + 1) % m
        (alo, ahi, ares), (blo, bhi, bres) = pieces[i], pieces[j]
        gap = (blo - ahi) % n  # a dropped piece between them
        if gap > 2 * reach:
            continue
        blen = bhi - blo
        bstart = ahi + gap  # b's start, in a's positions
        lo = max(alo + 2 * min_points, ahi - reach)
        hi = min(bstart + blen - 2 * min_points, bstart + reach)
        if hi - lo < 2:
            continue
        pos = np.arange(lo, hi) % n
        k = None
        if {ares[0], bres[0]} == {"line", "arc"}:
            line, arc = (ares[1], bres[1]) if ares[0] == "line" else (bres[1], ares[1])
            touch, dist = _tangent_point(line, arc)
            near = np.linalg.norm(xy_all[pos] - touch, axis=1)
            # The touching point must lie on this stretch of the edge (within
            # 2 px of one of its points), not on the far side of the ellipse.
            if dist < TANGENT_TOLERANCE and near.min() < 2.0:
                k = lo + max(1, int(np.argmin(near)))
        if k is None:
            k = lo + _best_break(xy_all[pos], std_all[pos], ares, bres, (ahi + bstart) // 2 - lo)
        if k != ahi or gap:
            ends[i][1] = k
            ends[j][0] = blo + (k - bstart)  # b's hi stays as it is
    for _ in range(2):
        moved = [k for k in range(m) if ends[k] != old[k]]
        if not moved:
            return pieces
        results = yield from fit_ranges([(ends[k][0], ends[k][1], True, True,
                                          ("arc",) if pieces[k][2][0] == "arc" else ("line", "arc")) for k in moved])
        failed = [k for k, res in zip(moved, results) if res is None]
        if not failed:
            for k, res in zip(moved, results):
                pieces[k] = (ends[k][0], ends[k][1], res)
            return sorted(pieces, key=lambda t: t[0])
        for k in failed:
            # Back to its old ends, and its neighbours' ends that touch it.
            prev, nxt = (k - 1) % m, (k + 1) % m
            if ends[k][0] != old[k][0] and (closed or k > 0):
                ends[prev][1] = old[prev][1]
            if ends[k][1] != old[k][1] and (closed or k < m - 1):
                ends[nxt][0] = old[nxt][0]
            ends[k] = list(old[k])
        # A neighbour with both ends old again is as it was.
    return pieces


def _run_steps(steps):
    """Run segmentation generators (:func:`_segment_steps`) side by side,
    answering the tests they ask for in one batch per round.

    Returns
    -------
    list
        What each generator returns, in order.
    """
    out = [None] * len(steps)
    waiting = {}
    for k, g in enumerate(steps):
        try:
            waiting[k] = next(g)
        except StopIteration as stop:
            out[k] = stop.value
    while waiting:
        asked = [(k, req) for k, reqs in waiting.items() for req in reqs]
        answers = _test_pieces([req for _, req in asked])
        per = {k: [] for k in waiting}
        for (k, _), ans in zip(asked, answers):
            per[k].append(ans)
        waiting = {}
        for k, ans in per.items():
            try:
                waiting[k] = steps[k].send(ans)
            except StopIteration as stop:
                out[k] = stop.value
    return out


def _make_segments(edges, contours, contour_ids, accepted, refit, min_points):
    """Segments of the accepted pieces of several contours, the refits of
    all their arcs together.

    A line's fitted points within ``CLEARANCE`` edge widths of another
    piece's edge, or of its own unfitted points off its line
    (:func:`_off_line`), are left out first where they run up to an end of
    the line (:func:`_crowded`): the end of an edge at a junction or a
    corner. Inside a line such points stay: an edge running beside another
    for a stretch would otherwise lose it; the chi-square test of the
    segmentation has passed them. Arcs keep theirs: the two sides of a rim
    seen nearly edge-on come within the reach of each other at its tips,
    whose points fix the ellipse's major axis. A line left with fewer than
    ``min_points`` is
    dropped, and one that lost points is refitted whatever ``refit``
    says.

    Parameters
    ----------
    contours, contour_ids : list
    accepted : list
        Per contour, what :func:`_segment_steps` returns.
    refit : bool
        See :func:`segment_contour`.
    min_points : int
    """
    cl = edges.sigma
    reach = CLEARANCE * float(np.median(edges.width)) if len(edges.width) else 0.0
    todo = [(contour, cid, pos, kind, fit, contour.index[fit_pos])
            for contour, cid, pieces in zip(contours, contour_ids, accepted)
            for pos, (kind, fit, _, fit_pos) in pieces]
    lines = [k for k, t in enumerate(todo) if t[3] == "line"]
    whole = [todo[k][0].index[todo[k][2]] for k in lines]
    crowded = _crowded(edges, whole, [todo[k][5] for k in lines], reach,
                       [_off_line(edges, idx, todo[k][4], todo[k][5]) for k, idx in zip(lines, whole)])
    ends = dict(zip(lines, map(end_runs, crowded)))
    out, arcs = [], []
    for k, (contour, cid, pos, kind, fit, fit_index) in enumerate(todo):
        bad = ends.get(k)
        trimmed = bad is not None and bool(bad.any())
        if trimmed:
            if (~bad).sum() < min_points:
                continue
            fit_index = fit_index[~bad]
        xy, cov = edges.xy[fit_index], edges.cov[fit_index]
        if not (refit or trimmed):
            # The test's fit (of the points with the floor added), with the
            # covariance _test_pieces made it without.
            complete = line_with_covariance if kind == "line" else ellipse_with_covariance
            fit = complete(fit, xy, cl)
        elif kind == "line":
            fit = fit_line(xy, cov, corr_length=cl)
        else:
            # The test's fit of the same points (with the floor added to
            # their variances) is a start next to the minimum.
            arcs.append((len(out), EllipseJob(as_points(xy, 6), cov, cl, float(np.median(edges.width[fit_index])),
                                              fit.params, max_axis=axis_bound(xy))))
        out.append(Segment(kind, contour.index[pos], fit_index, fit, cid))
    refits = fit_ellipses([job for _, job in arcs], _TEST_ITERATIONS, sigma_tol=_SIGMA_TOL_REFIT)
    for (k, _), fit in zip(arcs, refits):
        out[k] = replace(out[k], fit=fit)
    return out


def end_runs(bad):
    """The runs of True at the two ends of ``bad``, as a mask.

    Parameters
    ----------
    bad : ndarray of bool, shape (N,)
        Per point along an edge, e.g. "within reach of another edge".

    Returns
    -------
    ndarray of bool, shape (N,)
        True for the points of the leading and trailing runs of ``bad``
        (all of them when every point is bad): an edge is cut back from its
        ends only, so a bad point inside it does not split it.
    """
    out = np.zeros_like(bad)
    clean = np.flatnonzero(~bad)
    if len(clean) == 0:
        out[:] = True
    else:
        out[: clean[0]] = True
        out[clean[-1] + 1:] = True
    return out


def _off_line(edges, piece, fit, fitted, k=OFF_LINE_Z):
    """A line piece's own unfitted points lying off its fitted line.

    The split between two edges meeting at a corner can fall past the
    corner: the line's piece then ends with the corner's rounded points
    and a few of the other edge's, which its end trim keeps out of the fit
    but which, being its own, do not count as another edge for
    :func:`_crowded`; its fitted points next to the corner would stay,
    displaced by the other edge's gradient, and set a short line's
    straightness. A point more than ``k`` of its own standard
    uncertainties off the line is taken as the other edge's: the fitted
    points within the reach of it go.

    Returns
    -------
    ndarray of int
        Edge point indices.
    """
    rest = piece[~np.isin(piece, fitted)]
    # (A, B) of the line's Hesse normal form is its unit normal.
    sd = std_along(edges.cov[rest], np.asarray(fit.params[:2], float))
    return rest[np.abs(_model_residuals("line", fit, edges.xy[rest])) > k * sd]


def _crowded(edges, pieces, fitted, reach, foreign=None):
    """Fitted points lying within ``reach`` of an edge point of another piece.

    The Gaussian smoothing mixes two edges that come closer than a few of
    its scales, and displaces both: at a junction of three edges, where an
    edge of another contour ends beside this piece's end (which the
    arc-length trim of :func:`_trimmed` cannot see), at an acute corner, or
    beside a close parallel edge. A piece's end points there are displaced
    by several of their standard uncertainties and can alone set the
    straightness of a short line.

    Parameters
    ----------
    edges : EdgePoints
    pieces : list of ndarray
        Each piece's edge point indices, the whole piece (its trimmed ends
        too): these are its own edge.
    fitted : list of ndarray
        The indices of the points each piece fits.
    reach : float
        px.
    foreign : list of ndarray, optional
        Per piece, points of its own that count as another edge's
        (:func:`_off_line`).

    Returns
    -------
    list of ndarray of bool
        Per piece, per fitted point: another edge lies within ``reach``.
    """
    if not pieces:
        return []
    owner = np.full(len(edges.xy), -1)
    for k, idx in enumerate(pieces):
        owner[idx] = k
    for idx in foreign or ():
        owner[idx] = -1
    label = np.repeat(np.arange(len(fitted)), [len(f) for f in fitted])
    pts = np.concatenate(fitted)
    near = cKDTree(edges.xy[pts]).sparse_distance_matrix(cKDTree(edges.xy), reach, output_type="coo_matrix")
    # A line's neighbour across a split lies the trim (3 sigma + 1 px) away
    # along the edge, beyond the reach while the edge width is below
    # sigma + 1/3 px, as in a sharp image. In a blurrier image the end
    # points within the reach of that neighbour go too: right at a corner,
    # a small loss where the split cut one straight edge.
    other = (owner[near.col] != label[near.row]) & (near.data < reach)
    bad = np.zeros(len(pts), bool)
    bad[near.row[other]] = True
    return np.split(bad, np.cumsum([len(f) for f in fitted])[:-1])


def segment_contours(edges, contours=None, *, min_length=10, **kwargs):
    """Segment every contour of an image.

    The contours are segmented side by side, the trial fits of all of them
    run together (see :func:`_segment_steps`); the result is that of
    :func:`segment_contour` on each.

    Parameters
    ----------
    edges : EdgePoints
    contours : list of Contour, optional
        Default ``chain_edges(edges)``.
    min_length : int
        Contours with fewer points are skipped.
    **kwargs
        Passed to :func:`segment_contour`.

    Returns
    -------
    list of Segment
    """
    if contours is None:
        contours = chain_edges(edges)
    # segment_contour's options and defaults, contour_id aside.
    opts = {k: v for k, v in segment_contour.__kwdefaults__.items() if k != "contour_id"}
    unknown = set(kwargs) - set(opts)
    if unknown:
        raise TypeError(f"segment_contours() got unexpected keyword arguments {sorted(unknown)}")
    opts.update(kwargs)
    refit = opts.pop("refit")
    todo = [(k, c) for k, c in enumerate(contours) if len(c) >= min_length]
    accepted = _run_steps([_segment_steps(edges, c, **opts) for _, c in todo])
    return _make_segments(edges, [c for _, c in todo], [k for k, _ in todo], accepted, refit, opts["min_points"])
