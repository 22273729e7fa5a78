"""One inspection from several views of the part: each view measured as a pair, the features fused.

A views folder holds one sub-folder per image pair (``view-1/``,
``view-2/``, ...), each with ``left.png`` and ``right.png``, and either its
own calibration or the folder's shared ``calibration.yaml``. Each view goes
through the single-pair stages of :mod:`partinspect.pipeline` (the CAD
model loaded once): calibration check, adaptive measurement, registration
with its pose covariance. A view whose chain cannot be made (its
calibration does not fit its images, the model cannot be aligned) is left
out and named. The views' features are then fused
(:mod:`partinspect.tolerances.fusion`) and the characteristics evaluated on
them; this module only orchestrates.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from partinspect.errors import InputError
from partinspect.progress import quiet

__all__ = ["is_views_folder", "view_folders", "run_views", "measure_views", "evaluate_views", "View"]


def _is_pair(folder):
    # Either image makes it a view: one without its partner is then refused by name, not skipped.
    return (folder / "left.png").exists() or (folder / "right.png").exists()


def view_folders(path):
    """The sub-folders of ``path`` holding a pair (or half of one), in natural order (view-2 before view-10)."""
    path = Path(path)
    subs = [p for p in path.iterdir() if p.is_dir() and _is_pair(p)] if path.is_dir() else []
    return sorted(subs, key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)])


def is_views_folder(path):
    """True for a folder without a pair of its own whose sub-folders hold pairs."""
    path = Path(path)
    return path.is_dir() and not (path / "left.png").exists() and bool(view_folders(path))


@dataclass
class View:
    """One view of a multi-view run: its folder, inputs, measurement, or why it was left out."""

    name: str
    folder: Path
    inputs: object
    measured: object = None
    problem: str | None = None


class _SeenInViews:
    """A feature's visibility over views: in view if any view has it in view."""

    def __init__(self, records, names):
        self.records, self.names = records, names

    @property
    def in_view(self):
        return any(r.in_view for r in self.records)

    @property
    def seen(self):
        return tuple(max(r.seen[i] for r in self.records) for i in (0, 1))

    def reason(self):
        return "; ".join(f"{n}: {r.reason()}" for n, r in zip(self.names, self.records) if not r.in_view)


def run_views(part, views_dir, out="inspection", *, tolerances=None, progress=quiet, uncertainty="first-order",
              draws=200, pose_hint=None, load_cad=None, timings=None):
    """Inspect a part from a views folder; parameters as :func:`partinspect.pipeline.run_inspection`.

    ``timings`` adds up each stage over the views.

    Returns
    -------
    InspectionResult
        report.json as for one pair, the features and characteristics
        fused over the views, plus ``views`` (per view: folder, pose,
        registration RMS, features measured, or why it was left out) and
        ``fusion`` (the consistency test and the views it left out per
        feature); each characteristic names its ``views``.

    Raises
    ------
    InputError
        Bad input in any view (nothing is written), a pose hint (one pose
        does not fit several views), or no view that could be measured.
    """
    from partinspect import pipeline
    from partinspect.atomic import prepare_output_dir
    from partinspect.reports.assemble import with_timings
    from partinspect.reports.writer import render_reports, report_json, write_texts
    from partinspect.results import figure_data, view_figure
    from partinspect.timings import Timings

    timings = Timings() if timings is None else timings
    views_dir = Path(views_dir)
    if pose_hint is not None:
        raise InputError(views_dir, "--pose-hint fits one pair; the views of a views folder are each aligned by search")
    cad = {}

    def cached(path):
        if not cad:
            cad["model"] = (load_cad or pipeline.load_cad_model)(path)
        return cad["model"]

    views = measure_views(part, views_dir, out, tolerances=tolerances, progress=progress,
                          uncertainty=uncertainty, draws=draws, load_cad=cached, timings=timings)
    used = [v for v in views if v.measured is not None]
    if not used:
        raise InputError(views_dir, "no view could be measured: " + "; ".join(f"{v.name}: {v.problem}" for v in views))
    with timings.stage("evaluating"):
        report, features = evaluate_views(views, progress)
    progress("writing reports")
    used = [v for v in views if v.measured is not None]  # without the views the fusion left out whole
    first = used[0]
    with timings.stage("report"):
        out_dir = prepare_output_dir(out)
        figures = figure_data(first.inputs.left, first.inputs.right, first.inputs.calib, first.inputs.inv,
                              first.measured.stereo, first.measured.registration, features)
        figures["views"] = [view_figure(v.name, v.inputs, v.measured, features) for v in used]
        texts = render_reports(report, figures)
    report = with_timings(report, timings)
    texts["report.json"] = report_json(report)
    write_texts(out_dir, texts)
    return pipeline.InspectionResult(report["verdict"], report, out_dir)


def measure_views(part, views_dir, out, *, tolerances=None, progress=quiet, uncertainty="first-order", draws=200,
                  load_cad=None, timings=None):
    """Each view of a views folder read and measured with the single-pair stages; a list of :class:`View`.

    A view whose chain cannot be made (its calibration does not fit its
    images, the CAD model cannot be aligned) keeps its ``problem`` and no
    measurement; bad input in any view raises.
    """
    from partinspect import pipeline

    def teller(name):
        return lambda message: progress(f"{name}: {message}")

    # Every view's inputs read first: a bad one fails before seconds of measuring the others.
    views = [View(folder.name, folder, pipeline.load_inputs(part, folder, out, tolerances, None, teller(folder.name),
                                                            load_cad, calibration_dir=views_dir, timings=timings))
             for folder in view_folders(views_dir)]
    from partinspect.vision import forked as fork

    def run(view, serial):
        if serial:
            fork.ENABLED = False  # in a child measuring one view: the other CPU is the parent's
        before = dict(timings.seconds) if timings is not None else {}
        outcome = _measure_view(view, uncertainty, draws, teller(view.name))
        spent = {k: v - before.get(k, 0.0) for k, v in (timings.seconds.items() if timings is not None else ())}
        return outcome, spent

    # Two views at a time, one in a forked child, each measured on one CPU
    # (the same results as one after the other: vision.forked).
    for i in range(0, len(views), 2):
        pair = views[i:i + 2]
        if len(pair) == 2 and fork.can_fork():
            enabled = fork.ENABLED
            with fork.forked(run, pair[1], True) as other:
                fork.ENABLED = False
                try:
                    mine, (theirs, spent) = run(pair[0], True)[0], other()
                finally:
                    fork.ENABLED = enabled
            if timings is not None:
                for k, v in spent.items():
                    timings.seconds[k] = timings.seconds.get(k, 0.0) + v
            outcomes = [mine, theirs]
        else:
            outcomes = [run(v, False)[0] for v in pair]
        for view, (measured, problem, calib) in zip(pair, outcomes):
            view.measured, view.problem, view.inputs.calib = measured, problem, calib
    return views


def _measure_view(view, uncertainty, draws, say):
    """One view's calibration check and measurement: (Measured or None, problem or None, the calibration measured with).

    The check may correct the view's calibration (``inputs.calib``); it is
    returned so that a view measured in a child process keeps it.
    """
    from partinspect import pipeline

    inputs = view.inputs
    try:
        check, first = pipeline.check_calibration(inputs, say)
        m = pipeline.measure(inputs, say, check, first)
        if uncertainty == "montecarlo":
            m = pipeline.with_monte_carlo(inputs, m, draws, say)
        if m.registration.competing:
            # Fusion places each view's features by its one pose: a view whose pose is ambiguous has none.
            raise InputError(view.folder, "cannot align the CAD model to the images: alignment is ambiguous: "
                             + m.registration.ambiguity + " (a view is fused under one pose)")
        return m, None, inputs.calib
    except InputError as e:
        say(f"left out: {e.problem}")
        return None, e.problem, inputs.calib


def evaluate_views(views, progress):
    """Fuse the measured views' features, evaluate and decide every characteristic, assemble report.json.

    A view whose features as a whole disagree with the others' is left out
    first (its ``problem`` says why); the rest are fused feature by feature.

    Returns
    -------
    report : dict
    features : list of dict
    """
    from partinspect.diagnosis import split_unseen
    from partinspect.results import characteristic_entry, fused_feature_entries
    from partinspect.tolerances.decision import decide_all
    from partinspect.tolerances.evaluate_fused import evaluate_fused
    from partinspect.tolerances.fusion import fuse

    used = _consistent_views(views, progress)
    names = [v.name for v in used]
    inputs = used[0].inputs
    inv = inputs.inv
    regs = [v.measured.registration for v in used]
    progress(f"fusing the features of {len(used)} views")
    one_rig = all(v.inputs.calib.same_rig(inputs.calib) for v in used)
    fused = fuse([r.features_in_part_frame() for r in regs], inv, rank={i: r.weighted_rms for i, r in enumerate(regs)},
                 registrations=regs if one_rig else None)
    seen = {f.id: _SeenInViews([v.measured.seen[f.id] for v in used], names) for f in inv.features}
    judged, not_inspected = split_unseen(inputs.characteristics, seen, None, measured=set(fused))
    progress(f"evaluating {len(inputs.characteristics)} characteristics")
    evaluations, sources = evaluate_fused(judged, fused, regs, inv)
    decisions = decide_all(evaluations, inputs.resolved.decision_rule)
    why = _why_unmeasured(used, inv, fused)
    characteristics = []
    for d, src in zip(decisions, sources):
        entry = characteristic_entry(d)
        entry["views"] = [names[i] for i in src]
        if entry["measured"] is None:
            entry["reason"] = "not measured: " + "; ".join(f"{fid}: {why[fid]}" for fid in entry["features"]
                                                           if fid in why)
        characteristics.append(entry)
    features = fused_feature_entries(inv, fused, [v.measured for v in used], names, seen, decisions, why)
    report = _views_report(views, used, decisions, features, characteristics, not_inspected)
    index = {v.name: i for i, v in enumerate(used)}
    report["views"] = [_view_entry_of(v, fused, index.get(v.name)) for v in views]
    report["fusion"] = _fusion_entry(fused, names)
    return report, features


def _consistent_views(views, progress):
    """The measured views less those the view-level consistency test leaves out (their ``problem`` set)."""
    from partinspect.tolerances.fusion import consistent_view_set

    used = [v for v in views if v.measured is not None]
    regs = [v.measured.registration for v in used]
    _, dropped = consistent_view_set([r.features_in_part_frame() for r in regs], regs, used[0].inputs.inv,
                                     rank={i: r.weighted_rms for i, r in enumerate(regs)})
    for d in dropped:
        view = used[d["view"]]
        view.measured, view.problem = None, d["reason"]
        progress(f"{view.name} left out: {d['reason']}")
    return [v for v in views if v.measured is not None]


def _why_unmeasured(used, inv, fused):
    """Feature id -> why no view measured it ("view-1: ...; view-2: ..."), for features not fused."""
    from partinspect.diagnosis import unmeasured_reasons

    why = {}
    for v in used:
        m = v.measured
        images = (v.inputs.left, v.inputs.right, v.inputs.bit_depth)
        for fid, reason in unmeasured_reasons(inv, m.stereo, m.registration, m.seen, v.inputs.calib, images).items():
            why.setdefault(fid, []).append(f"{v.name}: {reason}")
    return {fid: "; ".join(r) for fid, r in why.items() if fid not in fused}


def _views_report(views, used, decisions, features, characteristics, not_inspected):
    """report.json's keys shared with a single pair's, from the first view used and every view's inputs."""
    from partinspect.reports.assemble import assemble_report, input_entries
    from partinspect.results import registration_entry
    from partinspect.tolerances.decision import verdict
    from partinspect.tolerances.from_pmi import datum_entry
    from partinspect.vision.images import IMAGE_NAMES

    inputs, first = used[0].inputs, used[0].measured
    inputs_list = []
    for v in views:
        entries = input_entries(inputs.part, v.folder / IMAGE_NAMES[0], v.folder / IMAGE_NAMES[1],
                                v.inputs.calib_file, inputs.tol_path)
        inputs_list.extend({**e, "view": v.name} for e in entries if e["role"] not in ("part", "tolerances")
                           or v is views[0])
    return assemble_report(
        part=inputs.part.name,
        verdict=verdict(decisions),
        inputs=inputs_list,
        calibration=None if first.calibration is None else first.calibration.to_dict(),
        image={"width": inputs.left.shape[1], "height": inputs.left.shape[0], "bit_depth": inputs.bit_depth},
        tolerances={"file": None if inputs.tol_path is None else str(inputs.tol_path),
                    "general": inputs.resolved.general, "decision_rule": inputs.resolved.decision_rule,
                    "not_evaluated": [n.to_dict() for n in inputs.resolved.not_evaluated]},
        uncertainty={**first.uncertainty,
                     "views": "each view's features in the part frame with its pose covariance, tested for "
                              "consistency across views and combined by generalised least squares"},
        adaptive=first.adaptive,
        registration=registration_entry(first.registration, datum_entry(inputs.resolved, first.registration.datums)),
        features=features,
        characteristics=characteristics,
        not_inspected=not_inspected,
        skipped_edges=inputs.inv.to_dict().get("skipped", {}),
    )


def _view_entry_of(view, fused, index):
    """report.json's entry for one view (``index`` its place among the fused views, None if left out)."""
    from partinspect.results import view_entry

    return view_entry(view.name, view.folder, None if view.measured is None else view.measured.registration,
                      fused, index, view.problem)


def _fusion_entry(fused, names):
    """report.json's ``fusion``: the consistency test and every view it left out of a feature."""
    from partinspect.tolerances.fusion import SIGNIFICANCE

    return {
        "significance": SIGNIFICANCE,
        "test": "each view's feature against the combination of the other views': chi-square of the difference "
                "against the sum of their covariances (minimal parameters: circle 6, line 4)",
        "reference_view": names[0],
        "left_out": [{"feature": fid, "view": names[r["view"]], "chi2": round(r["chi2"], 3), "dof": r["dof"],
                      "threshold": round(r["threshold"], 3), "reason": r["reason"]}
                     for fid, f in fused.items() for r in f.rejected],
    }
