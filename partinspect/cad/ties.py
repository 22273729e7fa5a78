"""Poses that explain the measured features equally well: the model's own symmetry, or a real ambiguity.

Registration (:mod:`.registration`) refines the best distinct pose
hypotheses; two of them *tie* when they explain as many measured features
with chi-squares within ``AMBIGUITY_RATIO`` (plus a few standard deviations
of the chi-square). Where the CAD model maps onto itself under the turn
between two tied poses (:func:`model_symmetry`: a bolt circle, a square
plate), both give the same characteristics and the best is taken. Where it
does not, the measured features are symmetric and the model is not (the
clocking feature unseen): the tie is real, and each pose, one per class the
model's symmetry relates, is kept as a :class:`CompetingPose`
(:func:`competing_poses`), with the CAD edges that the turn moves where the
model has nothing like them (:func:`unmatched_under`) and that were not
measured: seen, they would tell.

References
----------
.. [1] Johnson, N. L., Kotz, S., & Balakrishnan, N. (1994). Continuous
       Univariate Distributions, vol. 1 (2nd ed.), Wiley, chapter 18: the
       chi-square on n degrees of freedom has mean n and variance 2n, so
       ``10 sqrt(n)`` is about seven of its standard deviations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from partinspect.cad.pose_refine import pose_error
from partinspect.cad.pose_search import MATCH_GATE, same_pose

__all__ = ["AMBIGUITY_RATIO", "CompetingPose", "ties", "first_hint_first", "competing_poses", "competing_pose",
           "ambiguity_words", "feature_order", "unmatched_under", "model_symmetry"]

AMBIGUITY_RATIO = 2.0
"""Two distinct poses whose chi-squares are within this factor (plus about
seven standard deviations of the chi-square) explain the data equally well."""


@dataclass(frozen=True, eq=False)
class CompetingPose:
    """A pose that explains the measured features as well as the chosen one, the CAD model not being symmetric under the turn.

    Attributes
    ----------
    registration : partinspect.cad.registration.Registration
        The pose refined on its own assignment of the measured features,
        its covariance and fit statistics.
    angle : float
        Degrees: the rotation between it and the chosen pose.
    shift : float
        mm: how far the CAD features move between the two poses (the
        largest), not the part's arbitrary origin.
    deciding : tuple of str
        CAD ids of the features the turn between the poses puts where the
        model has no feature of their kind and size (or brings one there
        from such a place): measured, any of them would tell the two poses
        apart.
    """

    registration: object
    angle: float
    shift: float
    deciding: tuple


def ties(first, other):
    """Whether refined pose ``other`` explains as many features about as well as ``first`` (``AMBIGUITY_RATIO``)."""
    return (other["score"] == first["score"]
            and other["chi2"] <= AMBIGUITY_RATIO * first["chi2"] + 10.0 * max(1, first["dof"]) ** 0.5)


def first_hint_first(results, hint):
    """``results`` with the pose refined from the first hint in front when it ties with the best.

    Measured again (another round, features added), tied poses swap places
    on chi-squares that differ by chance; the first hint, the pose chosen
    before, stays the chosen one, so that a CAD id names the same measured
    edge from round to round.
    """
    R, t = hint
    for j, r in enumerate(results):
        if same_pose(R, t, r["T"][:3, :3], r["T"][:3, 3]):
            if j and ties(results[0], r):
                return [r] + results[:j] + results[j + 1:]
            break
    return results


def competing_poses(results, cad):
    """The poses that explain as many features about as well as the best, split by the model's symmetry.

    A second distinct pose with the best's score and a chi-square within
    ``AMBIGUITY_RATIO`` (plus a few standard deviations of the chi-square)
    ties with it. Under a turn the CAD model maps onto itself
    (:func:`model_symmetry`), both give the same characteristics: the turn
    is named and the best kept. Otherwise the tie is real and the pose
    competes, unless it is one already kept moved by a symmetry of the model.

    Returns
    -------
    symmetry : str
        What was said of the model's own turns ("" if none).
    rivals : list of dict
        The competing refined poses (:func:`~partinspect.cad.pose_refine.solve_pose`'s results).
    """
    first = results[0]
    turns, rivals = [], []
    for other in results[1:]:
        if other["score"] < first["score"]:
            break
        if same_pose(first["T"][:3, :3], first["T"][:3, 3], other["T"][:3, :3], other["T"][:3, 3]):
            continue
        if not ties(first, other):
            continue
        turn = model_symmetry(cad, np.linalg.inv(first["T"]) @ other["T"])
        if turn is not None:
            if turn not in turns:
                turns.append(turn)
            continue
        if any(same_pose(o["T"][:3, :3], o["T"][:3, 3], other["T"][:3, :3], other["T"][:3, 3])
               or model_symmetry(cad, np.linalg.inv(o["T"]) @ other["T"]) is not None for o in rivals):
            continue
        rivals.append(other)
    if not turns:
        return "", rivals
    return ("the CAD model maps onto itself under " + ", ".join(turns) + ": the poses those turns relate explain "
            "the features equally well and give the same characteristics; the best fitting one was taken"), rivals


def competing_pose(reg, best, cad):
    """A :class:`CompetingPose`: ``reg`` and how it differs from the refined pose ``best``.

    Its deciding features are those the turn between them moves where the
    model has nothing like them, either way, and which neither pose matched
    to a measured feature.
    """
    T, T_best = reg.part_to_camera, best["T"]
    e = pose_error(T, T_best)
    # how far the part's features move between the two poses, not its (arbitrary) origin
    pts = np.r_[cad.centers, cad.starts]
    shift = np.linalg.norm(pts @ (T[:3, :3] - T_best[:3, :3]).T + T[:3, 3] - T_best[:3, 3], axis=1).max()
    S = np.linalg.inv(T_best) @ T
    ids = set()
    for M in (S, np.linalg.inv(S)):
        lone_circles, lone_lines = unmatched_under(cad, M)
        ids.update(cad.round_ids[k] for k in lone_circles)
        ids.update(cad.line_ids[k] for k in lone_lines)
    ids -= {cad.round_ids[k] for k in best["circ"].values()} | {cad.line_ids[k] for k in best["lin"].values()}
    ids -= set(reg.assignment["circle"].values()) | set(reg.assignment["line"].values())
    return CompetingPose(reg, float(np.rad2deg(np.linalg.norm(e[:3]))), float(shift), tuple(sorted(ids, key=feature_order)))


def feature_order(fid):
    """Sort key of a CAD id in its number's order: circle-2 before circle-10."""
    kind, _, n = fid.rpartition("-")
    return (kind, int(n)) if n.isdigit() else (fid, 0)


def ambiguity_words(best, rivals, competing):
    """The tie in words: the poses, the fits, and what would tell them apart."""
    angles = ", ".join(f"{c.angle:.1f}" for c in competing)
    n = len(competing) + 1
    poses = (f"two poses {angles} degrees apart" if n == 2 else f"{n} poses ({angles} degrees from the best fitting)")
    shift = max(c.shift for c in competing)
    chi2 = " vs ".join(f"{r['chi2']:.3g}" for r in [best, *rivals])
    deciding = sorted({fid for c in competing for fid in c.deciding}, key=feature_order)
    tell = (f": {', '.join(deciding)}, which would tell, {'was' if len(deciding) == 1 else 'were'} not measured"
            if deciding else "")
    return (f"{poses} (features moved by up to {shift:.1f} mm) explain the {best['score']} matched features equally "
            f"well (chi-square {chi2}); the measured features are symmetric, the CAD model is not{tell}")


def unmatched_under(cad, S, tol=MATCH_GATE):
    """The CAD edges that the turn ``S`` puts where the model has no edge like them.

    Parameters
    ----------
    cad : CadArrays
    S : ndarray, shape (4, 4)
        A rigid motion of the part frame onto itself.
    tol : float
        mm: how far a moved edge may lie from its counterpart.

    Returns
    -------
    circles, lines : list of int
        Indices into ``cad.round_ids`` and ``cad.line_ids``: a moved circle
        with no circle of its radius and axis direction within ``tol`` of
        its centre, a moved line with no line whose ends (either way round)
        lie within ``tol`` of its ends. Both empty when the model maps onto
        itself under ``S``.
    """
    R, t = S[:3, :3], S[:3, 3]
    c = cad.centers @ R.T + t
    n = cad.normals @ R.T
    circles = []
    for k in range(len(c)):
        d = np.linalg.norm(cad.centers - c[k], axis=1)
        same = (d < tol) & (np.abs(cad.radii - cad.radii[k]) < tol) & (np.abs(np.einsum("ij,j->i", cad.normals, n[k])) > 0.999)
        if not same.any():
            circles.append(k)
    ends = cad.starts + cad.dirs * cad.lengths[:, None]
    a, b = cad.starts @ R.T + t, ends @ R.T + t
    lines = []
    for k in range(len(a)):
        fwd = np.maximum(np.linalg.norm(cad.starts - a[k], axis=1), np.linalg.norm(ends - b[k], axis=1))
        back = np.maximum(np.linalg.norm(cad.starts - b[k], axis=1), np.linalg.norm(ends - a[k], axis=1))
        if not (np.minimum(fwd, back) < tol).any():
            lines.append(k)
    return circles, lines


def model_symmetry(cad, S, tol=MATCH_GATE):
    """The turn ``S`` (part frame to part frame) as words if it maps every CAD edge onto one, else None.

    Parameters
    ----------
    cad : CadArrays
    S : ndarray, shape (4, 4)
        ``inv(T_best) @ T_other`` of two registered poses: the part moved by
        it is seen by the second pose as the part by the first.
    tol : float
        mm: how far a moved edge may lie from its counterpart (the two poses
        are estimates; ``MATCH_GATE`` is what registration itself accepts).

    Returns
    -------
    str or None
        E.g. "a turn of 60.0 deg about (0.000, 0.000, 1.000) through (45.0, 45.0, 6.0)".
    """
    lone_circles, lone_lines = unmatched_under(cad, S, tol)
    if lone_circles or lone_lines:
        return None
    R, t = S[:3, :3], S[:3, 3]
    from scipy.spatial.transform import Rotation

    from partinspect.cad.features import canonical_direction

    rv = Rotation.from_matrix(R).as_rotvec()
    angle = float(np.linalg.norm(rv))
    # A turn by a about -n is one by -a about n: the axis is named by its sign-free direction.
    axis = canonical_direction(rv) if angle > 0 else np.array([0.0, 0.0, 1.0])
    # A point on the axis: the least-squares solution of (I - R) p = t within the plane normal to the axis.
    p = np.linalg.lstsq(np.eye(3) - R, t, rcond=None)[0]
    p -= (p @ axis) * axis
    p = np.where(np.abs(p) < 0.05, 0.0, p)  # no "-0.0" in the words
    axis = np.where(np.abs(axis) < 5e-4, 0.0, axis)
    return (f"a turn of {np.degrees(angle):.1f} deg about ({axis[0]:.3f}, {axis[1]:.3f}, {axis[2]:.3f}) "
            f"through ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f})")
