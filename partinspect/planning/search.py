"""Search the part's pose on the fixture for one where every characteristic is decidable.

The fixture frame is the part frame in the starting pose (``--pose``, or the
simulator's default pose): its XY plane is the fixture's plate, Z its axis.
A fixture pose turns the part about that axis by ``rotation`` and tilts it
by ``tilt_x`` about the fixture's X axis and ``tilt_y`` about its Y axis,
all about the part's bounding-box centre, which stays where it was:

    R = R_start @ Rx(tilt_x) @ Ry(tilt_y) @ Rz(rotation)

The search is coarse to fine, to keep the number of predictions small
(each runs the whole covariance chain):

1. rotations over the allowed range at ``step`` degrees, untilted;
2. for the best two rotations, tilts of half and all of ``max_tilt`` about
   X and about Y, both senses;
3. around the best pose so far, half steps of rotation and tilt.

Poses are ranked first on the characteristics of the tolerance file
(``source == "spec"``): how many are decidable, then how many measurable;
then by :meth:`~partinspect.planning.predict.PosePrediction.score` over all
of them (decidable, measurable, the worst and the summed log ratio
``U / tolerance``).

A characteristic undecidable in every pose tried is reported with the
reason it had in the pose where it came closest, and how often each cause
occurred (hidden, edge-on, along the epipolar lines, ...).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

__all__ = ["FixturePose", "fixture_pose", "pose_text", "SearchResult", "search_poses", "rank_key", "cause_of"]


@dataclass(frozen=True)
class FixturePose:
    """Angles of a pose on the fixture, degrees."""

    rotation: float = 0.0
    tilt_x: float = 0.0
    tilt_y: float = 0.0

    @property
    def label(self):
        parts = [f"rotation {self.rotation:+.0f} deg"]
        if self.tilt_x or self.tilt_y:
            parts.append(f"tilt {self.tilt_x:+.1f} deg about X, {self.tilt_y:+.1f} deg about Y")
        else:
            parts.append("no tilt")
        return ", ".join(parts)

    def key(self):
        return (round(self.rotation, 6), round(self.tilt_x, 6), round(self.tilt_y, 6))


def _rot(axis, deg):
    from scipy.spatial.transform import Rotation

    v = np.zeros(3)
    v["xyz".index(axis)] = math.radians(deg)
    return Rotation.from_rotvec(v).as_matrix()


def fixture_pose(start, center, fp):
    """``part_to_camera`` of a fixture pose.

    Parameters
    ----------
    start : ndarray, shape (4, 4)
        The starting pose.
    center : ndarray, shape (3,)
        Bounding-box centre of the part, part frame (the pivot).
    fp : FixturePose

    Returns
    -------
    ndarray, shape (4, 4)
    """
    S = np.asarray(start, float)
    R = S[:3, :3] @ _rot("x", fp.tilt_x) @ _rot("y", fp.tilt_y) @ _rot("z", fp.rotation)
    pivot = S[:3, :3] @ center + S[:3, 3]
    P = np.eye(4)
    P[:3, :3] = R
    P[:3, 3] = pivot - R @ center
    return P


def pose_text(part_to_camera, center):
    """The ``--pose RX,RY,RZ,TX,TY,TZ`` text of a pose (as ``inspect render`` reads it).

    Angles: extrinsic rotations about the camera's x, y, z (degrees), the
    position: the bounding-box centre in the left camera frame (mm); see
    :func:`partinspect.poses.euler_pose`.
    """
    from scipy.spatial.transform import Rotation

    P = np.asarray(part_to_camera, float)
    ang = Rotation.from_matrix(P[:3, :3]).as_euler("xyz", degrees=True)
    pos = P[:3, :3] @ np.asarray(center, float) + P[:3, 3]
    return ",".join(f"{v:.3f}" for v in (*ang, *pos))


def rank_key(pred):
    """Sort key of a PosePrediction, larger is better (module notes)."""
    spec = [c for c in pred.characteristics if c.characteristic.source == "spec"]
    return (sum(c.decidable for c in spec), sum(math.isfinite(c.U) for c in spec)) + tuple(pred.score())


def cause_of(cp):
    """A short cause category of an undecidable CharacteristicPrediction."""
    r = cp.reason or ""
    if cp.decidable:
        return "decidable"
    if "edge-on" in r:
        return "edge-on"
    if "epipolar" in r and not math.isfinite(cp.U):
        return "along the epipolar lines"
    if "not visible" in r or "shows no edge" in r or "not in the" in r:
        return "hidden"
    if "registration" in r:
        return "not registered"
    if not math.isfinite(cp.U):
        return "not measurable"
    return "U too large"


@dataclass(frozen=True, eq=False)
class SearchResult:
    """Outcome of :func:`search_poses`.

    Attributes
    ----------
    start : PosePrediction
        The starting pose (fixture angles 0).
    best : PosePrediction
    poses : list of PosePrediction
        Every pose tried, in the order tried.
    never : list of (CharacteristicPrediction, str)
        Characteristics undecidable in every pose tried, each in the pose
        where its ratio was lowest, with a summary of the causes (general
        tolerances of edges out of view in every pose are not among them:
        ``inspect`` does not judge those).
    out_of_view : list of str
        Ids of the general-tolerance characteristics out of view in every
        pose tried.
    """

    start: object
    best: object
    poses: list
    never: list
    out_of_view: list


def _never_decidable(poses):
    out = []
    ids = [c.id for c in poses[0].characteristics]
    for k, cid in enumerate(ids):
        cps = [p.characteristics[k] for p in poses]
        if any(c.decidable for c in cps) or not any(c.inspected for c in cps):
            continue
        best = min(cps, key=lambda c: (c.ratio if not math.isnan(c.ratio) else math.inf, cause_of(c) != "U too large"))
        counts = Counter(cause_of(c) for c in cps)
        summary = ", ".join(f"{name} in {n} of {len(cps)} poses" for name, n in counts.most_common())
        out.append((best, summary))
    return out


def search_poses(predict, start, center, *, rotation=180.0, max_tilt=30.0, step=30.0, progress=None):
    """Find the fixture pose in which the most characteristics are decidable.

    Parameters
    ----------
    predict : callable
        ``predict(part_to_camera, fixture_pose) -> PosePrediction``.
    start : ndarray, shape (4, 4)
        The starting pose (fixture angles 0).
    center : ndarray, shape (3,)
        The part's bounding-box centre, part frame (the pivot).
    rotation : float
        Rotations from ``-rotation`` to ``+rotation`` degrees are allowed
        (180: a full turn).
    max_tilt : float
        Largest tilt about each fixture axis, degrees (0: no tilt).
    step : float
        Coarse rotation step, degrees.
    progress : callable, optional
        ``progress(message)`` per pose.

    Returns
    -------
    SearchResult
    """
    tried = {}
    order = []

    def run(fp):
        k = fp.key()
        if k not in tried:
            if abs(fp.rotation) > rotation + 1e-9 or max(abs(fp.tilt_x), abs(fp.tilt_y)) > max_tilt + 1e-9:
                return None
            if progress:
                progress(f"predicting pose {len(tried) + 1}: {fp.label}")
            tried[k] = predict(fixture_pose(start, center, fp), fp)
            order.append(tried[k])
        return tried[k]

    start_pred = run(FixturePose())
    best = start_pred
    if not start_pred.all_decidable and (rotation > 0 or max_tilt > 0):
        n = int(math.floor(rotation / step + 1e-9)) if step > 0 else 0
        rots = sorted({0.0} | {s * k * step for k in range(1, n + 1) for s in (-1, 1)})
        rots = [r for r in rots if not (rotation >= 180 and r == -180 and 180 in rots)]
        stage1 = [run(FixturePose(r)) for r in rots]
        stage1.sort(key=rank_key, reverse=True)
        best = stage1[0]
        if max_tilt > 0 and not best.all_decidable:
            for p in stage1[:2]:
                r = p.angles[0]
                for t in (0.5 * max_tilt, max_tilt):
                    for tx, ty in ((t, 0), (-t, 0), (0, t), (0, -t)):
                        q = run(FixturePose(r, tx, ty))
                        if q is not None and rank_key(q) > rank_key(best):
                            best = q
        if not best.all_decidable:
            r0, tx0, ty0 = best.angles
            hs, ht = 0.5 * step, 0.25 * max_tilt
            for dr, dx, dy in ((hs, 0, 0), (-hs, 0, 0), (0, ht, 0), (0, -ht, 0), (0, 0, ht), (0, 0, -ht)):
                if (dx or dy) and max_tilt <= 0:
                    continue
                q = run(FixturePose(r0 + dr, tx0 + dx, ty0 + dy))
                if q is not None and rank_key(q) > rank_key(best):
                    best = q
    out_of_view = [c.id for k, c in enumerate(order[0].characteristics)
                   if not any(p.characteristics[k].inspected for p in order)]
    return SearchResult(start_pred, best, order, _never_decidable(order), out_of_view)
