"""Lines measured where the CAD model puts them: a CAD edge's stretch of a longer image line.

Collinear edges of a part (the two lips of a slot in line, the edges of a
step on either side of a gap) are one straight line in each image. The
segmentation cannot see where one ends and the next begins, and the merge
of collinear pieces (:func:`partinspect.vision.imagefeatures.image_features`)
joins them across the gap, as it must join the pieces of one broken edge.
Their 3D line then spans both CAD edges and the registration matches it to
neither (a measured line's ends must lie on the CAD edge). Once the pose is
known, the CAD edge's image tells which stretch of such a line is its own:
the points within it, less a trim at each end where a third edge's
smoothing reaches, are fitted as an image feature of their own in each
image, and the pair is fitted in 3D as any matched pair is
(:func:`partinspect.vision.stereo.measure_pair_feature`).

The selection is by position along the edge only, never by residual, so it
leaves the fit's statistics as they are: the points' errors across the
edge are those of the same points in the longer line.
"""

from dataclasses import replace

import numpy as np
from scipy.linalg import block_diag

from partinspect.vision.contours import CLEARANCE, arc_length
from partinspect.vision.edges import BACKGROUND_DISTANCES
from partinspect.vision.fitting import fit_line, line_with_covariance
from partinspect.vision.ideal import IDEAL_FIELDS
from partinspect.vision.imagefeatures import arc_stretch, at_points
from partinspect.vision.matching import MIN_EPIPOLAR_ANGLE, Match, line_angles
from partinspect.vision.stereo import measure_pair_feature

MAX_DISTANCE = 2.0
"""A point belongs to an expected edge when it lies within this many px of
its image (the pose's error there is a few hundredths of a px on the sample
parts; the same distance as the report uses to say an edge was found)."""
MAX_ANGLE = np.deg2rad(3.0)
"""An image line runs along an expected edge when their directions differ
by less than this (the merge's tolerance for pieces of one line)."""
RIM_SHARE = 0.5
"""An unmatched arc is taken as a rim's (:func:`rims_along`) when more than
this share of its points have that rim's image the nearest of all the
edges' images, in each image: a majority, so that one edge at most can
claim an arc, whatever edges its other points lie nearest."""


def stretch_along(uv, polyline, *, max_distance=MAX_DISTANCE, trim=0.0):
    """Which points lie along an expected edge, and where along it.

    Parameters
    ----------
    uv : ndarray, shape (N, 2)
        Edge points, px (distorted).
    polyline : ndarray, shape (M, 2)
        The expected edge's image, densely sampled from one end to the other
        (at most a pixel apart), same pixels as ``uv``.
    max_distance : float
        Largest distance of a point from the polyline, px.
    trim : float
        Arc length left out at each end of the polyline, px.

    Returns
    -------
    inside : ndarray of bool, shape (N,)
    s : ndarray, shape (N,)
        Arc length of each point's nearest polyline sample from the first
        end, px.
    """
    from scipy.spatial import cKDTree

    uv = np.asarray(uv, float).reshape(-1, 2)
    poly = np.asarray(polyline, float)
    ok = np.isfinite(poly).all(axis=1)
    if ok.sum() < 2 or len(uv) == 0:
        return np.zeros(len(uv), bool), np.zeros(len(uv))
    poly = poly[ok]
    length = arc_length(poly)
    d, j = cKDTree(poly).query(uv)
    s = length[j]
    return (d <= max_distance) & (s >= trim) & (s <= length[-1] - trim), s


def line_stretch(feature, keep, corr_length):
    """An image line feature restricted to some of its points and fitted again.

    Parameters
    ----------
    feature : EdgeFeature
        A line (:class:`partinspect.vision.stereo.EdgeFeature`).
    keep : ndarray of int, shape (K,)
        Positions of the kept points in the feature's point arrays, in the
        order they are to have (along the edge).
    corr_length : float
        Correlation length of the points' noise along the edge, px.

    Returns
    -------
    EdgeFeature
        Same kind, segments, polarity and blur; its points, their ideal
        coordinates, edge normals and shading bounds those at ``keep``; its
        fit (with covariance) that of those points alone.
    """
    def fit(ideal):
        return line_with_covariance(fit_line(ideal.xy, ideal.cov, corr_length=corr_length, with_cov=False),
                                    ideal.xy, corr_length)

    return at_points(feature, keep, fit, _LINE_POINT_FIELDS)


_LINE_POINT_FIELDS = ("edge_normal", "background_bound", "band_shift", "phase_factor")


def _gather(features, candidates, polyline, trim, min_points, crowd=None, cid=None, reach=MAX_DISTANCE):
    """The points of ``features[candidates]`` along ``polyline``: (feature, positions) pieces, or None.

    ``crowd``: a :class:`_Crowd`; points within ``reach`` of another
    edge's image than ``cid``'s are not taken.
    """
    a, b = polyline[0], polyline[-1]
    d = (b - a) / max(np.hypot(*(b - a)), 1e-12)
    picked = []
    for i in candidates:
        f = features[i]
        if f.kind != "line" or abs(f.fit.direction @ d) < np.cos(MAX_ANGLE):
            continue
        inside, s = stretch_along(f.uv, polyline, trim=trim)
        if crowd is not None and inside.any():
            inside[inside] = crowd.clear_of_others(f.uv[inside], cid, reach)
        if inside.any():
            picked.append((i, np.flatnonzero(inside), s[inside]))
    if sum(len(k) for _, k, _ in picked) < min_points:
        return None
    return picked


class _Crowd:
    """The edges' images in one image, to tell which points lie near an edge other than a given one."""

    def __init__(self, images, side):
        from scipy.spatial import cKDTree

        polys = [np.asarray(pair[side], float) for pair in images.values()]
        polys = [p[np.isfinite(p).all(axis=1)] for p in polys]
        self.ids = list(images)
        self.owner = np.repeat(np.arange(len(polys)), [len(p) for p in polys])
        pts = np.concatenate(polys + [np.zeros((0, 2))])
        self.tree = cKDTree(pts) if len(pts) else None

    def clear_of_others(self, uv, cid, reach, ignore=()):
        """Mask of the points ``uv`` farther than ``reach`` px from every edge's image but ``cid``'s (and ``ignore``'s)."""
        if self.tree is None or len(uv) == 0:
            return np.ones(len(uv), bool)
        own = self._indices((cid, *ignore))
        near = self.tree.query_ball_point(uv, reach)
        return np.array([np.isin(self.owner[n], own).all() for n in near], bool)

    def crowding(self, uv, cid, reach, ignore=()):
        """The edge other than ``cid`` (and ``ignore``) whose image lies within ``reach`` px of most of ``uv`` (None: none)."""
        own = self._indices((cid, *ignore))
        hits = [np.unique(self.owner[n]) for n in self.tree.query_ball_point(uv, reach)] if self.tree else []
        return self._most(np.concatenate([h[~np.isin(h, own)] for h in hits] + [np.zeros(0, int)]))[0]

    def nearest_other(self, uv, cid):
        """The edge other than ``cid`` whose image lies nearest to most of the points ``uv`` (None: no other)."""
        _, j = self.tree.query(uv, k=min(16, len(self.owner)))
        own = self.owner[np.reshape(j, (len(uv), -1))]
        other = own != self.ids.index(cid)
        rows = other.any(axis=1)
        return self._most(own[rows, other[rows].argmax(axis=1)])[0]

    def nearest(self, uv):
        """The edge whose image lies nearest to most of the points ``uv``, and the share of them it is nearest to."""
        _, j = self.tree.query(uv)
        cid, n = self._most(self.owner[j])
        return cid, n / len(uv)

    def _indices(self, ids):
        """Indices into ``ids`` of those of ``ids`` that have an image here."""
        return [self.ids.index(i) for i in ids if i in self.ids]

    def _most(self, owners):
        """The edge most of ``owners`` (indices into ``ids``, each a point's vote) name, and its votes: (None, 0) if none.

        Ties go to the edge first in ``ids``.
        """
        if not len(owners):
            return None, 0
        votes = np.bincount(owners)
        k = int(votes.argmax())
        return self.ids[k], int(votes[k])


def guided_lines(stereo, calib, expected, owned, *, others=None, min_points=12):
    """Measure expected line edges from the stretches of image lines that run along them.

    Parameters
    ----------
    stereo : StereoResult
    calib : StereoCalibration
    expected : dict of str to (ndarray (M, 2), ndarray (M, 2))
        Per edge to look for (a CAD id), its image in the left and the right
        image as dense polylines (distorted px), from the registered pose.
    owned : set of (str, int)
        Image features ("left"/"right", index) already measured as another
        edge: their points are not taken.
    others : dict of str to (ndarray (M, 2), ndarray (M, 2)), optional
        The images of every other edge, hidden ones too (same form as
        ``expected``): points within ``CLEARANCE`` edge widths (at least
        ``MAX_DISTANCE``) of another edge's image are not taken, as the
        segmentation keeps its points clear of other edges: that edge's
        smoothing reaches them, or they are its own (two parallel edges of
        a face seen edge-on lie on one image line in one image, and the
        other image then pins a 3D line near either edge, so a hidden edge
        could be measured from the visible one's points).
    min_points : int
        Points each image must give an edge (the matching's minimum).

    Returns
    -------
    stereo : StereoResult
        With, per edge found, the stretch's image feature appended to each
        image's features and its 3D line to ``features``; the 3D lines whose
        image features gave points are left out (those points now belong to
        the stretches); ``guided_failed`` holds ``failed``'s items.
    found : dict of str to int
        Edge -> index of its 3D line in the returned ``features``.
    failed : dict of str to str
        Edges whose stretches were found in both images but not measured,
        and why (too few correspondences, nearly along the epipolar lines).

    Notes
    -----
    Each stretch leaves out ``3 sigma + 1`` px (sigma the edge filter's
    scale) at either end of the edge's image, as the segmentation trims its
    pieces' ends: the smoothing of the edges meeting there reaches that far.
    """
    L, R, geo = stereo.left, stereo.right, stereo.geometry
    sigma = float(L.edges.sigma)
    trim = 3.0 * sigma + 1.0
    free = {side: [i for i, f in enumerate(res.features) if f.kind == "line" and (side, i) not in owned]
            for side, res in (("left", L), ("right", R))}
    images = {**(others or {}), **expected}
    crowds = [_Crowd(images, 0), _Crowd(images, 1)]
    reach = [max(MAX_DISTANCE, CLEARANCE * float(np.median(res.edges.width))) if len(res.edges.width)
             else MAX_DISTANCE for res in (L, R)]
    lefts, rights, feats3, found, failed, donors = [], [], [], {}, {}, set()
    for cid, (poly_l, poly_r) in expected.items():
        pieces = []
        for k, (side, res, poly) in enumerate((("left", L, poly_l), ("right", R, poly_r))):
            poly = np.asarray(poly, float)
            poly = poly[np.isfinite(poly).all(axis=1)]
            if len(poly) < 2:
                break
            got = _gather(res.features, free[side], poly, trim, min_points, crowds[k], cid, reach[k])
            if got is None:
                break
            pieces.append(got)
        if len(pieces) < 2:
            continue
        # One image line usually; two when the edge broke and its pieces were
        # not merged. Taken in order along the edge.
        # Image lines added from another adaptive round carry their own filter scale.
        scale = L.features[pieces[0][0][0]].corr_length or sigma
        fl, fr = (line_stretch(_concat([res.features[i] for i, _, _ in got], [k for _, k, _ in got]),
                               np.argsort(np.concatenate([s for _, _, s in got]), kind="stable"), scale)
                  for res, got in zip((L, R), pieces))
        angle = min(line_angles(geo, [fl], "left")[0], line_angles(geo, [fr], "right")[0])
        if angle < MIN_EPIPOLAR_ANGLE:
            failed[cid] = (f"its stretch runs {np.degrees(angle):.1f} deg from the epipolar lines "
                           f"(< {np.degrees(MIN_EPIPOLAR_ANGLE):.0f})")
            continue
        nl, nr = len(L.features) + len(lefts), len(R.features) + len(rights)
        f3, why = measure_pair_feature(Match(nl, nr, float("nan"), float("nan"), float("nan"), float("inf")),
                                       fl, fr, calib, geo, scale, stereo.edge_break)
        if f3 is None:
            failed[cid] = why
            continue
        lefts.append(fl)
        rights.append(fr)
        feats3.append(replace(f3, guided=cid))
        found[cid] = len(feats3) - 1
        donors.update(("left", i) for i, _, _ in pieces[0])
        donors.update(("right", i) for i, _, _ in pieces[1])
    if not feats3:
        return (replace(stereo, guided_failed=tuple(failed.items())) if failed else stereo), {}, failed
    kept = [f for f in stereo.features
            if f.kind != "line" or (("left", f.left) not in donors and ("right", f.right) not in donors)]
    found = {cid: len(kept) + k for cid, k in found.items()}
    stereo = replace(stereo, left=replace(L, features=list(L.features) + lefts),
                     right=replace(R, features=list(R.features) + rights),
                     features=tuple(kept) + tuple(feats3), guided_failed=tuple(failed.items()))
    return stereo, found, failed


def clear_line_ends(stereo, calib, lines, images, *, min_points=12):
    """Measured lines fitted again without their points that lie near another edge's image.

    The segmentation keeps a line's ends clear of the other edges it can
    see (:func:`partinspect.vision.contours._crowded`), but not of an edge
    too faint to give edge points of its own, whose grey step the smoothing
    still mixes into the line's (at the corner of a thin face seen nearly
    edge-on, a wedge of darker grey between a bright face and the
    background): the line's last points are displaced by several of their
    standard uncertainties and set a short line's straightness. The same
    happens inside a line where such a face runs beside it over a stretch
    (a chamfer seen at grazing incidence along a silhouette, narrowing
    along it): the points there are pulled by a few tenths of a px, a bend
    that reads as form. Once the pose is known the CAD model says where
    every edge's image is.

    Parameters
    ----------
    stereo : StereoResult
    calib : StereoCalibration
    lines : dict of int to str
        Index into ``stereo.features`` of a measured line -> the CAD edge it
        was registered as.
    images : dict of str to (ndarray (M, 2), ndarray (M, 2))
        Per edge that shows in the images (the lines' own included), its
        image in the left and the right image as dense polylines (at most a
        pixel apart, distorted px, NaN where not projected).
    min_points : int
        Points each image must keep (the matching's minimum); a line that
        would keep fewer stays as it was.

    Returns
    -------
    stereo : StereoResult
        The lines that lost points refitted (their image features, same
        indices, and their 3D lines); everything else as it was.
    cleared : dict of str to (int, int)
        Edge -> points left out in the left and the right image.
    covered : dict of str to (str, str)
        Edges all of whose points in one image lie near another edge's
        image -> (that image, "left" or "right"; the other edge): the line
        may be that edge's image paired with this one's in the other image.
        Such a line is left as it was.

    Notes
    -----
    Points within ``CLEARANCE`` edge widths of another edge's image are left
    out wherever they lie along the line, by position alone, never by
    residual. The segmentation cuts a line back from its ends only
    (:func:`partinspect.vision.contours._make_segments`), since a crowded
    point inside a segment must not split it; here the line is one already,
    and its fit and its form need no unbroken run of points.
    """
    L, R, geo = stereo.left, stereo.right, stereo.geometry
    sigma = float(L.edges.sigma)
    crowds = [_Crowd(images, 0), _Crowd(images, 1)]
    reach = [CLEARANCE * float(np.median(res.edges.width)) if len(res.edges.width) else 0.0 for res in (L, R)]
    lefts, rights, feats = list(L.features), list(R.features), list(stereo.features)
    cleared, covered = {}, {}
    for k, cid in lines.items():
        f3 = stereo.features[k]
        if f3.kind != "line" or cid not in images:
            continue
        kept, lost = [], []
        for side, res in enumerate((L, R)):
            f = res.features[f3.left if side == 0 else f3.right]
            order = np.argsort(f.ideal.xy @ f.fit.direction, kind="stable")
            near = ~crowds[side].clear_of_others(f.uv[order], cid, reach[side])
            kept.append(order[~near])
            lost.append(int(near.sum()))
            if len(f.uv) and near.all() and cid not in covered:
                covered[cid] = (("left", "right")[side], crowds[side].nearest_other(f.uv, cid))
        if not any(lost) or min(len(x) for x in kept) < min_points:
            continue
        # A feature added from another adaptive round carries its own filter scale.
        scale = L.features[f3.left].corr_length or sigma
        fl, fr = (res.features[i] if not n else line_stretch(res.features[i], keep, scale)
                  for res, i, keep, n in zip((L, R), (f3.left, f3.right), kept, lost))
        new, _ = measure_pair_feature(Match(f3.left, f3.right, float("nan"), float("nan"), float("nan"), float("inf")),
                                      fl, fr, calib, geo, scale, stereo.edge_break)
        if new is None:
            continue
        lefts[f3.left], rights[f3.right] = fl, fr
        feats[k] = replace(new, guided=f3.guided)
        cleared[cid] = tuple(lost)
    if not cleared:
        return stereo, {}, covered
    return replace(stereo, left=replace(L, features=lefts), right=replace(R, features=rights),
                   features=tuple(feats)), cleared, covered


def clear_arc_ends(stereo, calib, arcs, images, *, meets=None, min_points=12):
    """Measured arcs fitted again without their end points that lie near another edge's image.

    Where a rim passes out of sight behind a face of the part, the edge
    that hides it (a counterbore's or a bore's upper rim, seen across the
    wall) runs into it in the image: over its last few px the rim and the
    occluding edge are closer than the edge filter's reach, the thin band
    of the wall between them is smoothed into both, and the rim's points
    are pushed off it, all to one side. They run up to the arc's ends,
    where they set its ellipse's extent: the measured circle comes out
    several tenths of a mm large, by many of its standard uncertainties
    (the fit's Type A sees a smooth arc). The segmentation keeps arcs'
    crowded points (:func:`partinspect.vision.contours._make_segments`:
    a rim's own two sides meet at its tips); once the pose is known, the
    other edges' images say which points another edge crowds: those
    within ``CLEARANCE`` edge widths of the reach of the shading reading
    (``max(BACKGROUND_DISTANCES)`` px) are left out, wherever they lie on
    the arc (an ellipse needs no run of points to stay one edge, unlike a
    line, :func:`clear_line_ends`), by position alone, never by residual.
    The same reading beside a hub's top rim, where the rim at its foot
    comes near it at the sides, turns a round rim out of round.

    Parameters
    ----------
    stereo : StereoResult
    calib : StereoCalibration
    arcs : dict of int to str
        Index into ``stereo.features`` of a measured circle -> the CAD edge
        it was registered as.
    images : dict of str to (ndarray (M, 2), ndarray (M, 2))
        As :func:`clear_line_ends`'s: per edge that shows in the images, its
        whole image in the left and the right image (distorted px), hidden
        stretches included: where a rim passes behind a face, the face's
        outline (no CAD edge) continues it in the image, and the hidden
        stretch's image stands for it.
    meets : dict of str to set of str, optional
        Per arc, the edges that meet it at its ends: they do not crowd it
        (where a slot's side runs tangentially into its round end, the
        side continues the same grey step; the segmentation ends the arc
        at the junction).
    min_points : int
        Points each image must keep; an arc that would keep fewer stays as
        it was, unless most of its points in that image are crowded: then
        the rim is not seen clear of the other edge there at all (a
        countersink's lower rim seen from below, the cone between it and the
        upper rim edge-on, a few px wide in the image, the two steps smoothed
        into one), and it is returned in ``crowded``.

    Returns
    -------
    stereo : StereoResult
        The arcs that lost points refitted (image features at the same
        indices, and their 3D circles); an arc whose refit fails, or whose
        two images' arcs are then not one circle, stays as it was.
    cleared : dict of str to (int, int)
        Edge -> points left out in the left and the right image.
    crowded : dict of str to str
        Edge -> why it is not measured: an image in which fewer than
        ``min_points`` of its points, and fewer than half, are clear of the
        other edges' images.

    References
    ----------
    .. [1] Canny, J. (1986). A computational approach to edge detection.
       IEEE TPAMI 8(6), 679-698 (section on the interaction of nearby
       edges under the smoothing filter).
    """
    L, R, geo = stereo.left, stereo.right, stereo.geometry
    sigma = float(L.edges.sigma)
    crowds = [_Crowd(images, 0), _Crowd(images, 1)]
    # The shading beside a rim is read up to max(BACKGROUND_DISTANCES) px
    # off it, and another edge's smoothing reaches CLEARANCE edge widths
    # beyond that reading.
    reach = [max(BACKGROUND_DISTANCES) + CLEARANCE * float(np.median(res.edges.width)) if len(res.edges.width)
             else 0.0 for res in (L, R)]
    lefts, rights, feats = list(L.features), list(R.features), list(stereo.features)
    cleared, crowded = {}, {}
    for k, cid in arcs.items():
        f3 = stereo.features[k]
        if f3.kind != "arc" or cid not in images:
            continue
        kept, lost = [], []
        for side, res in enumerate((L, R)):
            f = res.features[f3.left if side == 0 else f3.right]
            ignore = (meets or {}).get(cid, ())
            bad = ~crowds[side].clear_of_others(f.uv, cid, reach[side], ignore)
            kept.append(np.flatnonzero(~bad))
            lost.append(int(bad.sum()))
            if len(kept[-1]) < min(min_points, lost[-1]) and cid not in crowded:
                other = crowds[side].crowding(f.uv, cid, reach[side], ignore)
                crowded[cid] = (f"in the {('left', 'right')[side]} image {lost[-1]} of its {len(f.uv)} points lie "
                                f"within {reach[side]:.1f} px of {other}'s image, whose step the edge filter smooths "
                                f"into the rim's: too little of it is seen clear of it")
        if not any(lost) or min(len(x) for x in kept) < min_points:
            continue
        scale = L.features[f3.left].corr_length or sigma
        try:
            fl, fr = (res.features[i] if not n else arc_stretch(res.features[i], keep, scale)
                      for res, i, keep, n in zip((L, R), (f3.left, f3.right), kept, lost))
        except (np.linalg.LinAlgError, ValueError):
            continue
        new, _ = measure_pair_feature(Match(f3.left, f3.right, float("nan"), float("nan"), float("nan"), float("inf")),
                                      fl, fr, calib, geo, scale, stereo.edge_break)
        if new is None:
            continue
        lefts[f3.left], rights[f3.right] = fl, fr
        feats[k] = replace(new, guided=f3.guided)
        cleared[cid] = tuple(lost)
    if not cleared:
        return stereo, {}, crowded
    return replace(stereo, left=replace(L, features=lefts), right=replace(R, features=rights),
                   features=tuple(feats)), cleared, crowded


def rims_along(stereo, unmatched, rims, images):
    """Unmatched measured arcs that lie along a CAD rim's image in both images: index -> that rim's CAD id.

    A rim crowded by another edge near the ends of its visible arc is
    pushed off there (:func:`clear_arc_ends`), and a short arc's centre and
    radius follow its ends: the circle can come out further from its CAD
    rim than the registration's gates allow, so it is left unmatched and
    never cleared. Its image points still lie on the rim's image, within
    the crowding's fraction of a px. An arc is taken as a rim's when, in
    each image, more than half of its points (``RIM_SHARE``) have that
    rim's image as the nearest of all the edges' images and the median
    distance of all its points to it is within ``MAX_DISTANCE`` px (what
    makes a point an edge's, :func:`stretch_along`); the same rim in both
    images, and each rim taken by one arc at most (the nearest). By
    position alone: the arc is then cleared and refitted, and the
    registration judges it again with its unchanged gates.

    Parameters
    ----------
    stereo : StereoResult
    unmatched : sequence of int
        Indices into ``stereo.features`` of the measured circles the
        registration left unmatched.
    rims : set of str
        CAD ids of the round edges (circles and arcs) no measured feature
        was matched to.
    images : dict of str to (ndarray (M, 2), ndarray (M, 2))
        Every edge's whole image in the left and the right image (distorted
        px), as :func:`clear_arc_ends` takes them; the candidates among
        them are ``rims``.

    Returns
    -------
    dict of int to str
    """
    rims = [cid for cid in rims if cid in images]
    if not rims or not len(unmatched):
        return {}
    crowds = [_Crowd(images, 0), _Crowd(images, 1)]
    best = {}
    for k in unmatched:
        f3 = stereo.features[k]
        if f3.kind != "arc":
            continue
        found = []
        for side, res in enumerate((stereo.left, stereo.right)):
            uv = res.features[f3.left if side == 0 else f3.right].uv
            if crowds[side].tree is None or len(uv) == 0:
                break
            cid, share = crowds[side].nearest(uv)
            if cid not in rims or share <= RIM_SHARE:
                break
            poly = np.asarray(images[cid][side], float)
            poly = poly[np.isfinite(poly).all(axis=1)]
            d = np.median(np.min(np.linalg.norm(uv[:, None] - poly[None], axis=2), axis=1))
            if d > MAX_DISTANCE:
                break
            found.append((cid, d))
        if len(found) == 2 and found[0][0] == found[1][0]:
            cid, d = found[0][0], max(found[0][1], found[1][1])
            if cid not in best or d < best[cid][1]:
                best[cid] = (k, d)
    return {k: cid for cid, (k, _) in best.items()}


def _concat(features, positions):
    """One line feature of the points at ``positions`` of each of ``features`` (its fit the first's: refit it)."""
    first = features[0]
    ideal = replace(first.ideal, **{f: np.concatenate([getattr(g.ideal, f)[k] for g, k in zip(features, positions)])
                                    for f in IDEAL_FIELDS})
    extra = {name: np.concatenate([getattr(g, name)[k] for g, k in zip(features, positions)])
             if all(getattr(g, name) is not None for g in features) else None
             for name in _LINE_POINT_FIELDS if name != "phase_factor"}
    factors = [getattr(g, "phase_factor", None) for g in features]
    if any(F is not None for F in factors):
        # Each piece's ripple correction is its own: one block of columns each.
        extra["phase_factor"] = block_diag(*[np.zeros((len(k), 0)) if F is None else F[k]
                                             for F, k in zip(factors, positions)])
    return replace(first, segments=tuple(s for g in features for s in g.segments),
                   index=np.concatenate([g.index[k] for g, k in zip(features, positions)]),
                   uv=np.concatenate([g.uv[k] for g, k in zip(features, positions)]),
                   cov_uv=np.concatenate([g.cov_uv[k] for g, k in zip(features, positions)]),
                   ideal=ideal, **extra)

