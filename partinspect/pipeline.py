"""One inspection run, as a short sequence of named stages.

load the inputs -> measure (adaptive rounds, each registered and settled
under its pose) -> evaluate and decide -> report. Each stage calls into
:mod:`partinspect.vision`, :mod:`partinspect.cad`, :mod:`partinspect.tolerances`
and :mod:`partinspect.reports`; this module holds no maths of its own. A
feature that was not measured says why (:mod:`partinspect.diagnosis`), its
characteristics are inconclusive, and no number is ever invented.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from partinspect.atomic import check_output_dir, prepare_output_dir
from partinspect.errors import InputError
from partinspect.progress import quiet
from partinspect.timings import Timings
from partinspect.tolerances.decision import EXIT_CODES

CALIBRATION_NAMES = ("calibration.yaml", "calibration.yml", "intrinsics.yml")


@dataclass(frozen=True)
class InspectionResult:
    """What one run produced.

    Attributes
    ----------
    verdict : str
        "pass", "fail" or "inconclusive".
    report : dict
        The report.json content (schema report/1).
    out_dir : Path
        Where report.html, report.json and junit.xml were written.
    """

    verdict: str
    report: dict
    out_dir: Path

    @property
    def exit_code(self):
        return EXIT_CODES[self.verdict]

    def summary_line(self):
        counts = self.report["summary"]
        return (
            f"{self.verdict.upper()}: {counts['pass']} pass, {counts['fail']} fail, "
            f"{counts['inconclusive']} inconclusive of {counts['characteristics']} characteristics; "
            f"{counts['features_measured']} of {counts['features']} features measured"
            + (f", {counts['not_inspected']} general-tolerance characteristics of edges out of view not inspected; "
               if counts.get("not_inspected") else "; ")
            + self._views_note()
            + self._refinement_note()
            + self._ambiguity_note()
            + f"report: {self.out_dir / 'report.html'}"
        )

    def _refinement_note(self):
        rr = self.report.get("rig_refinement")
        if rr is None:
            return ""
        if not rr["refined"]:
            return f"rig not refined ({rr['reason']}); "
        return (f"measured with the rig refined from {rr['circles']} circles "
                f"(turned {rr['rotation_correction_deg']:.5f} deg"
                f"{', significant' if rr['significant'] else ''}); ")

    def _ambiguity_note(self):
        amb = (self.report.get("registration") or {}).get("ambiguity")
        if not amb:
            return ""
        n = sum(bool((c.get("details") or {}).get("ambiguity")) for c in self.report["characteristics"])
        return (f"pose ambiguous: {len(amb['competing']) + 1} poses fit the measured features, {n} characteristics "
                "depend on which is right; ")

    def _views_note(self):
        views = self.report.get("views")
        if not views:
            return ""
        out = [v["name"] for v in views if not v["used"]]
        return (f"{len(views) - len(out)} of {len(views)} views fused"
                + (f" ({', '.join(out)} left out: see the report)" if out else "") + "; ")


@dataclass
class Inputs:
    """What a run reads: the part, its tolerances, the rig and the images."""

    part: Path
    images: Path
    tol_path: Path | None
    calib: object
    left: np.ndarray
    right: np.ndarray
    bit_depth: int
    model: object
    inv: object
    resolved: object
    characteristics: list
    hint: np.ndarray | None
    calib_file: Path | None = None
    timings: Timings = field(default_factory=Timings)


@dataclass
class Measured:
    """The chosen measurement: 3D features, the pose, what the cameras see."""

    stereo: object
    registration: object
    seen: dict
    adaptive: dict
    uncertainty: dict
    calibration: object = None
    refinement: dict | None = None


def run_inspection(part, images, out="inspection", *, tolerances=None, progress=quiet, uncertainty="first-order",
                   draws=200, pose_hint=None, load_cad=None, timings=None, refine_rig=False):
    """Inspect a part from a stereo pair and write the reports.

    Parameters
    ----------
    part : str or Path
        STEP file of the part.
    images : str or Path
        Folder with left.png, right.png and the calibration (a views
        folder, one sub-folder per pair, is :func:`partinspect.multiview.run_views`'s).
    out : str or Path
        Output folder; created if needed. report.html, report.json and
        junit.xml are each written atomically.
    tolerances : str or Path, optional
        Tolerance spec; default PART.tol.yaml beside the STEP file.
    progress : callable
        ``progress(message)`` for each stage.
    uncertainty : {"first-order", "montecarlo"}
        How the 3D features' covariances are obtained. "montecarlo"
        replaces each first-order covariance by the covariance of ``draws``
        repetitions of the 3D fits with the edge points (and calibration,
        when it states uncertainties) drawn from their distributions
        (JCGM 101); the first-order standard uncertainties are kept in the
        report beside them.
    draws : int
        Monte Carlo draws per feature.
    pose_hint : str, Path or ndarray (4, 4), optional
        An approximate ``part_to_camera`` (a JSON file holding it, or
        ``RX,RY,RZ,TX,TY,TZ`` as ``inspect render --pose`` takes), close
        enough that each feature lies within half a millimetre of its place:
        the pose search is skipped, which also settles parts that look
        symmetric to the cameras.
    load_cad : callable, optional
        ``load_cad(path) -> partinspect.cad.model.CadModel`` in place of
        `load_cad_model`: a batch worker keeps each part number's model in
        memory, so it is read once, not once per part.
    refine_rig : bool
        Once registered, re-estimate the rig's relative orientation from the
        part's own circles (:func:`refined_rig`) and measure again with it;
        the report says so and shows the correction beside the stated
        calibration.
    timings : partinspect.timings.Timings, optional
        Receives each stage's wall-clock seconds (report.json's ``timings``
        holds them too); a new one counting from this call by default.

    Returns
    -------
    InspectionResult

    Raises
    ------
    InputError
        Any bad input (exit code 2 at the command line); nothing is written.
    """
    from partinspect.reports.assemble import with_timings
    from partinspect.reports.writer import render_reports, report_json, write_texts
    from partinspect.results import figure_data

    timings = Timings() if timings is None else timings
    inputs = load_inputs(part, images, out, tolerances, pose_hint, progress, load_cad, timings=timings)
    stated = inputs.calib
    check, first = check_calibration(inputs, progress)
    m = measure(inputs, progress, check, first)
    if refine_rig:
        m = refined_rig(inputs, m, stated, check, progress)
    if uncertainty == "montecarlo":
        with timings.stage("Monte Carlo"):
            m = with_monte_carlo(inputs, m, draws, progress)
    with timings.stage("evaluating"):
        report, features = evaluate(inputs, m, progress)
    progress("writing reports")
    with timings.stage("report"):
        out_dir = prepare_output_dir(out)
        texts = render_reports(report, figure_data(inputs.left, inputs.right, inputs.calib, inputs.inv, m.stereo,
                                                   m.registration, features))
    # Every stage but the writing itself, which is milliseconds.
    report = with_timings(report, timings)
    texts["report.json"] = report_json(report)
    write_texts(out_dir, texts)
    return InspectionResult(report["verdict"], report, out_dir)


def load_inputs(part, images, out, tolerances, pose_hint, progress, load_cad=None, calibration_dir=None, timings=None):
    """Check and read every input; cheap checks first, so a typo fails before seconds of CAD loading.

    ``calibration_dir``: where the calibration is read when ``images``
    holds none (a views folder's shared calibration.yaml).
    """
    from partinspect.diagnosis import edges_found
    from partinspect.tolerances.loading import find_tolerances, load_characteristics
    from partinspect.vision.calibration import read_calibration
    from partinspect.vision.images import read_pair

    part = _check_part_path(part)
    images = Path(images)
    if not images.is_dir():  # else read_calibration would take it for a calibration file
        raise InputError(images, "images folder not found" if not images.exists() else "not a folder (IMAGES_DIR holds left.png, right.png, calibration.yaml)")
    tol_path = find_tolerances(part, tolerances)
    check_output_dir(out)

    timings = Timings() if timings is None else timings
    progress("reading calibration and images")
    calib_dir = images
    if calibration_dir is not None and not any((images / n).is_file() for n in CALIBRATION_NAMES):
        calib_dir = Path(calibration_dir)
    with timings.stage("reading calibration and images"):
        calib = read_calibration(calib_dir)
        left, right, bit_depth = read_pair(images, calib)

    progress(f"loading {part.name}")
    with timings.stage("loading the CAD model"):
        model = (load_cad or load_cad_model)(part)
    inv = model.inventory
    if not inv.features:
        raise InputError(part, f"no line or circle edges to measure ({edges_found(inv)})")
    hint = _pose_hint(pose_hint, model.bounds, calib)
    if tol_path is not None:
        progress(f"reading tolerances {tol_path.name}")
    with timings.stage("tolerances"):
        resolved, characteristics = load_characteristics(inv, tol_path, part=part, pmi=model.pmi)
    calib_file = next((calib_dir / n for n in CALIBRATION_NAMES if (calib_dir / n).is_file()), None)
    return Inputs(part, images, tol_path, calib, left, right, bit_depth, model, inv, resolved, characteristics, hint,
                  calib_file, timings)


def load_cad_model(part):
    """The STEP file's model: inventory, visibility mesh, bounds and PMI (`partinspect.cad.model`), cached."""
    from partinspect.cad.model import load_model

    return load_model(part)


def check_calibration(inputs, progress):
    """The stated calibration checked against this pair (epipolar tangency of matched circles).

    A significant drift is corrected (``inputs.calib`` becomes the corrected
    rig, its uncertainty carried); one beyond what a run can correct is an
    input error. Returns the check and the stereo result of the adaptive
    loop's first round when the calibration stood, so it is not measured twice.
    """
    from partinspect.adaptive import DEFAULTS
    from partinspect.vision.epipolar_drift import check_calibration as check, matched_arcs, matched_edge_points

    progress("checking the calibration against the images")
    stereo = _stereo_round(inputs, DEFAULTS, progress)
    with inputs.timings.stage("checking the calibration"):
        result = check(inputs.calib, matched_arcs(stereo), matched_edge_points(stereo))
    if result.verdict == "invalid":
        raise InputError(inputs.calib_file or inputs.images, result.refusal())
    progress(result.summary())
    if result.calib is inputs.calib:
        return result, stereo
    inputs.calib = result.calib
    return result, None


def refined_rig(inputs, m, stated, check, progress):
    """The rig re-estimated from the registered circles (:mod:`partinspect.vision.rig_refinement`), measured again.

    The registration supplies only which measured circles are the part's;
    the stated calibration is the prior (widened by the drift the check
    corrected, if any), the checked one the start. Where the
    circles cannot determine the rig, the run goes on with the checked
    calibration and the report says why it was not refined.
    """
    from partinspect.vision.calibration_uncertainty import budget_entry
    from partinspect.vision.rig_refinement import RefinementError, circle_observations, refine_rig

    # A circle the pose fit left out as inconsistent may be a wrong pair of arcs: it would bend the rig.
    assigned = m.registration.cad_ids(m.stereo.features, "circle")
    indices = sorted(k for k, cid in assigned.items() if cid not in m.registration.outliers)
    progress(f"refining the rig from {len(indices)} registered circles")
    try:
        with inputs.timings.stage("refining the rig"):
            result = refine_rig(stated, circle_observations(m.stereo, indices, inputs.calib), start=inputs.calib,
                                drifted=check.verdict == "drifted")
    except RefinementError as e:
        progress(f"rig not refined: {e}")
        return replace(m, refinement={"refined": False, "reason": str(e), "circles": len(indices)})
    progress(result.summary())
    inputs.calib = result.calib
    again = measure(inputs, progress, check)
    # The budget as the calibration stated it, and that the refined rig's posterior is what is carried.
    budget = {**budget_entry(stated), "refined_rig": True}
    return replace(again, uncertainty={**again.uncertainty, "calibration": budget},
                   refinement={"refined": True, **result.to_dict()})


def _stereo_round(inputs, params, progress):
    from partinspect.tolerances.edge_break import apparent_edge_rms
    from partinspect.vision.stereo import measure_stereo

    eb = inputs.resolved.spec.edge_break
    with inputs.timings.stage("measuring the images"):
        return measure_stereo(
            inputs.left, inputs.right, inputs.calib, sigma=params["sigma"], progress=progress,
            edge_options={"k_low": params["k_low"], "k_high": params["k_high"]},
            match_options={"min_points": params["min_points"]},
            edge_break=None if eb is None else apparent_edge_rms(eb.min, eb.max),
        )


def measure(inputs, progress, calibration=None, first=None):
    """Adaptive rounds of the stereo chain, each registered and settled; the best round.

    ``calibration``: the calibration check the rounds were measured after;
    ``first``: the stereo result of the default round, if already measured
    with ``inputs.calib``.
    """
    from partinspect.adaptive import DEFAULTS, measure_adaptively
    from partinspect.vision.calibration_uncertainty import budget_entry
    from partinspect.vision.posed import merged_stereo

    done = {tuple(sorted(DEFAULTS.items())): first} if first is not None else {}
    # Once a round's pose is ambiguous, later rounds start from its poses, the chosen one first: a CAD id then
    # names the same measured edge in every round (merge adds features by id), and the search is not repeated.
    hint = {"poses": inputs.hint}

    def registered(stereo):
        with inputs.timings.stage("registering"):
            registration = _register(stereo, inputs, hint["poses"])
        if registration.competing and hint["poses"] is None:
            hint["poses"] = registration.poses
        return registration

    def run_round(params):
        stereo = done.pop(tuple(sorted(params.items())), None) or _stereo_round(inputs, params, progress)
        progress(f"registering {len(stereo.features)} measured features to the CAD model")
        try:
            registration = registered(stereo)
        except InputError as e:
            e.stereo = stereo
            raise
        return settle(inputs, stereo, registration, progress)

    def merge(base, new, ids):
        stereo = merged_stereo(base.stereo, new.stereo, new.registration, ids)
        progress(f"registering {len(stereo.features)} features, {len(ids)} of them from the re-run")
        return settle(inputs, stereo, registered(stereo), progress)

    best, log, advice = measure_adaptively(run_round, progress=progress, merge=merge)
    return Measured(best.stereo, best.registration, best.visibility, {"rounds": log, "advice": advice},
                    {"method": "first-order propagation (JCGM 100)", "coverage_factor": 2.0,
                     "calibration": budget_entry(inputs.calib)}, calibration)


def settle(inputs, stereo, registration, progress):
    """What the registered pose adds (:func:`partinspect.vision.posed.posed_stereo`), registered again.

    Returns
    -------
    stereo, registration, seen
        ``seen``: each CAD feature's visibility at the final pose.
    """
    from partinspect.cad.outlines import outline_images
    from partinspect.cad.projection import edge_polylines
    from partinspect.cad.raycast import build_scene
    from partinspect.cad.visibility import visibility
    from partinspect.vision.posed import posed_stereo

    scene = build_scene(inputs.model.mesh)

    def seen_at(pose):
        with inputs.timings.stage("visibility"):
            return visibility(None, inputs.inv, inputs.calib, pose, images=(inputs.left, inputs.right), scene=scene)

    progress("checking which edges the cameras see")
    seen = seen_at(registration.part_to_camera)
    polylines = edge_polylines(inputs.inv, registration.part_to_camera, inputs.calib)
    outlines = outline_images(scene, inputs.calib, registration.part_to_camera)
    with inputs.timings.stage("measuring along the posed edges"):
        more, found, ends, withdrawn = posed_stereo(stereo, registration, seen, inputs.inv, inputs.calib, polylines,
                                                    outlines)
    if not found and not ends and not withdrawn:
        # ``more`` is ``stereo`` with the stretches found but not measured, if any.
        return more, registration, seen
    if ends:
        progress(f"{len(ends)} edge(s) fitted again clear of other edges at their ends")
    if withdrawn:
        progress(f"{len(withdrawn)} edge(s) taken out: another edge's image paired with theirs or crowding theirs")
    if found:
        progress(f"measuring {len(found)} edge(s) on their stretches of longer image lines")
    try:
        # The pose is known: no new search (it is the expensive part).
        with inputs.timings.stage("registering"):
            again = _register_again(more, inputs, registration)
    except InputError:
        return stereo, registration, seen
    return more, again, seen_at(again.part_to_camera)


def with_monte_carlo(inputs, m, draws, progress):
    """The chosen round with Monte Carlo covariances (JCGM 101), registered again."""
    from partinspect.vision.montecarlo import with_monte_carlo_covariances

    progress(f"Monte Carlo: {draws} draws for each of {len(m.stereo.features)} features")
    stereo, ratios = with_monte_carlo_covariances(m.stereo, inputs.calib, draws)
    # An ambiguous pose's candidates, the chosen one first, keep the CAD ids the round was settled under.
    registration = _register(stereo, inputs, m.registration.poses if m.registration.competing else inputs.hint)
    info = {"method": "Monte Carlo (JCGM 101) of the image noise; the calibration's part first order",
            "draws": draws, "seed": 0, "coverage_factor": 2.0,
            "std_ratio_median": round(float(np.median(ratios)), 4) if len(ratios) else None,
            "calibration": m.uncertainty["calibration"]}
    return Measured(stereo, registration, m.seen, m.adaptive, info, m.calibration, m.refinement)


def evaluate(inputs, m, progress):
    """Every characteristic evaluated and decided; report.json assembled.

    Returns
    -------
    report : dict
    features : list of dict
        report.json's "features" (the figures are drawn from them).
    """
    from partinspect.diagnosis import split_unseen, unmeasured_reasons
    from partinspect.reports.assemble import assemble_report, input_entries
    from partinspect.results import characteristic_entry, edge_break_entries, feature_entries, registration_entry
    from partinspect.tolerances.decision import decide_all, verdict
    from partinspect.tolerances.from_pmi import datum_entry
    from partinspect.vision.images import IMAGE_NAMES

    progress(f"evaluating {len(inputs.characteristics)} characteristics")
    judged, not_inspected = split_unseen(inputs.characteristics, m.seen, m.registration)
    judged, m, placed = _at_band_places(judged, inputs, m, progress)
    decisions = decide_all(_evaluate_on_two_cores(judged, m.registration, inputs.inv), inputs.resolved.decision_rule)
    if m.registration.competing:
        decisions = _judged_across_poses(judged, decisions, m.registration, inputs, progress)
    characteristics = [characteristic_entry(d) for d in decisions]
    why = unmeasured_reasons(inputs.inv, m.stereo, m.registration, m.seen, inputs.calib,
                             (inputs.left, inputs.right, inputs.bit_depth))
    features = feature_entries(inputs.inv, m.stereo, m.registration, m.seen, decisions, why,
                               edge_break_entries(m.stereo, m.registration, inputs.calib, *placed))
    for c in characteristics:
        if c["measured"] is None:
            c["reason"] = "not measured: " + "; ".join(f"{fid}: {why[fid]}" for fid in c["features"] if fid in why)
    images = inputs.images
    report = assemble_report(
        part=inputs.part.name,
        verdict=verdict(decisions),
        inputs=input_entries(inputs.part, images / IMAGE_NAMES[0], images / IMAGE_NAMES[1], inputs.calib_file,
                             inputs.tol_path),
        calibration=None if m.calibration is None else m.calibration.to_dict(),
        rig_refinement=m.refinement,
        image={"width": inputs.left.shape[1], "height": inputs.left.shape[0], "bit_depth": inputs.bit_depth},
        tolerances={"file": None if inputs.tol_path is None else str(inputs.tol_path),
                    "general": inputs.resolved.general, "decision_rule": inputs.resolved.decision_rule,
                    "not_evaluated": [n.to_dict() for n in inputs.resolved.not_evaluated]},
        uncertainty=m.uncertainty,
        adaptive=m.adaptive,
        registration=registration_entry(m.registration, datum_entry(inputs.resolved, m.registration.datums)),
        features=features,
        characteristics=characteristics,
        not_inspected=not_inspected,
        skipped_edges=inputs.inv.to_dict().get("skipped", {}),
    )
    return report, features


def _at_band_places(characteristics, inputs, m, progress):
    """Broken rims and lines measured at their predicted band places (:mod:`.vision.band_place`,
    :mod:`.vision.line_band`), registered again.

    Only where the spec states an edge break. A rim refitted with its
    points moved onto the sharp rim's image measures the wall; one that
    could not be keeps its fit and has its size corrected by the place
    (``Characteristic.band_place``); one whose place cannot be predicted
    keeps the uniform band. Lines alike: moved onto the sharp edge's image
    where their place is predicted better than the uniform band.

    Returns
    -------
    characteristics : list of Characteristic
    m : Measured
    placed : (dict, dict)
        Rims and lines: CAD id -> (place or None, the rim's break size or
        the ``BrokenLine``, moved), for
        :func:`partinspect.results.edge_break_entries`.
    """
    from partinspect.tolerances.edge_break import broken_rims, with_band_places
    from partinspect.vision.band_place import band_place, rims_at_sharp_edge

    rims = broken_rims(characteristics, inputs.inv, m.registration.part_to_camera)
    if not rims and m.stereo.edge_break is None:
        return characteristics, m, ({}, {})
    widths = tuple(float(np.median(side.edges.width)) for side in (m.stereo.left, m.stereo.right))
    stereo, refitted, places = m.stereo, set(), {}
    if rims:
        progress(f"predicting where {len(rims)} broken rim(s) show their edge")
        with inputs.timings.stage("edge-break band places"):
            places = {fid: band_place((inputs.left, inputs.right), inputs.calib, m.registration.part_to_camera, *rim,
                                      width=widths) for fid, rim in rims.items()}
            places = {fid: p for fid, p in places.items() if p is not None}
            arcs = m.registration.cad_ids(stereo.features, "circle")
            stereo, refitted = rims_at_sharp_edge(stereo, inputs.calib, m.registration.part_to_camera, arcs,
                                                  {fid: (p, rims[fid]) for fid, p in places.items()})
        if refitted:
            progress(f"{len(refitted)} broken rim(s) measured at their predicted place")
    stereo, lines, placed_lines = _lines_at_band_places(stereo, inputs, m.registration, widths, progress)
    if refitted or lines:
        try:
            with inputs.timings.stage("registering"):
                m = replace(m, stereo=stereo, registration=_register_again(stereo, inputs, m.registration))
        except InputError:
            # Kept as measured before the moves: nothing was moved.
            refitted, lines = set(), set()
            placed_lines = {cid: (p, line, False) for cid, (p, line, _) in placed_lines.items()}
    placed_rims = {fid: (places.get(fid), rim[4], fid in refitted) for fid, rim in rims.items()}
    return with_band_places(characteristics, places), m, (placed_rims, placed_lines)


def _lines_at_band_places(stereo, inputs, registration, widths, progress):
    """The measured broken lines moved onto their sharp edges' images (:mod:`.vision.line_band`), where predicted.

    Returns the stereo result, the lines moved, and per broken line its
    place (None where not predicted), the line and whether it was moved.
    """
    from partinspect.tolerances.edge_break import broken_lines
    from partinspect.vision.line_band import BrokenLine, line_places, lines_at_sharp_edge

    eb = inputs.resolved.spec.edge_break
    if eb is None or stereo.edge_break is None:
        return stereo, set(), {}
    matched = registration.cad_ids(stereo.features, "line")
    lines = {cid: BrokenLine(*t) for cid, t in broken_lines(inputs.inv, inputs.model.mesh, set(matched.values()),
                                                             eb.min, eb.max).items()}
    if not lines:
        return stereo, set(), {}
    progress(f"predicting where {len(lines)} broken line(s) show their edge")
    uv = {cid: (stereo.left.features[stereo.features[k].left].uv, stereo.right.features[stereo.features[k].right].uv)
          for k, cid in matched.items() if cid in lines}
    images = (inputs.left, inputs.right)
    with inputs.timings.stage("edge-break line places"):
        # The misfit read at the pose registered on the apparent steps, each carrying the whole band: a
        # pose registered on the lines moved would take up the error their places share (one light, one
        # break shape for all) and read it as no misfit. This pose's own error, within its covariance,
        # is read as misfit too: conservative.
        places = line_places(images, inputs.calib, registration.part_to_camera, lines, widths, uv)
        stereo, refitted = lines_at_sharp_edge(stereo, inputs.calib, registration.part_to_camera, matched, lines,
                                               places, stereo.edge_break)
    if refitted:
        progress(f"{len(refitted)} broken line(s) measured at their predicted place")
    return stereo, refitted, {cid: (places.get(cid), line, cid in refitted) for cid, line in lines.items()}


def _judged_across_poses(characteristics, decisions, registration, inputs, progress):
    """The decisions, inconclusive where a competing pose would decide otherwise (:mod:`partinspect.tolerances.ambiguity`).

    Under each competing pose only the characteristics whose features it
    assigns alike are evaluated: the others depend on it whatever their values.
    """
    from partinspect.tolerances.ambiguity import alike, reconcile
    from partinspect.tolerances.decision import decide_all

    rivals = []
    for k, rival in enumerate(registration.competing, 1):
        same = alike(characteristics, registration, rival.registration)
        progress(f"evaluating {len(same)} characteristics under competing pose {k} of {len(registration.competing)} "
                 f"({rival.angle:.1f} degrees away)")
        evaluated = decide_all(_evaluate_on_two_cores(same, rival.registration, inputs.inv),
                               inputs.resolved.decision_rule)
        rivals.append({d.id: d for d in evaluated})
    return reconcile(decisions, registration, rivals)


def _evaluate_on_two_cores(characteristics, registration, inv):
    """`partinspect.tolerances.evaluate.evaluate`, every other characteristic in a forked child.

    Each characteristic's Monte Carlo draws are seeded by its own id, so
    the split changes no number; alternate ones balance the costly form
    values between the two processes.
    """
    from partinspect.tolerances.evaluate import evaluate as evaluate_all
    from partinspect.tolerances.evaluate import with_datum_shifts
    from partinspect.vision.forked import forked

    if len(characteristics) < 2:
        return evaluate_all(characteristics, registration, inv)
    out = list(characteristics)
    # A datum shift places a pattern's members together: after both halves.
    with forked(evaluate_all, out[1::2], registration, inv, datum_shift=False) as odd:
        out[0::2] = evaluate_all(out[0::2], registration, inv, datum_shift=False)
        out[1::2] = odd()
    return with_datum_shifts(out, registration, inv)


def _check_part_path(part):
    part = Path(part)
    if not part.is_file():
        raise InputError(part, "STEP file not found" if not part.exists() else "not a regular file")
    return part


def _pose_hint(pose_hint, bounds, calib):
    if pose_hint is None or isinstance(pose_hint, np.ndarray):
        return pose_hint
    from partinspect.poses import parse_pose

    try:
        return parse_pose(pose_hint, bounds, calib)
    except InputError as e:
        raise InputError(e.path, e.problem.replace("--pose", "--pose-hint")) from None


def _register_again(stereo, inputs, registration):
    """``stereo`` registered from ``registration``'s poses (no search), keeping what it said of the model's symmetry.

    Started from the chosen pose, the registration sees none of the poses
    the CAD model's own turns relate to it, so it cannot name them again;
    they still explain the features equally well, the ones added since
    included: the model, and so the images of its edges, map onto
    themselves under those turns.
    """
    again = _register(stereo, inputs, registration.poses)
    return replace(again, symmetry=again.symmetry or registration.symmetry)


def _register(stereo, inputs, pose_hint=None):
    """Pose of the part and which CAD feature each measured one is; a failure is the images' (exit code 2)."""
    from partinspect.cad.registration import RegistrationError, register

    circles = [f for f in stereo.features if f.kind != "line"]
    lines = [f for f in stereo.features if f.kind == "line"]
    resolved = inputs.resolved
    datums = resolved.alignment_datums
    try:
        try:
            return register(circles, lines, inputs.inv, datums=datums, pose_hint=pose_hint)
        except RegistrationError:
            # The PMI's datums were not asked for by the user: when their
            # edges, as seen, leave the pose free, align on every feature
            # (the report says so, tolerances.from_pmi.datum_entry).
            if not resolved.datum_frame:
                raise
            return register(circles, lines, inputs.inv, datums=None, pose_hint=pose_hint)
    except RegistrationError as e:
        raise InputError(inputs.images, f"cannot align the CAD model to the images: {e.problem}") from None
