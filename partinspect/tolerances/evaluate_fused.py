"""Characteristics evaluated on features combined over several views (:mod:`.fusion`).

A characteristic whose features one view alone measured is evaluated on
that view, exactly as a single pair is (:func:`.evaluate.evaluate_characteristic`).
Otherwise on the combined features: sizes, positions and profiles on the
combination, its covariance including each view's pose; a distance or
angle between two features from their joint covariance in the part frame,
correlated through a view that measured both and independent otherwise
(:func:`.fusion.fused_cross_covariance`), so each view's pose uncertainty is
carried; a form value (straightness, circularity) on the edge points of the
view with the most, as points are not merged across views.

References
----------
.. [1] JCGM 100:2008 (GUM), 5.1 and 5.2: propagation with correlated inputs.
"""

from __future__ import annotations

import functools
from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from partinspect.frames import orthonormal_frame
from partinspect.tolerances.evaluate import (
    COVERAGE_FACTOR,
    N_MC,
    evaluate_characteristic,
    without_datum_shifts,
    PAIR_VALUES,
    measured_result,
    nominal_legs,
    propagate,
    unmeasured_result,
)
from partinspect.tolerances.fusion import fused_cross_covariance

__all__ = ["FORM_TYPES", "evaluate_fused", "pair_value"]

FORM_TYPES = ("straightness", "circularity")
"""Form values: read on one view's edge points (:func:`_form_evaluation`),
never combined, as points are not merged across views."""


def _rebuilt(kind, x, extent):
    if kind == "line":
        p, d = x[:3], x[3:6] / np.linalg.norm(x[3:6])
        return SimpleNamespace(kind="line", start=p + extent[0] * d, end=p + extent[1] * d)
    return SimpleNamespace(kind="circle", center=x[:3], normal=x[3:6], radius=x[6])


def _extent(f):
    if f.kind != "line" or f.start is None:
        return None
    return float((f.start - f.point) @ f.direction), float((f.end - f.point) @ f.direction)


class _FusedView:
    """What :func:`~partinspect.tolerances.evaluate.evaluate_characteristic` reads of a registration, for fused features."""

    def __init__(self, fused, registrations, form_view):
        self._fused = fused
        self.part_to_camera = registrations[form_view].part_to_camera
        self.datums = tuple(sorted({d for v in fused.views for d in registrations[v].datums}))
        # Edge points (for a form value) from the view with the most; the size from the combination.
        source = next(p for v, p, _, _ in fused.contributions if v == form_view)
        rec = registrations[form_view].measured_feature(source.kind, source.index)
        self._record = SimpleNamespace(
            radius=fused.radius, radius_std=fused.radius_std, start=fused.start, end=fused.end,
            points=getattr(rec, "points", None), point_covs=getattr(rec, "point_covs", None),
            point_errors=getattr(rec, "point_errors", None))

    def measured_feature(self, kind, index):
        return self._record


FORM_COVERAGE = 0.9
"""A form value is read in a view that sees at least this share of the
edge's extent the best-covering view sees: a view of part of an edge would
judge the form of that part only."""


def _coverage(part, rec):
    """How much of its edge a view measured: a line's length, mm; a circle's share of the 36 ten-degree sectors."""
    if part.kind == "line":
        return 0.0 if part.start is None else float(np.linalg.norm(part.end - part.start))
    pts = getattr(rec, "points", None)
    if pts is None or len(pts) == 0:
        return 0.0
    # Points are in the rig frame (the record's), as the circle's own parameters.
    v = np.asarray(pts, float) - np.asarray(rec.center, float)
    e1, e2 = orthonormal_frame(np.asarray(rec.normal, float))[:2]
    sectors = np.floor((np.arctan2(v @ e2, v @ e1) + np.pi) / (2 * np.pi) * 36).astype(int) % 36
    return len(set(sectors.tolist())) / 36.0


def _form_evaluation(c, fused, parts, registrations, inventory, **options):
    """A form characteristic evaluated in the view that judges it best: (view, Evaluation).

    Among the combined views that cover about as much of the edge as any
    (``FORM_COVERAGE``), the one whose form value has the smallest standard
    uncertainty, as the plan counts a characteristic decided by the view
    that decides it; the uncertainty comes from each view's error model,
    not from its residuals, so the choice does not favour a lucky value.
    """
    recs = {v: registrations[v].measured_feature(p.kind, p.index) for v, p, _, _ in fused.contributions}
    cover = {v: _coverage(p, recs[v]) for v, p, _, _ in fused.contributions}
    best = max(cover.values())
    out = []
    for v in sorted(cover):
        if cover[v] >= FORM_COVERAGE * best:
            ev = evaluate_characteristic(c, parts[v], registrations[v], inventory, **options)
            u = ev.standard_uncertainty if ev.measured is not None else np.inf
            out.append((u, v, ev))
    _, v, ev = min(out, key=lambda t: (t[0], t[1]))
    return v, ev


def _form_view(fused, registrations):
    """The combined view whose record of the feature has the most edge points."""
    def n_points(item):
        v, p = item[0], item[1]
        pts = getattr(registrations[v].measured_feature(p.kind, p.index), "points", None)
        return (0 if pts is None else len(pts), -v)

    return max(fused.contributions, key=n_points)[0]


def evaluate_fused(characteristics, fused, registrations, inventory, *, k=COVERAGE_FACTOR, seed=0, n_mc=N_MC):
    """Evaluate characteristics on features combined over several views.

    A characteristic whose features were all measured in one view only, the
    same one, is evaluated on that view alone, exactly as a single pair is.
    Otherwise on the combined features: sizes, positions and profiles on
    the combination (its covariance, each view's pose included); a
    distance or angle between two features from their joint covariance in
    the part frame (:func:`fused_cross_covariance`: correlated through a
    view that measured both, independent otherwise, so each view's pose
    uncertainty is carried); a form value in the view that judges it best
    (:func:`_form_evaluation`).

    Parameters
    ----------
    characteristics : sequence of Characteristic
    fused : dict
        :func:`fuse`'s result.
    registrations : sequence of Registration
        Per view.
    inventory : Inventory
    k, seed, n_mc
        As :func:`~partinspect.tolerances.evaluate.evaluate`.

    Returns
    -------
    evaluations : list of Evaluation
    views : list of tuple of int
        Per characteristic, the views its value came from.
    """
    parts = [r.features_in_part_frame() for r in registrations]
    evaluations, used = [], []
    for c in characteristics:
        fs = [fused.get(fid) for fid in c.features]
        if any(f is None for f in fs):
            missing = [fid for fid, f in zip(c.features, fs) if f is None]
            evaluations.append(unmeasured_result(c, f"{', '.join(missing)} not measured in any view (not visible in both "
                                              f"images or not matched)"))
            used.append(())
            continue
        views = sorted({v for f in fs for v in f.views})
        one = len(views) == 1
        if c.type in FORM_TYPES and not one:
            v, ev = _form_evaluation(c, fs[0], parts, registrations, inventory, k=k, seed=seed, n_mc=n_mc)
            evaluations.append(ev)
            used.append((v,))
            continue
        if one:
            v = views[0]
            evaluations.append(evaluate_characteristic(c, parts[v], registrations[v], inventory, k=k, seed=seed,
                                                       n_mc=n_mc))
        elif c.type in PAIR_VALUES:
            evaluations.append(pair_value(c, fs, registrations, k, inventory=inventory))
        else:
            view = _FusedView(fs[0], registrations, _form_view(fs[0], registrations))
            ev = evaluate_characteristic(c, fs, view, inventory, k=k, seed=seed, n_mc=n_mc)
            if ev.measured is not None:
                ev = replace(ev, method=f"{ev.method}; combined over {len(views)} views (generalised least squares)")
            evaluations.append(ev)
        used.append(tuple(views))
    # Each feature is combined from its own views: there is no one frame to
    # place a pattern in, and the value without the shift is the stricter.
    return without_datum_shifts(evaluations, "several views: the pattern is not placed as one across them"), used


def pair_value(c, fs, registrations, k=COVERAGE_FACTOR, inventory=None):
    """A distance or angle between two combined features, from their joint part-frame covariance.

    Parameters
    ----------
    c : Characteristic
        Of type "distance", "angle" or "parallelism".
    fs : (FusedFeature, FusedFeature)
    registrations : sequence of Registration
        Per view (for the cross-covariance through a view that measured both).
    k : float
    inventory : Inventory, optional
        The CAD edges, whose legs orient an angle's measured directions
        (:func:`partinspect.tolerances.evaluate.nominal_legs`); without it
        the legs are found from the measured segments.

    Returns
    -------
    Evaluation
    """
    a, b = fs
    K = fused_cross_covariance(a, b, registrations)
    x = np.r_[a.params, b.params]
    cov = np.block([[a.param_cov, K], [K.T, b.param_cov]])
    na, ea, eb = len(a.params), _extent(a), _extent(b)
    g = PAIR_VALUES[c.type]
    if c.type == "parallelism" and c.towards is not None:
        g = functools.partial(g, towards=np.asarray(c.towards, float))  # the part frame's, as these features
    elif c.type == "angle" and inventory is not None:
        g = functools.partial(g, legs=nominal_legs(c, inventory))  # part frame, as these features

    def f(z):
        return g(_rebuilt(a.kind, z[:na], ea), _rebuilt(b.kind, z[na:], eb))

    try:
        value, u = propagate(f, x, cov)
    except ValueError as e:
        return unmeasured_result(c, f"{c.type} of the measured features undefined: {e}")
    return measured_result(c, value, u, k, "first order, part frame, features combined over views, each view's pose "
                                   "covariance included")
