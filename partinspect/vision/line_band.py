"""Where the apparent edge of a broken straight edge lies across its band, predicted from the light on the part.

A straight edge between two planar faces is broken (rounded or chamfered,
ISO 13715) while its CAD edge is sharp, and the detector's step lies
somewhere across the break's band. :mod:`partinspect.vision.band_place`
predicts that place for a hole's rim; this module does the same for a
straight edge of the registered part:

1. *The light.* A Lambertian face of outward unit normal ``n`` under a
   distant light has the grey ``max(0, n . k) + a`` [1]_. The greys of the
   planar faces read beside the broken edges (both images, a median per
   face) give ``n . k`` of each face seen, ``g - a``; one light for the
   part, ``k``, fitted to them where three independent normals are seen,
   gives it for a face no camera sees. The ambient ``a`` is not told by
   three faces: it is carried as a range, from 0 to the darkest face's
   grey (no face is darker than the ambient), the place taken at both ends
   and midway (:func:`face_light`).
2. *The section.* Across a fillet tangent to both faces the normal turns
   from one face's to the other's, ``n = w1 n1 + w2 n2`` (spherical
   interpolation); across a chamfer it is their bisector
   (:func:`edge_section`). Projected into each camera at stations along
   the edge, up to where the band turns away from the camera (its
   occluding contour, on an edge one of whose faces the camera does not
   see), between the grey read beyond the band's face end and the grey
   read past its seen end, it is the profile
   :func:`partinspect.vision.band_place.band_profile` blurs by the
   image's edge width; :func:`partinspect.vision.band_place.apparent_place`
   gives the steepest step and a rival.
3. *The place and its Type B.* At each station the place is taken midway
   between the extremes the shapes (fillet, chamfer: ISO 13715 leaves the
   shape open), the rival steps and the ambient's range give, their range
   a rectangular distribution (JCGM 100, 4.3.7). Along a straight edge the
   place changes only with the perspective, so the stations' places are
   fitted by a straight line in the station (stations that disagree, where
   a read fell on another edge, left out): a station's own error would
   otherwise bend the line moved by it. The mean of the predicted
   less the image's own steepest places along the edge
   (:func:`partinspect.vision.band_place.observed_place`), with its
   standard error (the step's error is one offset along a line), is the
   model's misfit, a Type B component of its own. The caller reads it at
   the pose registered on the apparent steps, each carrying the whole
   band: a pose registered on the lines moved would take up the error
   their places share (one light, one break shape) and read it as no
   misfit; this one's own error, within its covariance, counts as misfit
   (conservative).

:func:`lines_at_sharp_edge` moves each measured line's points by their
station's place onto the sharp edge's image and fits it again, each point
carrying only the prediction's standard uncertainty instead of the whole
band; a line whose place is predicted no better than the uniform band
keeps the band.

Frames: edge geometry in the part frame (mm), the pose ``part_to_camera``
into the left camera (the rig frame), images in distorted pixels.

References
----------
.. [1] B. K. P. Horn, Robot Vision, MIT Press, 1986, chapter 10 (image
       irradiance of a Lambertian surface).
.. [2] ISO 13715:2019, Technical product documentation -- Edges of
       undefined shape -- Indication and dimensioning.
.. [3] JCGM 100:2008 (GUM), 4.3.7 (rectangular distribution).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from partinspect.vision.band_place import (READ_WIDTHS, SECTION_SAMPLES, apparent_place, camera_views, observed_place,
                                           read_grey, refit_pair, with_refitted)
from partinspect.vision.calibration import project_points
from partinspect.vision.fitting import fit_line

__all__ = ["BrokenLine", "LinePlace", "edge_section", "face_light", "line_place", "line_places",
           "lines_at_sharp_edge"]

STATIONS = 15
"""Stations along the edge (between 5 % and 95 % of its length) at which the band is predicted."""

AMBIENTS = 3
"""Ambient levels tried across its range (both ends and midway)."""

NEAR_FEATURE = 3.0
"""px: a station counts where the measured line's points lie this near its sharp image (the edge seen there)."""

MIN_STATIONS = 3
"""Stations an image must see for its place to be predicted."""


@dataclass(frozen=True)
class BrokenLine:
    """A straight broken edge between two planar faces, part frame (mm).

    Attributes
    ----------
    start, end : ndarray, shape (3,)
    faces : (str, str)
        The two faces' ids (their greys are read per face).
    normals : (ndarray, ndarray)
        Their outward unit normals, shape (3,) each.
    inward : (ndarray, ndarray)
        Unit vectors from the edge into each face, perpendicular to the edge.
    size : float
        The break's expected size (fillet's tangent length or chamfer's leg), mm.
    """

    start: np.ndarray
    end: np.ndarray
    faces: tuple
    normals: tuple
    inward: tuple
    size: float


@dataclass(frozen=True)
class LinePlace:
    """The predicted place of a broken line's step, per image.

    Attributes
    ----------
    stations : ndarray, shape (k,)
        Place along the edge, 0 at ``start``, 1 at ``end``.
    offsets : (ndarray, ndarray), shape (k,) each
        Per image, the step's place at each station, px along the image
        normal towards the first face from the sharp edge's image (NaN
        where not predicted).
    directions : (ndarray, ndarray), shape (k, 2) each
        Those unit image normals.
    observed : (ndarray, ndarray), shape (k,) each
        Per image, the image's own steepest place there, px (as ``offsets``).
    u_px : (float, float)
        Per image, the place's standard uncertainty, px: the shapes',
        rivals' and ambient's range (rectangular) and the misfit.
    u_shape, u_model : (float, float)
        Per image, the two components, px.
    u : float
        The place's standard uncertainty as a distance across the edge, mm
        (the larger image's ``u_px`` at its depth): what each point of the
        line carries as its Type B.
    """

    stations: np.ndarray
    offsets: tuple
    directions: tuple
    observed: tuple
    u_px: tuple
    u_shape: tuple
    u_model: tuple
    u: float


def edge_section(normals, inward, shape, n=SECTION_SAMPLES):
    """A unit break's section across a convex straight edge, from the first face (index 0) to the second.

    Parameters
    ----------
    normals : (ndarray, ndarray)
        The faces' outward unit normals n1, n2, shape (3,).
    inward : (ndarray, ndarray)
        Unit vectors t1, t2 from the edge into each face, perpendicular to it.
    shape : {"fillet", "chamfer"}
        A fillet tangent to both faces at unit distance from the sharp edge
        (radius ``tan(beta / 2)``, beta the faces' interior angle: 1 at a
        right angle), or a chamfer with unit legs.
    n : int

    Returns
    -------
    points : ndarray, shape (n, 3)
        Offsets from the sharp edge per unit break size.
    w1, w2 : ndarray, shape (n,)
        The section's unit normal as ``w1 n1 + w2 n2``.
    """
    n1, n2 = (np.asarray(v, float) for v in normals)
    t1, t2 = (np.asarray(v, float) for v in inward)
    tau = np.linspace(0.0, 1.0, n)
    if shape == "chamfer":
        w = np.full(n, 1.0 / np.linalg.norm(n1 + n2))
        return (1.0 - tau)[:, None] * t1 + tau[:, None] * t2, w, w
    gamma = math.acos(float(np.clip(n1 @ n2, -1.0, 1.0)))  # the normal turns by this across the fillet
    r = math.tan(0.5 * (math.pi - gamma))
    w1, w2 = np.sin((1.0 - tau) * gamma) / math.sin(gamma), np.sin(tau * gamma) / math.sin(gamma)
    return (t1 - r * n1)[None] + r * (w1[:, None] * n1 + w2[:, None] * n2), w1, w2


def _frame(cam, p, edge_dir, t1):
    """The sharp edge's pixels at points ``p`` (k, 3) and unit image normals towards the first face (k, 2)."""
    K, D, R, t, _, _ = cam
    uv0 = project_points(p, K, D, R, t)
    along = project_points(p + 0.01 * edge_dir, K, D, R, t) - uv0
    d = np.c_[-along[:, 1], along[:, 0]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    towards = project_points(p + 0.01 * t1, K, D, R, t) - uv0
    return uv0, d * np.sign(np.einsum("ij,ij->i", d, towards) + 1e-300)[:, None]


def _face_reads(line, cam, image, p, width):
    """Grey levels of each face read beside the band (READ_WIDTHS edge widths past it), where the camera sees it."""
    K, D, R, t, C, _ = cam
    out = []
    for n_f, t_f in zip(line.normals, line.inward):
        seen = (C - p) @ n_f > 0
        uv0 = project_points(p, K, D, R, t)
        px_per_mm = np.linalg.norm(project_points(p + t_f, K, D, R, t) - uv0, axis=1)
        ok = seen & np.isfinite(px_per_mm) & (px_per_mm > 1e-6)
        reach = line.size + READ_WIDTHS * width / np.where(ok, px_per_mm, 1.0)
        uv = project_points(p + reach[:, None] * t_f, K, D, R, t)
        ok &= np.isfinite(uv).all(1)
        out.append(read_grey(image, uv[ok]))
    return out


def face_light(greys, normals):
    """Each face's ``n . k`` for each ambient of its range, from the greys of the faces seen.

    Parameters
    ----------
    greys : dict of str to float
        Face id -> its grey level read beside the edges (median), for the faces seen.
    normals : dict of str to ndarray
        Face id -> outward unit normal, part frame, for every face wanted
        (seen or not).

    Returns
    -------
    list of (float, dict of str to float or None)
        Per ambient ``a`` (``AMBIENTS`` values from 0 to the darkest grey
        seen): ``a`` and each face's ``n . k``: ``g - a`` for a face seen;
        for one not seen, from the part's light ``k`` fitted to the faces
        seen (least squares), or None where they do not span three
        directions.
    """
    seen = [f for f in greys if f in normals]
    if not seen:
        return []
    N = np.array([normals[f] for f in seen])
    g = np.array([greys[f] for f in seen])
    spans = np.linalg.matrix_rank(N, tol=1e-3) == 3
    out = []
    for a in np.linspace(0.0, float(g.min()), AMBIENTS):
        k = np.linalg.lstsq(N, g - a, rcond=None)[0] if spans else None
        out.append((float(a), {f: (greys[f] - a if f in greys else (None if k is None else float(normals[f] @ k)))
                               for f in normals}))
    return out


def _seen_profile(cam, image, p, uv0, d, points, normal_w, normals, size, width):
    """The band of one shape at one station as one image sees it: (index of samples seen, u, g_face, g_past, observed).

    The band is seen from the end whose face looks at the camera up to
    where it turns away (its occluding contour); None if neither end faces
    the camera or fewer than two samples are seen.
    """
    K, D, R, t, C, _ = cam
    w1, w2 = normal_w
    P = p + size * points
    N = w1[:, None] * normals[0] + w2[:, None] * normals[1]
    facing = np.einsum("mk,mk->m", C - P, N) > 0
    index = np.arange(len(P))
    if not facing[0]:
        if not facing[-1]:
            return None
        index, facing = index[::-1], facing[::-1]
    m = int(np.argmin(facing)) if not facing.all() else len(facing)
    if m < 2:
        return None
    index = index[:m]
    uv = project_points(P[index], K, D, R, t)
    if not np.isfinite(uv).all():
        return None
    u = (uv - uv0) @ d
    out = math.copysign(READ_WIDTHS * width, u[0] - u[-1])
    g_face, g_past = read_grey(image, uv0 + np.array([u[0] + out, u[-1] - out])[:, None] * d)
    observed = observed_place(image, uv0, d, min(u[0], u[-1]) - width, max(u[0], u[-1]) + width)
    return index, u, float(g_face), float(g_past), observed


def _image_place(line, cam, image, stations, lights, width, near):
    """One image's predicted places along the line: (offsets, ranges, observed, depth), per station, px (NaN unseen)."""
    e = line.end - line.start
    length = float(np.linalg.norm(e))
    p_all = line.start + stations[:, None] * e
    uv0, d = _frame(cam, p_all, e / length, line.inward[0])
    k = len(stations)
    mid, rng, obs = np.full(k, np.nan), np.full(k, np.nan), np.full(k, np.nan)
    shapes = [edge_section(line.normals, line.inward, s) for s in ("fillet", "chamfer")]
    for i in np.flatnonzero(near):
        lo, hi, seen_obs = np.inf, -np.inf, None
        for points, w1, w2 in shapes:
            seen = _seen_profile(cam, image, p_all[i], uv0[i], d[i], points, (w1, w2), line.normals, line.size, width)
            if seen is None:
                continue
            index, u, g_face, g_past, seen_obs = seen
            for a, A, B in lights:
                grey = np.maximum(w1[index] * A + w2[index] * B, 0.0) + a
                place, other = apparent_place(u, grey, g_face, g_past, width)
                lo, hi = min(lo, place, other), max(hi, place, other)
        if np.isfinite(lo):
            mid[i], rng[i], obs[i] = 0.5 * (lo + hi), hi - lo, seen_obs
    K, D, R, t, _, _ = cam
    depth = float(np.median((p_all @ R.T + t)[:, 2]))
    return mid, rng, obs, d, depth


def _along_the_line(stations, mid):
    """The stations whose predicted place agrees with a straight line through the others (3 robust SD, 0.05 px floor).

    A station where the band's ends are read on another edge, or near the
    edge's end, predicts a place the rest of the line does not share.
    """
    ok = np.isfinite(mid)
    if ok.sum() < MIN_STATIONS:
        return ok
    for _ in range(2):
        r = mid - np.polyval(np.polyfit(stations[ok], mid[ok], 1), stations)
        scale = max(3.0 * 1.4826 * float(np.median(np.abs(r[ok]))), 0.05)
        ok = np.isfinite(mid) & (np.abs(np.nan_to_num(r, nan=np.inf)) <= scale)
        if ok.sum() < MIN_STATIONS:
            break
    return ok


def line_place(images, calib, part_to_camera, line, lights, width, uv=None, misfit=True):
    """The predicted place of one broken line's step in both images, or None where it cannot be predicted.

    Parameters
    ----------
    images : (ndarray, ndarray)
        Left and right grey images, float, shape (H, W).
    calib : StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
        The registered pose.
    line : BrokenLine
    lights : list of (float, float, float)
        ``(a, n1 . k, n2 . k)`` per ambient tried (:func:`face_light` for
        the line's two faces).
    width : (float, float)
        Each image's edge width (``EdgePoints.width``, median), px.
    uv : (ndarray, ndarray), optional
        The measured line's points in each image (distorted px): only
        stations where they lie near the sharp edge's image are predicted.

    Returns
    -------
    LinePlace or None
        None where an image sees fewer than ``MIN_STATIONS`` stations.
    """
    stations = np.linspace(0.05, 0.95, STATIONS)
    cams = camera_views(calib, part_to_camera)
    e = line.end - line.start
    offsets, dirs, seen, u_px, u_shape, u_model, u_mm = [], [], [], [], [], [], []
    for i, (image, cam) in enumerate(zip(images, cams)):
        near = np.ones(STATIONS, bool)
        if uv is not None:
            uv0 = project_points(line.start + stations[:, None] * e, *cam[:4])
            gap = np.linalg.norm(uv[i][None] - uv0[:, None], axis=2).min(axis=1)
            near = gap < NEAR_FEATURE
        mid, rng, obs, d, depth = _image_place(line, cam, image, stations, lights, width[i], near)
        ok = _along_the_line(stations, mid)
        if ok.sum() < MIN_STATIONS:
            return None
        # Along a straight edge the place changes only with the perspective: a straight line in the
        # station, fitted to the stations that agree, so that no station's read bends the line moved.
        mid = np.where(np.isfinite(mid), np.polyval(np.polyfit(stations[ok], mid[ok], 1), stations), np.nan)
        shape = math.sqrt(float(np.mean(rng[ok] ** 2)) / 12.0)
        # The step's error is one offset along the line: the mean misfit, with its own standard error.
        r = mid[ok] - obs[ok]
        model = math.sqrt(float(np.mean(r)) ** 2 + float(np.var(r)) / r.size) if misfit else 0.0
        offsets.append(mid)
        dirs.append(d)
        seen.append(obs)
        u_shape.append(shape)
        u_model.append(model)
        u_px.append(math.hypot(shape, model))
        u_mm.append(u_px[-1] * depth / float(cam[0][0, 0]))
    return LinePlace(stations, tuple(offsets), tuple(dirs), tuple(seen), tuple(u_px), tuple(u_shape), tuple(u_model), max(u_mm))


def line_places(images, calib, part_to_camera, lines, width, uv=None, misfit=True):
    """:func:`line_place` of every broken line, under one light for the part read off both images.

    Parameters
    ----------
    images, calib, part_to_camera, width
        As :func:`line_place` (images as recorded; read as float here).
    lines : dict of str to BrokenLine
    uv : dict of str to (ndarray, ndarray), optional
        Per line, its measured points in each image.
    misfit : bool
        As :func:`line_place`.

    Returns
    -------
    dict of str to LinePlace
        The lines whose place could be predicted.
    """
    images = tuple(np.asarray(image, float) for image in images)
    cams = camera_views(calib, part_to_camera)
    reads, normals = {}, {}
    for line in lines.values():
        p = line.start + np.linspace(0.05, 0.95, STATIONS)[:, None] * (line.end - line.start)
        for image, cam, w in zip(images, cams, width):
            for f, n_f, g in zip(line.faces, line.normals, _face_reads(line, cam, image, p, w)):
                normals[f] = n_f
                reads.setdefault(f, []).extend(g.tolist())
    greys = {f: float(np.median(g)) for f, g in reads.items() if len(g)}
    light = face_light(greys, normals)
    out = {}
    for cid, line in lines.items():
        lights = [(a, k[line.faces[0]], k[line.faces[1]]) for a, k in light]
        if not lights or any(A is None or B is None for _, A, B in lights):
            continue
        place = line_place(images, calib, part_to_camera, line, lights, width, None if uv is None else uv.get(cid),
                           misfit)
        if place is not None:
            out[cid] = place
    return out


def _moved(feature, cam, place, image_index, start, end, corr_length):
    """An image line with each point moved by minus its station's place (onto the sharp edge's image), refitted."""
    off, d = place.offsets[image_index], place.directions[image_index]
    ok = np.isfinite(off)
    uv0 = project_points(start + place.stations[:, None] * (end - start), *cam[:4])
    a, b = uv0[0], uv0[-1]
    ab = b - a
    # Each point's place along the edge, from its projection on the sharp edge's image.
    s = place.stations[0] + (place.stations[-1] - place.stations[0]) * ((feature.uv - a) @ ab) / float(ab @ ab)
    offset = np.interp(s, place.stations[ok], off[ok])
    direction = np.c_[np.interp(s, place.stations[ok], d[ok, 0]), np.interp(s, place.stations[ok], d[ok, 1])]
    shift = -offset[:, None] * direction
    xy = feature.ideal.xy + np.einsum("nij,nj->ni", feature.ideal.jacobian, shift)
    ideal = replace(feature.ideal, xy=xy)
    return replace(feature, uv=feature.uv + shift, ideal=ideal, fit=fit_line(xy, ideal.cov, corr_length=corr_length))


def lines_at_sharp_edge(stereo, calib, part_to_camera, matched, lines, places, band):
    """Broken lines refitted with their points moved onto the sharp edge's image by their predicted places.

    Each point then carries, in place of the whole band, the prediction's
    standard uncertainty ``LinePlace.u`` as the Type B of
    :func:`partinspect.vision.band_modes.edge_band` (one offset along the line).
    A line whose place is predicted no better than the uniform band
    (``u`` at least ``band``) is left as it was.

    Parameters
    ----------
    stereo : StereoResult
    calib : StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
        The registered pose.
    matched : dict of int to str
        Index into ``stereo.features`` of a measured line -> its CAD edge.
    lines : dict of str to BrokenLine
    places : dict of str to LinePlace
    band : float
        The uniform band's Type B, mm (``StereoResult.edge_break``).

    Returns
    -------
    stereo : StereoResult
        Those lines refitted (their image features too).
    refitted : set of str
    """
    L, R = stereo.left, stereo.right
    cams = camera_views(calib, part_to_camera)
    refits, refitted = {}, set()
    for k, cid in matched.items():
        place = places.get(cid)
        if place is None or place.u >= band:
            continue
        line, f3 = lines[cid], stereo.features[k]
        scale = L.features[f3.left].corr_length or float(L.edges.sigma)
        try:
            moved = [_moved(res.features[i], cam, place, j, line.start, line.end, scale)
                     for j, (res, i, cam) in enumerate(zip((L, R), (f3.left, f3.right), cams))]
        except (np.linalg.LinAlgError, ValueError):
            continue
        new = refit_pair(stereo, calib, k, moved, scale, place.u)
        if new is None:
            continue
        refits[k] = (*moved, new)
        refitted.add(cid)
    return with_refitted(stereo, refits), refitted
