"""Hypothesis search for the part's pose: poses from feature pairs, scored by what they explain.

Every pair of measured circles is compared with every ordered pair of CAD
circles or arcs whose radii agree (``RADIUS_GATE``, mm), whose centre
distance agrees (``DISTANCE_GATE``, mm) and whose normals make the same
angle (``ANGLE_GATE``, rad; a measured normal's sign is unobservable, so
both signs are tried). Each consistent pairing gives a rotation aligning
the centre-to-centre vector and the two normals (weighted Kabsch / Wahba
least squares) and a translation from the centroids [1]_ [2]_ [3]_. With
fewer than two circles, or when circle pairs give nothing, pairs of
non-parallel measured lines are matched to CAD line pairs with the same
angle and common-perpendicular length.

Each pose is scored by the number of measured features it explains: a
circle when a CAD circle or arc of similar radius lies within
``MATCH_GATE`` of its centre with a parallel normal, a line when a CAD line
runs parallel within ``MATCH_GATE`` of both its measured end points and the
measured stretch lies on the CAD segment. CAD features all of whose faces
are planes turned away from the camera never count. Equal scores are
ordered by the summed squared distances over ``MATCH_GATE``. The poses are
scored in batches, one array operation per batch, and the best-scoring ones
grouped into distinct poses (within 2 degrees and 2 mm) for the refinement
(:mod:`partinspect.cad.pose_refine`).

References
----------
.. [1] Arun, K. S., Huang, T. S., & Blostein, S. D. (1987). Least-squares
       fitting of two 3-D point sets. IEEE PAMI 9(5), 698-700.
.. [2] Umeyama, S. (1991). Least-squares estimation of transformation
       parameters between two point patterns. IEEE PAMI 13(4), 376-380.
.. [3] Kabsch, W. (1976). A solution for the best rotation to relate two
       sets of vectors. Acta Cryst. A32, 922-923.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from partinspect.errors import InputError

__all__ = [
    "RegistrationError",
    "CadArrays",
    "MeasuredArrays",
    "cad_arrays",
    "measured_arrays",
    "initial_poses",
    "distinct_best",
    "match",
    "same_pose",
    "unit",
    "line_extent",
    "axis_cov",
    "RADIUS_GATE",
    "DISTANCE_GATE",
    "ANGLE_GATE",
    "MATCH_GATE",
    "DIRECTION_GATE",
    "DIRECTION_GATE_SIGMAS",
    "DIRECTION_GATE_MAX",
]

RADIUS_GATE = 0.3
"""mm: a measured and a CAD radius this close may be the same edge (machining
tolerance plus a poorly measured radius)."""
DISTANCE_GATE = 0.3
"""mm: centre distances of two pairs agreeing this well may be the same pair."""
ANGLE_GATE = np.deg2rad(3.0)
"""rad: angles between normals (or lines) agreeing this well are the same."""
MATCH_GATE = 0.5
"""mm: a measured feature this close to a posed CAD feature is taken as it.
Large against the noise (microns), small against feature spacing (mm), and
loose enough to accept a feature machined a few tenths off."""
DIRECTION_GATE = np.deg2rad(2.0)
"""rad: a measured line or normal within this of a posed CAD one is parallel
(or within ``DIRECTION_GATE_SIGMAS`` of its own standard uncertainty, when
that is wider)."""
DIRECTION_GATE_SIGMAS = 4.0
"""A measured axis is gated at this many of its own standard uncertainties
when that is wider than ``DIRECTION_GATE``: a short or faint edge's direction
can be uncertain by a degree or more, and a fixed angle would refuse such an
edge that its own covariance explains. Its weight in the fit follows that
covariance."""
DIRECTION_GATE_MAX = np.deg2rad(10.0)
"""rad: however uncertain, a direction further off than this is not parallel."""
_SAME_POSE_ANGLE = np.deg2rad(2.0)
_SAME_POSE_SHIFT = 2.0  # mm
_MAX_LINE_SEEDS = 8  # longest measured lines used to seed line hypotheses
_MAX_DISTINCT = 12  # distinct best-scoring poses handed on to the refinement


class RegistrationError(InputError):
    """The measured features do not determine the part's pose uniquely.

    Raised by the search, the refinement (:mod:`partinspect.cad.pose_refine`)
    and :func:`partinspect.cad.registration.register`. An
    :class:`~partinspect.errors.InputError` (exit code 2, one line).
    """

    def __init__(self, problem):
        super().__init__(None, problem)


# ---------------------------------------------------------------------------
# measured records


def unit(v):
    """``v`` as a float array scaled to unit length."""
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def line_extent(rec):
    """Arc-length parameters of the measured end points along the record's line, or (None, None)."""
    s, e = getattr(rec, "start", None), getattr(rec, "end", None)
    if s is None or e is None:
        return None, None
    p, d = np.asarray(rec.point, float), unit(rec.direction)
    s0, s1 = float((np.asarray(s, float) - p) @ d), float((np.asarray(e, float) - p) @ d)
    return min(s0, s1), max(s0, s1)


def axis_cov(rec):
    """Covariance (3, 3) of a record's unit normal or direction.

    ``normal_cov`` / ``direction_cov`` (fit3d records) or ``axis_cov``
    (:class:`partinspect.vision.feature3d.Feature3D`).
    """
    for name in ("normal_cov", "direction_cov", "axis_cov"):
        v = getattr(rec, name, None)
        if v is not None:
            return np.asarray(v, float)
    raise AttributeError(f"{type(rec).__name__} has no normal/direction covariance")



# ---------------------------------------------------------------------------
# CAD side


@dataclass(frozen=True)
class CadArrays:
    """The CAD model's non-smooth edges as arrays, part frame, mm (:func:`cad_arrays`)."""

    round_ids: tuple
    centers: np.ndarray  # (K, 3)
    normals: np.ndarray
    radii: np.ndarray
    round_faces: np.ndarray  # (K, F, 3) outward normals of plane faces, zeros for curved ones, NaN-padded
    line_ids: tuple
    starts: np.ndarray  # (L, 3)
    dirs: np.ndarray
    lengths: np.ndarray
    line_faces: np.ndarray


def _face_normals(inventory, feature, width=2):
    """Outward normals of a feature's adjacent faces: a plane's normal, zeros for a curved face, NaN padding."""
    out = np.full((width, 3), np.nan)
    k = 0
    for fid in feature.faces:
        try:
            face = inventory[fid]
        except KeyError:
            continue
        if k < width:
            normal = getattr(face, "normal", None)
            out[k] = 0.0 if normal is None else normal
            k += 1
    return out


def cad_arrays(inventory):
    """The inventory's circles, arcs and lines as :class:`CadArrays`; smooth edges left out."""
    feats = [f for f in inventory.features if not f.smooth]
    rnd = [f for f in feats if f.kind in ("circle", "arc")]
    lines = [f for f in feats if f.kind == "line"]
    z3 = np.zeros((0, 3))
    return CadArrays(
        tuple(f.id for f in rnd),
        np.array([f.center for f in rnd], float).reshape(-1, 3) if rnd else z3,
        np.array([f.normal for f in rnd], float).reshape(-1, 3) if rnd else z3,
        np.array([f.radius for f in rnd], float),
        np.array([_face_normals(inventory, f) for f in rnd]).reshape(-1, 2, 3),
        tuple(f.id for f in lines),
        np.array([f.start for f in lines], float).reshape(-1, 3) if lines else z3,
        np.array([f.direction for f in lines], float).reshape(-1, 3) if lines else z3,
        np.array([np.linalg.norm(f.end - f.start) for f in lines], float),
        np.array([_face_normals(inventory, f) for f in lines]).reshape(-1, 2, 3),
    )


def _facing(face_normals, R, points_cam):
    """(B, K) True where a feature may be seen: some adjacent plane faces the camera, or a face is curved.

    ``R`` (B, 3, 3) and ``points_cam`` (B, K, 3) are B poses' rotations
    and the features' points in each camera frame; ``face_normals`` (K, F, 3)
    the adjacent faces' normals in the part frame (zero: curved; NaN: none).

    An edge between a plane turned away and a curved face shows where the
    curved face turns to the camera (the bottom end of the bracket's
    through slot, seen through the slot against the background, is such an
    arc), so it counts as seen.
    """
    # Which faces are known and which plane does not change with the pose.
    known = ~np.isnan(face_normals[..., 0])
    plane = known & (np.abs(np.nan_to_num(face_normals)).sum(axis=2) > 0)
    n = np.einsum("kfi,bji->bkfj", np.nan_to_num(face_normals), R)
    toward = np.einsum("bkfi,bki->bkf", n, -points_cam) > 0
    return (~plane.any(1) | (known & ~plane).any(1))[None] | (toward & plane[None]).any(2)


# ---------------------------------------------------------------------------
# measured side


@dataclass(frozen=True)
class MeasuredArrays:
    """The measured circles and lines as arrays, rig frame, mm (:func:`measured_arrays`)."""

    centers: np.ndarray
    normals: np.ndarray
    radii: np.ndarray
    points: np.ndarray  # lines
    dirs: np.ndarray
    ends: np.ndarray  # (N, 2, 3) measured extent end points (or +-5 mm)
    lengths: np.ndarray
    normal_cos: np.ndarray  # (M,) cosine of each circle's direction gate
    dir_cos: np.ndarray  # (N,) the same for lines


def _direction_gate_cos(rec):
    """Cosine of the angle within which a measured axis counts as parallel to a CAD one."""
    try:
        C = axis_cov(rec)
        u = float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (C + C.T))[-1], 0.0)))
    except (AttributeError, np.linalg.LinAlgError, ValueError):
        u = 0.0
    if not np.isfinite(u):
        u = 0.0
    return float(np.cos(np.clip(DIRECTION_GATE_SIGMAS * u, DIRECTION_GATE, DIRECTION_GATE_MAX)))


def measured_arrays(circles, lines):
    """Measured circle and line records (as :func:`partinspect.cad.registration.register` takes them) as :class:`MeasuredArrays`."""
    z3 = np.zeros((0, 3))
    ends, lens = [], []
    for rec in lines:
        p, d = np.asarray(rec.point, float), unit(rec.direction)
        s0, s1 = line_extent(rec)
        if s0 is None:
            s0, s1 = -5.0, 5.0  # no extent: judge the line by a short stretch
        ends.append([p + s0 * d, p + s1 * d])
        lens.append(s1 - s0)
    return MeasuredArrays(
        np.array([c.center for c in circles], float).reshape(-1, 3) if circles else z3,
        np.array([unit(c.normal) for c in circles], float).reshape(-1, 3) if circles else z3,
        np.array([c.radius for c in circles], float),
        np.array([l.point for l in lines], float).reshape(-1, 3) if lines else z3,
        np.array([unit(l.direction) for l in lines], float).reshape(-1, 3) if lines else z3,
        np.array(ends, float).reshape(-1, 2, 3),
        np.array(lens, float),
        np.array([_direction_gate_cos(c) for c in circles], float),
        np.array([_direction_gate_cos(l) for l in lines], float),
    )


# ---------------------------------------------------------------------------
# hypotheses


def _circle_hypotheses(meas, cad):
    """Poses from pairs of measured circles matched to pairs of CAD round features."""
    out = []
    m, k = len(meas.radii), len(cad.radii)
    if m < 2 or k < 2:
        return out
    rad_ok = np.abs(meas.radii[:, None] - cad.radii[None, :]) <= RADIUS_GATE  # (m, k)
    cad_d = np.linalg.norm(cad.centers[:, None] - cad.centers[None, :], axis=2)
    cad_cos = np.abs(cad.normals @ cad.normals.T)
    for i in range(m):
        for j in range(i + 1, m):
            dm = np.linalg.norm(meas.centers[j] - meas.centers[i])
            if dm < 1e-6:
                continue  # concentric circles: no baseline
            am = np.arccos(min(1.0, abs(meas.normals[i] @ meas.normals[j])))
            ok = rad_ok[i][:, None] & rad_ok[j][None, :]
            ok &= np.abs(cad_d - dm) <= DISTANCE_GATE
            ok &= np.abs(np.arccos(np.clip(cad_cos, -1, 1)) - am) <= ANGLE_GATE
            np.fill_diagonal(ok, False)
            for a, b in zip(*np.nonzero(ok)):
                base_m = meas.centers[j] - meas.centers[i]
                base_c = cad.centers[b] - cad.centers[a]
                for si in (1.0, -1.0):
                    for sj in (1.0, -1.0):
                        target = np.stack([base_m / dm, meas.normals[i], meas.normals[j]])
                        source = np.stack([base_c / dm, si * cad.normals[a], sj * cad.normals[b]])
                        R = _align(target, source, np.array([2.0, 1.0, 1.0]))
                        if R is None:
                            continue
                        t = 0.5 * (meas.centers[i] + meas.centers[j]) - R @ (0.5 * (cad.centers[a] + cad.centers[b]))
                        out.append((R, t))
    return out


def _align(target, source, weights):
    """Rotation R minimising sum w |target - R source|^2 (Kabsch), or None if degenerate."""
    H = (source * weights[:, None]).T @ target
    U, s, Vt = np.linalg.svd(H)
    if s[1] < 1e-6 * max(s[0], 1e-30):
        return None  # all vectors parallel: rotation about them undetermined
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def _common_perpendicular(p1, d1, p2, d2):
    """Midpoint and length of the common perpendicular of two non-parallel lines."""
    w = p1 - p2
    b = d1 @ d2
    den = 1.0 - b * b
    s = (b * (d2 @ w) - (d1 @ w)) / den
    u = ((d2 @ w) - b * (d1 @ w)) / den
    q1, q2 = p1 + s * d1, p2 + u * d2
    return 0.5 * (q1 + q2), float(np.linalg.norm(q1 - q2))


def _line_hypotheses(meas, cad):
    """Poses from pairs of non-parallel measured lines matched to CAD line pairs."""
    out = []
    order = np.argsort(-meas.lengths)[:_MAX_LINE_SEEDS]
    L = len(cad.lengths)
    if len(order) < 2 or L < 2:
        return out
    cad_cos = np.abs(cad.dirs @ cad.dirs.T)
    for ii, i in enumerate(order):
        for j in order[ii + 1 :]:
            c = abs(meas.dirs[i] @ meas.dirs[j])
            if c > np.cos(np.deg2rad(10.0)):
                continue  # near-parallel pairs fix the pose poorly
            vm, hm = _common_perpendicular(meas.points[i], meas.dirs[i], meas.points[j], meas.dirs[j])
            ang = np.arccos(min(1.0, c))
            ok = np.abs(np.arccos(np.clip(cad_cos, -1, 1)) - ang) <= ANGLE_GATE
            ok &= (cad.lengths[:, None] >= meas.lengths[i] - 2 * MATCH_GATE) & (cad.lengths[None, :] >= meas.lengths[j] - 2 * MATCH_GATE)
            np.fill_diagonal(ok, False)
            for a, b in zip(*np.nonzero(ok)):
                vc, hc = _common_perpendicular(cad.starts[a], cad.dirs[a], cad.starts[b], cad.dirs[b])
                if abs(hc - hm) > DISTANCE_GATE:
                    continue
                for si in (1.0, -1.0):
                    for sj in (1.0, -1.0):
                        da, db = si * cad.dirs[a], sj * cad.dirs[b]
                        target = np.stack([meas.dirs[i], meas.dirs[j], np.cross(meas.dirs[i], meas.dirs[j])])
                        source = np.stack([da, db, np.cross(da, db)])
                        R = _align(target, source, np.ones(3))
                        if R is None:
                            continue
                        out.append((R, vm - R @ vc))
    return out


# ---------------------------------------------------------------------------
# scoring and matching


def _candidates(meas, cad, R, t, gate=MATCH_GATE):
    """Distances of the candidate pairs under B poses: circles (B, m, K), lines (B, n, L), inf where not a candidate.

    ``R`` (B, 3, 3), ``t`` (B, 3). A circle pairs with a CAD round feature
    within ``gate`` of its centre, of its radius within ``RADIUS_GATE`` and
    its axis within the measured axis' gate, and that may be seen; a line
    with a CAD line parallel within its gate whose extent covers the
    measured ends (plus ``gate``) at most ``gate`` off it, and that may be
    seen.
    """
    B = len(R)
    dc = np.full((B, len(meas.radii), len(cad.radii)), np.inf)
    if len(meas.radii) and len(cad.radii):
        cc = cad.centers @ R.transpose(0, 2, 1) + t[:, None]  # (B, K, 3)
        nn = cad.normals @ R.transpose(0, 2, 1)
        d = np.linalg.norm(meas.centers[None, :, None] - cc[:, None], axis=3)
        ok = d <= gate
        ok &= (np.abs(meas.radii[:, None] - cad.radii[None]) <= RADIUS_GATE)[None]
        ok &= np.abs(np.einsum("mi,bki->bmk", meas.normals, nn)) >= meas.normal_cos[None, :, None]
        ok &= _facing(cad.round_faces, R, cc)[:, None]
        dc = np.where(ok, d, np.inf)
    dl = np.full((B, len(meas.lengths), len(cad.lengths)), np.inf)
    if len(meas.lengths) and len(cad.lengths):
        s = cad.starts @ R.transpose(0, 2, 1) + t[:, None]  # (B, L, 3)
        u = cad.dirs @ R.transpose(0, 2, 1)
        mid_cad = s + 0.5 * cad.lengths[None, :, None] * u
        # The distances only of the parallel pairs (a third or less of them).
        b, j, l = np.nonzero(np.abs(np.einsum("ni,bli->bnl", meas.dirs, u)) >= meas.dir_cos[None, :, None])
        sp, up = s[b, l], u[b, l]
        dist = np.zeros(len(b))
        inside = np.ones(len(b), bool)
        for e in range(2):
            v = meas.ends[j, e] - sp
            along = np.einsum("pi,pi->p", v, up)
            dist = np.maximum(dist, np.linalg.norm(v - along[:, None] * up, axis=1))
            inside &= (along >= -gate) & (along <= cad.lengths[l] + gate)
        ok = inside & (dist <= gate) & _facing(cad.line_faces, R, mid_cad)[b, l]
        dl[b[ok], j[ok], l[ok]] = dist[ok]
    return dc, dl


def _assigned(dc, dl, gate=MATCH_GATE):
    """Correspondences of one pose's candidates (:func:`_candidates`): ({i: k}, {j: l}, cost).

    Circles one to one, nearest pair first; each line to its nearest CAD
    line. The cost sums the squared distances over ``gate``.
    """
    circ, lin, cost = {}, {}, 0.0
    pairs = np.flatnonzero(np.isfinite(dc))
    taken = set()
    for flat in pairs[np.argsort(dc.flat[pairs], kind="stable")]:
        i, k = divmod(int(flat), dc.shape[1])
        if i in circ or k in taken:
            continue
        circ[i] = k
        taken.add(k)
        cost += (dc[i, k] / gate) ** 2
    if dl.size:
        best = np.argmin(dl, axis=1)
        for j, l in enumerate(best):
            if np.isfinite(dl[j, l]):
                lin[j] = int(l)
                cost += (dl[j, l] / gate) ** 2
    return circ, lin, cost


def match(meas, cad, R, t, gate=MATCH_GATE):
    """Correspondences under a pose: ({i: k}, {j: l}, cost)."""
    dc, dl = _candidates(meas, cad, np.asarray(R, float)[None], np.asarray(t, float)[None], gate)
    return _assigned(dc[0], dl[0], gate)


_SCORE_BATCH = 150_000
"""Poses :func:`_scores` takes at once: as many as make about this many
elements in its largest arrays (B x m x K x 3 for the circles, B x n x L
for the lines' directions). Batches this small stay in the CPU's cache and
score faster than larger ones or one pose at a time."""


def _scores(meas, cad, hyps, gate=MATCH_GATE, batch=None):
    """Matched features and cost of each hypothesis (R, t): what :func:`match` gives, many poses at once.

    The candidates of a batch of poses are one array operation: the
    search scores tens of thousands of poses on a part with hundreds of
    edges. ``batch``: poses per batch (default: by ``_SCORE_BATCH``).
    """
    per_pose = max(1, len(meas.lengths) * len(cad.lengths), 3 * len(meas.radii) * len(cad.radii))
    step = batch or max(1, _SCORE_BATCH // per_pose)
    out = []
    for a in range(0, len(hyps), step):
        R = np.array([h[0] for h in hyps[a:a + step]], float)
        t = np.array([h[1] for h in hyps[a:a + step]], float)
        dc, dl = _candidates(meas, cad, R, t, gate)
        for b in range(len(R)):
            circ, lin, cost = _assigned(dc[b], dl[b], gate)
            out.append((len(circ) + len(lin), cost))
    return out


def _symmetric_model(cad):
    """True when the model's edges are circles on one axis and nothing else (exactly, as CAD is)."""
    if len(cad.line_ids) or len(cad.round_ids) == 0:
        return False
    n0 = unit(cad.normals[0])
    d = cad.centers - cad.centers[0]
    off_axis = d - np.outer(d @ n0, n0)
    scale = max(1.0, float(np.max(cad.radii)))
    return bool(np.all(np.abs(cad.normals @ n0) > 1.0 - 1e-9)
                and np.all(np.linalg.norm(off_axis, axis=1) < 1e-6 * scale))


def _coaxial(circles, rel=0.1, angle=np.deg2rad(10.0)):
    """True when the circles look coaxial: centres within ``rel`` of the largest
    radius (at least ``MATCH_GATE``) of the first one's axis, normals within ``angle``.

    Loose on purpose: it only chooses the wording of an error, and short arcs
    of a symmetric part are measured poorly."""
    if not circles:
        return False
    tol = max(MATCH_GATE, rel * max(float(c.radius) for c in circles))
    c0, n0 = np.asarray(circles[0].center, float), unit(np.asarray(circles[0].normal, float))
    for c in circles[1:]:
        d = np.asarray(c.center, float) - c0
        if np.linalg.norm(d - (d @ n0) * n0) > tol or abs(unit(np.asarray(c.normal, float)) @ n0) < np.cos(angle):
            return False
    return True


def same_pose(R1, t1, R2, t2):
    """True when two poses (R, t) differ by less than 2 degrees and 2 mm: one pose for the search."""
    ang = Rotation.from_matrix(R1.T @ R2).magnitude()
    return ang < _SAME_POSE_ANGLE and np.linalg.norm(t1 - t2) < _SAME_POSE_SHIFT


# ---------------------------------------------------------------------------
# the search


def initial_poses(meas, cad, circles, lines, pose_hint=None):
    """The pose hypotheses to score: ``[(R, t), ...]``, part to rig.

    Parameters
    ----------
    meas : MeasuredArrays
    cad : CadArrays
    circles, lines : sequence
        The measured records ``meas`` was made from (for the error wording).
    pose_hint : ndarray, shape (4, 4), optional
        A ``part_to_camera`` close enough to skip the search: the only
        hypothesis.

    Raises
    ------
    RegistrationError
        The model is rotationally symmetric (circles on one axis, no
        straight edge), or no pair of measured circles or lines matches it.
    """
    if pose_hint is not None:
        return [(np.asarray(pose_hint, float)[:3, :3], np.asarray(pose_hint, float)[:3, 3])]
    if _symmetric_model(cad):
        # A property of the model, whatever was measured (its short arcs
        # may even be measured as circles off the axis).
        raise RegistrationError(
            f"alignment is ambiguous: the CAD model's {len(cad.round_ids)} circles share one axis and it has no "
            "straight edge, so the rotation about that axis is undetermined (a rotationally symmetric part)"
        )
    hyps = _circle_hypotheses(meas, cad)
    if not hyps:
        hyps = _line_hypotheses(meas, cad)
    if not hyps and not lines and _coaxial(circles):
        raise RegistrationError(
            f"alignment is ambiguous: the {len(circles)} measured circles share one axis and no line was "
            "measured, so the rotation about that axis is undetermined (a rotationally symmetric view)"
        )
    if not hyps:
        raise RegistrationError(
            "alignment is ambiguous: no pair of measured circles or lines matches the CAD model "
            f"({len(circles)} circles, {len(lines)} lines measured)"
        )
    return hyps


def distinct_best(meas, cad, hyps):
    """The best-scoring hypotheses, one per distinct pose: ``[(R, t), ...]``, lowest cost first.

    Scores every hypothesis (:func:`_scores`), keeps those explaining the
    most measured features, and of poses within 2 degrees and 2 mm of an
    earlier (lower-cost) one keeps the earlier; at most ``_MAX_DISTINCT``.

    Raises
    ------
    RegistrationError
        No pose explains more than one measured feature.
    """
    scored = [(n, -cost, R, t) for (n, cost), (R, t) in zip(_scores(meas, cad, hyps), hyps)]
    best = max(s[0] for s in scored)
    if best < 2:
        raise RegistrationError("alignment is ambiguous: no pose explains more than one measured feature")
    top = sorted((s for s in scored if s[0] == best), key=lambda s: -s[1])
    clusters = []
    for s in top:
        if not any(same_pose(s[2], s[3], c[2], c[3]) for c in clusters):
            clusters.append(s)
        if len(clusters) >= _MAX_DISTINCT:
            break
    return [(R, t) for _, _, R, t in clusters]
