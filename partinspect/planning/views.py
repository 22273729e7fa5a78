"""The fewest views of the part that together make its characteristics decidable.

One stereo pair sees a part from one side: edges on its far side, under
it or edge-on are not measured. Inspection cells turn the part on a
turntable or re-place it and take several pairs (``inspect PART VIEWS/``
fuses them). This module chooses those views from the planner's own
prediction (:func:`partinspect.planning.predict.predict_pose`):

1. candidate views: the part turned about the fixture axis at ``step``
   degrees over a full turn, and the same turns with the part re-placed
   upside down (turned 180 degrees about the fixture's X axis) or, when
   asked, laid on a side (90 degrees), each predicted as ``inspect plan``
   predicts a single pose;
2. each candidate decides a set of characteristics (U <= ratio x
   tolerance, and the part registers in that view);
3. the smallest set of candidates whose union decides every
   characteristic any candidate decides, found exactly (every set of
   1, 2, ... views in turn, on bit masks), up to ``max_views``; where no
   set that small covers them all, the set of ``max_views`` that decides
   the most, ties broken by the summed ranking of its views.

The exact cover counts what each view decides alone. Views are then
predicted together as the run combines them (:func:`decided_together`:
the predicted features of every view fused by their covariances, each
view's pose included, :mod:`partinspect.tolerances.fusion`): a
characteristic between features no single view sees together (a distance
from a top rim to a bottom edge), or one that only the combination makes
precise enough, counts as decided by the views that contribute to it; and
the cover is adjusted greedily to that count (:func:`fused_choice`): a
view added where the combination decides more, a view dropped where the
others decide together all it did.

References
----------
.. [1] Scott, W. R., Roth, G., & Rivest, J.-F. (2003). View planning for
       automated three-dimensional object reconstruction and inspection.
       ACM Computing Surveys 35(1), 64-96 (view planning as set covering).
.. [2] Karp, R. M. (1972). Reducibility among combinatorial problems. In
       Complexity of Computer Computations, 85-103 (set cover is NP-hard:
       the exact search is kept to a few views of a few dozen candidates).
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from partinspect.planning.search import FixturePose, cause_of, fixture_pose, rank_key

__all__ = ["FLIP_TILT", "view_candidates", "ViewPlan", "fewest_views", "fused_choice", "decided_together", "plan_views",
           "view_turns", "turns_text"]

FLIP_TILT = 180.0
"""Degrees about the fixture's X axis: the part re-placed upside down."""


def view_candidates(step=30.0, tilts=(0.0, FLIP_TILT)):
    """Fixture poses to choose views from: a full turn at ``step`` degrees at each tilt about the fixture's X.

    Parameters
    ----------
    step : float
        Turn between candidates about the fixture axis, degrees.
    tilts : sequence of float
        Tilts about the fixture's X axis, degrees: 0 upright,
        :data:`FLIP_TILT` upside down, 90 and -90 the part laid on a side
        (its side faces, turned up in turn by the full turn, show their holes).

    Returns
    -------
    list of FixturePose
    """
    n = max(1, int(round(360.0 / step))) if step > 0 else 1
    turns = [k * 360.0 / n for k in range(n)]
    turns = [t - 360.0 if t > 180.0 + 1e-9 else t for t in turns]
    return [FixturePose(t, float(tx), 0.0) for tx in tilts for t in turns]


@dataclass(frozen=True, eq=False)
class ViewPlan:
    """The views chosen, and what they leave undecided.

    Attributes
    ----------
    views : list of PosePrediction
        The chosen views, in the order of the candidates.
    decided_by : dict
        Characteristic id -> indices into ``views`` of the views that
        decide it alone, or else of the views that decide it together.
    together : dict
        Characteristic id -> its predicted expanded uncertainty U (k = 2)
        from the views combined, for those no chosen view decides alone.
    undecided : list of (CharacteristicPrediction, str)
        Characteristics no chosen view decides, each as predicted in the
        candidate where its ratio U / tolerance was lowest, with why.
    candidates : list of PosePrediction
        Every candidate predicted.
    complete : bool
        Whether the views decide everything any candidate decides.
    out_of_view : list of str
        General-tolerance characteristics of edges no candidate sees
        (``inspect`` does not judge those either).
    """

    views: list
    decided_by: dict
    undecided: list
    candidates: list
    complete: bool
    out_of_view: list
    together: dict = field(default_factory=dict)


def _decides(p, k):
    """Whether candidate ``p`` decides its ``k``-th characteristic alone (the part registers in it)."""
    return p.characteristics[k].decidable and p.registration_error is None


def _masks(candidates):
    """Per candidate, a bit mask of the characteristics it decides (bit k: the k-th)."""
    return [sum(1 << k for k in range(len(p.characteristics)) if _decides(p, k)) for p in candidates]


def fewest_views(candidates, max_views):
    """Indices of the smallest set of candidates deciding the most characteristics.

    Parameters
    ----------
    candidates : list of PosePrediction
        All predicted for the same characteristics, in the same order.
    max_views : int
        The most views allowed.

    Returns
    -------
    chosen : tuple of int
        Increasing indices into ``candidates``.
    complete : bool
        Whether ``chosen`` decides everything the union of all candidates
        decides.
    """
    masks = _masks(candidates)
    target = 0
    for m in masks:
        target |= m
    # A candidate deciding a subset of another's is never needed.
    keep = [i for i, m in enumerate(masks) if m and not any(
        (m | n) == n and (m != n or j < i) for j, n in enumerate(masks) if j != i)]
    if not keep:
        return (), target == 0
    ranks = {i: rank_key(candidates[i]) for i in keep}
    best = None
    for k in range(1, max(1, max_views) + 1):
        for combo in itertools.combinations(keep, k):
            covered = 0
            for i in combo:
                covered |= masks[i]
            # Most decided, then fewest views, then the best-ranked views.
            score = (bin(covered).count("1"), -k, tuple(sum(x) for x in zip(*(ranks[i] for i in combo))))
            if best is None or score > best[0]:
                best = (score, combo, covered)
        if best[2] == target:
            break
    return tuple(sorted(best[1])), best[2] == target


def _decided_by_set(candidates, chosen, together):
    """Indices of the characteristics the views ``chosen`` decide, alone or together."""
    views = [candidates[i] for i in sorted(chosen)]
    alone = {k for k in range(len(candidates[0].characteristics)) if any(_decides(p, k) for p in views)}
    return alone | (set(together(views)) if len(views) > 1 else set())


def fused_choice(candidates, chosen, max_views, together):
    """The views ``chosen`` adjusted to what views decide together: one added where it helps, any made needless dropped.

    The exact cover (:func:`fewest_views`) counts what each view decides
    alone. Combined, views decide more (a distance from a rim seen only
    from above to one seen only from below), and some view may add nothing
    the others do not decide together. So, greedily, while fewer than
    ``max_views``: the candidate that adds the most decided characteristics
    is added (none when no candidate adds any; the best-ranked first when
    nothing is chosen yet); then each chosen view whose removal loses no
    decided characteristic is dropped, the weakest-ranked first. Greedy, not
    exact: a combination is predicted per set tried (as many sets as
    candidates per view added), which an exact search over every set of
    views would multiply.

    Parameters
    ----------
    candidates : list of PosePrediction
    chosen : sequence of int
        Indices into ``candidates``, e.g. from :func:`fewest_views`.
    max_views : int
    together : callable
        ``together(views) -> dict`` keyed by the indices of the
        characteristics the views decide only together
        (:func:`decided_together` with the part's inventory).

    Returns
    -------
    tuple of int
        Increasing indices into ``candidates``.
    """
    chosen = list(chosen)
    if not candidates:
        return ()
    if not chosen and max_views > 0:
        chosen = [max(range(len(candidates)), key=lambda i: rank_key(candidates[i]))]
    decided = _decided_by_set(candidates, chosen, together)
    while len(chosen) < max_views:
        gains = [(len(_decided_by_set(candidates, chosen + [i], together)), rank_key(candidates[i]), i)
                 for i in range(len(candidates)) if i not in chosen]
        if not gains:
            break
        n, _, best = max(gains)
        if n <= len(decided):
            break
        chosen.append(best)
        decided = _decided_by_set(candidates, chosen, together)
    for i in sorted(chosen, key=lambda i: rank_key(candidates[i])):
        rest = [j for j in chosen if j != i]
        if rest and _decided_by_set(candidates, rest, together) >= decided:
            chosen = rest
    return tuple(sorted(chosen))


def _why_undecided(cps, cid, covering):
    """Why no chosen view decides a characteristic: its causes over the candidates."""
    if covering:
        return (f"decidable in {covering} candidate view(s), none of them among the fewest views that "
                "decide the rest: allow more views")
    counts = Counter(cause_of(c) for c in cps)
    summary = ", ".join(f"{name} in {n} of {len(cps)} views" for name, n in counts.most_common())
    if all(not c.inspected for c in cps):
        summary += "; its features are not seen together in any one view, nor decided by the chosen views together"
    return summary


def decided_together(views, inventory):
    """What the views decide together that none decides alone, predicted as the run fuses them.

    Each view's predicted features (its predicted registration's, in the
    part frame, with the pose covariance) are combined over the views by
    :func:`partinspect.tolerances.fusion.fuse` and the characteristics
    evaluated on the combination by
    :func:`partinspect.tolerances.evaluate_fused.evaluate_fused`, the
    functions ``inspect PART VIEWS/`` uses, with one rig's calibration error
    shared between the views. A predicted feature has no noise drawn, so the
    consistency test between views keeps every view.

    Parameters
    ----------
    views : list of PosePrediction
        The chosen views, predicted for the same characteristics.
    inventory : Inventory

    Returns
    -------
    dict
        Index of a characteristic (in the predictions' order) -> ``(U,
        by)``: its predicted expanded uncertainty (k = 2) and the indices
        into ``views`` of the views it combines, for every characteristic
        that no view decides alone, that draws on two or more views, and
        whose U is within the views' ratio of its tolerance.
    """
    from partinspect.planning.predict import tolerance_width
    from partinspect.tolerances.evaluate_fused import evaluate_fused
    from partinspect.tolerances.fusion import fuse

    placed = [i for i, p in enumerate(views) if p.registration is not None and p.registration_error is None]
    if len(placed) < 2:
        return {}
    regs = [views[i].registration for i in placed]
    chars = [c.characteristic for c in views[0].characteristics]
    fused = fuse([r.features_in_part_frame() for r in regs], inventory, registrations=regs)
    todo = [k for k in range(len(chars)) if not any(_decides(p, k) for p in views) and _across_views(chars[k], fused)]
    evaluations, sources = evaluate_fused([chars[k] for k in todo], fused, regs, inventory)
    out = {}
    for k, ev, src in zip(todo, evaluations, sources):
        T = tolerance_width(chars[k])
        if ev.expanded_uncertainty is None or T is None:
            continue
        U = float(ev.expanded_uncertainty)
        if math.isfinite(U) and U <= views[0].max_ratio * T:
            out[k] = (U, [placed[v] for v in src])
    return out


def _across_views(c, fused):
    """Whether the run evaluates characteristic ``c`` on two or more views of ``fused`` (:func:`~.fusion.fuse`).

    Its features must all be combined, from two or more views between
    them, and it must not be a form value, which is read in one view
    (:func:`partinspect.tolerances.evaluate_fused.evaluate_fused`). Any
    other is one view's measurement, which that view decides alone or not
    at all.
    """
    from partinspect.tolerances.evaluate_fused import FORM_TYPES

    fs = [fused.get(fid) for fid in c.features]
    return c.type not in FORM_TYPES and all(f is not None for f in fs) and len({v for f in fs for v in f.views}) >= 2


def plan_views(predict, start, center, max_views, *, step=30.0, tilts=(0.0, FLIP_TILT), inventory=None,
               progress=None):
    """Predict the candidate views and choose the fewest that decide the characteristics.

    Parameters
    ----------
    predict : callable
        ``predict(part_to_camera, fixture_pose) -> PosePrediction``, as
        :func:`partinspect.planning.search.search_poses` takes it.
    start : ndarray, shape (4, 4)
        The starting pose (fixture angles 0).
    center : ndarray, shape (3,)
        The part's bounding-box centre, part frame (the pivot).
    max_views : int
    step : float
        Turn between candidate views, degrees.
    tilts : sequence of float
        Tilts about the fixture's X axis, degrees (:func:`view_candidates`).
    inventory : Inventory, optional
        The part's features: the chosen views are then also predicted
        together (:func:`decided_together`).
    progress : callable, optional

    Returns
    -------
    ViewPlan
    """
    poses = view_candidates(step, tilts)
    candidates = []
    for k, fp in enumerate(poses, 1):
        if progress:
            progress(f"predicting candidate view {k} of {len(poses)}: {fp.label}")
        candidates.append(predict(fixture_pose(start, center, fp), fp))
    memo = {}

    def together(views):
        # The same set is predicted by the choice's trials and again for the plan: fuse it once.
        key = tuple(map(id, views))
        if key not in memo:
            memo[key] = decided_together(views, inventory)
        return memo[key]

    chosen, complete = fewest_views(candidates, max_views)
    if inventory is not None and max_views > 1:
        if progress:
            progress("choosing the views by what they decide together")
        chosen = fused_choice(candidates, chosen, max_views, together)
    views = [candidates[i] for i in chosen]
    combined = together(views) if inventory is not None else {}
    decided_by, undecided, out_of_view, together = {}, [], [], {}
    for k, cid in enumerate(c.id for c in candidates[0].characteristics):
        by = [v for v, p in enumerate(views) if _decides(p, k)]
        if not by and k in combined:
            together[cid], by = combined[k]
        if by:
            decided_by[cid] = by
            continue
        cps = [p.characteristics[k] for p in candidates]
        if not any(c.inspected for c in cps) and cps[0].characteristic.source != "spec":
            out_of_view.append(cid)
            continue
        covering = sum(_decides(p, k) for p in candidates)
        best = min(cps, key=lambda c: c.ratio if not math.isnan(c.ratio) else math.inf)
        undecided.append((best, _why_undecided(cps, cid, covering)))
    return ViewPlan(views, decided_by, undecided, candidates, complete, out_of_view, together)


def view_turns(views):
    """Each chosen view's turn of the part in its own frame, as ``inspect render --views`` reads it.

    ``inspect render --views`` turns the part by extrinsic rotations about
    the part frame's X, then Y, then Z (:func:`partinspect.poses.turned_pose`);
    a fixture pose turns it about Z, then Y, then X
    (:func:`~partinspect.planning.search.fixture_pose`). The same rotation
    is written in the render's convention.

    Parameters
    ----------
    views : list of PosePrediction

    Returns
    -------
    list of ndarray, shape (3,)
        Degrees, rounded to 0.001 (tiny values to 0).
    """
    from scipy.spatial.transform import Rotation

    out = []
    for p in views:
        rotation, tilt_x, tilt_y = p.angles
        R = (Rotation.from_euler("x", tilt_x, degrees=True) * Rotation.from_euler("y", tilt_y, degrees=True)
             * Rotation.from_euler("z", rotation, degrees=True))
        with warnings.catch_warnings():
            # A part laid on its side (tilt 90) is SciPy's gimbal lock: the
            # three angles are not unique, and any triple it gives composes
            # to the same rotation, which is all --views needs.
            warnings.simplefilter("ignore", UserWarning)
            angles = np.round(R.as_euler("xyz", degrees=True), 3)
        out.append(np.where(np.abs(angles) < 5e-4, 0.0, angles))
    return out


def turns_text(turns):
    """:func:`view_turns` as ``--views`` text, e.g. ``"0.000,0.000,0.000;0.000,0.000,120.000"``."""
    return ";".join(",".join(f"{a:.3f}" for a in t) for t in turns)
