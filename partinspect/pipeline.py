"""One inspection run: load -> measure -> register -> evaluate -> report.

Stages: the STEP model's feature inventory and the tolerance spec
(:mod:`partinspect.tolerances`); the stereo chain from both images to 3D
lines and circles with covariances (:func:`partinspect.vision.stereo.measure_stereo`);
registration of those to the CAD model, with the pose's covariance
(:func:`partinspect.cad.registration.register`); which CAD edges the
cameras can see at that pose (:mod:`partinspect.cad.visibility`); each
characteristic's value and uncertainty (:mod:`partinspect.tolerances.evaluate`)
and its ISO 14253-1 decision (:mod:`partinspect.tolerances.decision`); the
reports. A feature that was not measured says why, its characteristics
are inconclusive, and no number is ever invented.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from partinspect.atomic import check_output_dir, prepare_output_dir
from partinspect.errors import InputError
from partinspect.progress import quiet

EXIT_CODES = {"pass": 0, "fail": 1, "inconclusive": 3}


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
            + f"report: {self.out_dir / 'report.html'}"
        )


def sha256_file(path):
    """SHA-256 hex digest of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def find_tolerances(part, tolerances=None):
    """The tolerance spec for ``part``: the given file, else PART.tol.yaml beside it, else None.

    ``part.step`` looks for ``part.tol.yaml`` (and ``part.tol.yml``).
    """
    if tolerances is not None:
        path = Path(tolerances)
        if not path.is_file():
            raise InputError(path, "tolerance file not found" if not path.exists() else "not a regular file")
        return path
    part = Path(part)
    for suffix in (".tol.yaml", ".tol.yml"):
        candidate = part.with_name(part.stem + suffix)
        if candidate.is_file():
            return candidate
    return None


def _check_part_path(part):
    part = Path(part)
    if not part.is_file():
        raise InputError(part, "STEP file not found" if not part.exists() else "not a regular file")
    return part


def _report_time():
    # SOURCE_DATE_EPOCH makes reports byte-reproducible (reproducible-builds.org convention).
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch is not None:
        return _dt.datetime.fromtimestamp(int(epoch), _dt.timezone.utc)
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0)


def run_inspection(part, images, out="inspection", *, tolerances=None, progress=quiet, uncertainty="first-order",
                   draws=200, pose_hint=None):
    """Inspect a part from a stereo pair and write the reports.

    Parameters
    ----------
    part : str or Path
        STEP file of the part.
    images : str or Path
        Folder with left.png, right.png and the calibration.
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

    Returns
    -------
    InspectionResult

    Raises
    ------
    InputError
        Any bad input (exit code 2 at the command line); nothing is written.
    """
    from partinspect.reports.writer import write_reports
    from partinspect.vision.calibration import read_calibration
    from partinspect.vision.images import IMAGE_NAMES, read_pair

    # Cheap checks first, so a typo fails before seconds of CAD loading.
    part = _check_part_path(part)
    images = Path(images)
    if not images.is_dir():  # else read_calibration would take it for a calibration file
        raise InputError(images, "images folder not found" if not images.exists() else "not a folder (IMAGES_DIR holds left.png, right.png, calibration.yaml)")
    tol_path = find_tolerances(part, tolerances)
    check_output_dir(out)

    progress("reading calibration and images")
    calib = read_calibration(images)
    left, right, bit_depth = read_pair(images, calib)
    calib_file = next(
        (images / n for n in ("calibration.yaml", "calibration.yml", "intrinsics.yml") if (images / n).is_file()),
        None,
    )

    progress(f"loading {part.name}")
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step

    shape = load_step(part)
    inv = inventory(shape)
    if not inv.features:
        raise InputError(part, f"no line or circle edges to measure ({_edges_found(inv)})")
    hint = _pose_hint(pose_hint, shape, calib)

    if tol_path is not None:
        progress(f"reading tolerances {tol_path.name}")
    resolved, characteristics = _characteristics(inv, tol_path)
    spec_info = {
        "file": None if tol_path is None else str(tol_path),
        "general": resolved.general,
        "decision_rule": resolved.decision_rule,
    }

    from partinspect.adaptive import measure_adaptively
    from partinspect.cad.visibility import visibility
    from partinspect.vision.stereo import measure_stereo

    def settle(stereo, registration):
        progress("checking which edges the cameras see")
        seen = visibility(shape, inv, calib, registration.part_to_camera, images=(left, right))
        more, found, ends, withdrawn = posed_stereo(stereo, registration, seen, inv, calib)
        if not found and not ends and not withdrawn:
            # ``more`` is ``stereo`` with the stretches found but not measured, if any.
            return more, registration, seen
        if ends:
            progress(f"{len(ends)} line(s) fitted again clear of the edges at their ends")
        if withdrawn:
            progress(f"{len(withdrawn)} line(s) taken out: another edge's image paired with theirs")
        if found:
            progress(f"measuring {len(found)} edge(s) on their stretches of longer image lines")
        try:
            # The pose is known: no new search (it is the expensive part).
            again = _register(more, inv, resolved, images, registration.part_to_camera)
        except InputError:
            return stereo, registration, seen
        return more, again, visibility(shape, inv, calib, again.part_to_camera, images=(left, right))

    def run_round(params):
        stereo = measure_stereo(
            left, right, calib, sigma=params["sigma"], progress=progress,
            edge_options={"k_low": params["k_low"], "k_high": params["k_high"]},
            match_options={"min_points": params["min_points"]},
        )
        progress(f"registering {len(stereo.features)} measured features to the CAD model")
        try:
            registration = _register(stereo, inv, resolved, images, hint)
        except InputError as e:
            e.stereo = stereo
            raise
        return settle(stereo, registration)

    def merge(base, new, ids):
        stereo = merged_stereo(base.stereo, new.stereo, new.registration, ids)
        progress(f"registering {len(stereo.features)} features, {len(ids)} of them from the re-run")
        return settle(stereo, _register(stereo, inv, resolved, images, hint))

    best, adaptive_log, advice = measure_adaptively(run_round, progress=progress, merge=merge)
    stereo, registration, seen = best.stereo, best.registration, best.visibility
    uncertainty_info = {"method": "first-order propagation (JCGM 100)", "coverage_factor": 2.0}
    if uncertainty == "montecarlo":
        # On the chosen round only: the draws are the expensive part.
        progress(f"Monte Carlo: {draws} draws for each of {len(stereo.features)} features")
        stereo, ratios = _monte_carlo(stereo, calib, draws)
        registration = _register(stereo, inv, resolved, images, hint)
        uncertainty_info = {"method": "Monte Carlo (JCGM 101)", "draws": draws, "seed": 0, "coverage_factor": 2.0,
                            "std_ratio_median": round(float(np.median(ratios)), 4) if len(ratios) else None}

    progress(f"evaluating {len(characteristics)} characteristics")
    from partinspect.tolerances.decision import decide_all
    from partinspect.tolerances.evaluate import evaluate

    # General tolerances cover the whole part, but a stereo pair sees one side
    # of it: general characteristics of edges out of view are listed as not
    # inspected (with the reason) rather than judged; a characteristic the
    # spec names explicitly is always judged, inconclusive when unseen.
    judged, not_inspected = [], []
    for c in characteristics:
        hidden = [fid for fid in c.features if not seen[fid].in_view]
        if hidden and c.source.endswith("(general tolerance)") and not _measured_any(registration, c.features):
            not_inspected.append({**c.to_dict(), "reason": "; ".join(f"{fid} {seen[fid].reason()}" for fid in hidden)})
        else:
            judged.append(c)
    decisions = decide_all(evaluate(judged, registration, inv), resolved.decision_rule)
    characteristics = [_characteristic_entry(d) for d in decisions]

    features = feature_entries(inv, stereo, registration, seen, decisions, calib)
    why = {f["id"]: f["reason"] for f in features if f["measured"] is None}
    for c in characteristics:
        if c["measured"] is None:
            c["reason"] = "not measured: " + "; ".join(f"{fid}: {why[fid]}" for fid in c["features"] if fid in why)

    inputs = [{"role": "part", "path": str(part), "sha256": sha256_file(part)}]
    for role, path in (("left image", images / IMAGE_NAMES[0]), ("right image", images / IMAGE_NAMES[1])):
        inputs.append({"role": role, "path": str(path), "sha256": sha256_file(path)})
    if calib_file is not None:
        inputs.append({"role": "calibration", "path": str(calib_file), "sha256": sha256_file(calib_file)})
    if tol_path is not None:
        inputs.append({"role": "tolerances", "path": str(tol_path), "sha256": sha256_file(tol_path)})

    verdict = decide_verdict([c["decision"] for c in characteristics])
    report = {
        "schema": "report/1",
        "part": part.name,
        "units": "mm",
        "verdict": verdict,
        "created": _report_time().isoformat(),
        "inputs": inputs,
        "images": {"width": left.shape[1], "height": left.shape[0], "bit_depth": bit_depth},
        "tolerances": spec_info,
        "uncertainty": uncertainty_info,
        "adaptive": {"rounds": adaptive_log, "advice": advice},
        "registration": registration_entry(registration),
        "features": features,
        "characteristics": characteristics,
        "not_inspected": not_inspected,
        "skipped_edges": inv.to_dict().get("skipped", {}),
        "summary": {
            "features": len(features),
            "features_measured": sum(f["measured"] is not None for f in features),
            "characteristics": len(characteristics),
            "not_inspected": len(not_inspected),
            **{d: sum(c["decision"] == d for c in characteristics) for d in ("pass", "fail", "inconclusive")},
        },
    }
    progress("writing reports")
    out_dir = prepare_output_dir(out)
    write_reports(out_dir, report, figure_data(left, right, calib, inv, stereo, registration, features))
    return InspectionResult(verdict, report, out_dir)


def merged_stereo(base, new, registration, ids):
    """``base`` (a StereoResult) with the features of ``new`` that ``registration`` assigned to ``ids`` added.

    The added 3D features' image features are appended to ``base``'s of
    each image (their indices renumbered); each carries its own edge data
    and filter scale (:class:`~partinspect.vision.stereo.EdgeFeature`), so
    the result is measured, drawn and Monte Carlo sampled as one. Edges,
    segments, matching and failures stay ``base``'s: what the report says
    of unmatched image features is said of the base round's.
    """
    from dataclasses import replace

    picks = [registration.measured_feature(kind, i) for kind in ("circle", "line")
             for i, cid in sorted(registration.assignment[kind].items()) if cid in ids]
    nl, nr = len(base.left.features), len(base.right.features)
    left = replace(base.left, features=list(base.left.features) + [new.left.features[f.left] for f in picks])
    right = replace(base.right, features=list(base.right.features) + [new.right.features[f.right] for f in picks])
    added = tuple(replace(f, left=nl + j, right=nr + j) for j, f in enumerate(picks))
    return replace(base, left=left, right=right, features=tuple(base.features) + added)


def edge_images(feature, part_to_camera, calib):
    """A CAD line's image in the left and the right camera under a pose.

    Returns
    -------
    tuple of two ndarray, shape (M, 2)
        Distorted pixels, sampled from ``feature.start`` to ``feature.end``
        about half a pixel apart (NaN where a point is behind a camera).
    """
    from partinspect.vision.calibration import project_points

    R, t = part_to_camera[:3, :3], part_to_camera[:3, 3]
    ends = np.array([feature.start, feature.end], float) @ R.T + t
    out = []
    for K, D, Rc, tc in ((calib.K1, calib.D1, np.eye(3), np.zeros(3)), (calib.K2, calib.D2, calib.R, calib.T)):
        uv = project_points(ends, K, D, Rc, tc)
        length = float(np.hypot(*(uv[1] - uv[0]))) if np.isfinite(uv).all() else 0.0
        s = np.linspace(0.0, 1.0, int(min(2 * length, 20000)) + 2)
        out.append(project_points(ends[0] + s[:, None] * (ends[1] - ends[0]), K, D, Rc, tc))
    return tuple(out)


def curve_images(feature, part_to_camera, calib):
    """A CAD edge's image (line, circle or arc) in the left and the right camera under a pose.

    Returns
    -------
    tuple of two ndarray, shape (M, 2)
        Distorted pixels, about half a pixel apart (NaN where a point is
        behind a camera).
    """
    if feature.kind == "line":
        return edge_images(feature, part_to_camera, calib)
    from partinspect.simulate.truth import feature_geometry, sample_edge
    from partinspect.vision.calibration import project_points

    R, t = part_to_camera[:3, :3], part_to_camera[:3, 3]
    g = feature_geometry(feature)
    out = []
    for K, D, Rc, tc in ((calib.K1, calib.D1, np.eye(3), np.zeros(3)), (calib.K2, calib.D2, calib.R, calib.T)):
        coarse = project_points(sample_edge(feature.kind, g, 64)[0] @ R.T + t, K, D, Rc, tc)
        ok = np.isfinite(coarse).all(axis=1)
        length = float(np.sum(np.hypot(*np.diff(coarse[ok], axis=0).T))) if ok.sum() > 1 else 0.0
        n = int(min(2 * length * 64 / 63, 20000)) + 2
        out.append(project_points(sample_edge(feature.kind, g, n)[0] @ R.T + t, K, D, Rc, tc))
    return tuple(out)


def edge_polylines(inv, part_to_camera, calib):
    """Every CAD edge's image in both cameras under a pose: id -> :func:`curve_images`."""
    return {f.id: curve_images(f, part_to_camera, calib) for f in inv.features}


def posed_stereo(stereo, registration, seen, inv, calib):
    """What the registered pose adds to ``stereo``: :func:`cleared_stereo`, then :func:`guided_stereo`.

    Every CAD edge's image is projected once (:func:`edge_polylines`) for
    both. ``seen`` as theirs.

    Returns
    -------
    stereo : StereoResult
    found : dict of str to int
        Of :func:`guided_stereo`.
    cleared, withdrawn : dict
        Of :func:`cleared_stereo`.
    """
    polylines = edge_polylines(inv, registration.part_to_camera, calib)
    cleared, ends, withdrawn = cleared_stereo(stereo, registration, seen, inv, calib, polylines)
    more, found = guided_stereo(cleared, registration, seen, inv, calib, polylines)
    return more, found, ends, withdrawn


def cleared_stereo(stereo, registration, seen, inv, calib, polylines=None):
    """``stereo`` with its registered lines fitted again clear of the other edges' images at their ends.

    Under the registered pose every CAD edge's image is known, faint ones
    too, whose grey step displaces a line's end points without giving edge
    points of its own (:func:`partinspect.vision.guided.clear_line_ends`).
    ``seen``: the visibility of each CAD feature, to take in each image
    only the edges it sees; None to take every edge (more points left out
    near hidden edges' images, never fewer). ``polylines``:
    :func:`edge_polylines` at the registered pose, if already made.

    A line that disagrees with the pose the other features give (a
    registration outlier) and all of whose points in one image lie on
    another edge's image is taken out, with the reason: that image's
    feature is the other edge's, paired with this one's in the other
    image (a face seen nearly edge-on puts two edges on one image line;
    on a stress render two such lines read chi-square 1366 and 11279
    against the pose, and their straightness was that of a line between
    two edges).

    Returns
    -------
    stereo : StereoResult
        ``withdrawn`` holds the lines taken out and why.
    cleared : dict of str to (int, int)
        CAD id -> points left out in the left and the right image.
    withdrawn : dict of str to str
        CAD id -> why its line was taken out.
    """
    from dataclasses import replace

    from partinspect.vision.guided import clear_line_ends

    at = [k for k, f in enumerate(stereo.features) if f.kind == "line"]
    lines = {at[i]: cid for i, cid in registration.assignment["line"].items()}
    if not lines:
        return stereo, {}, {}
    polylines = polylines or edge_polylines(inv, registration.part_to_camera, calib)
    images = {}
    for f in inv.features:
        shown = (1.0, 1.0) if seen is None else seen[f.id].seen
        if max(shown) > 0:
            images[f.id] = tuple(uv if v > 0 else uv[:0] for uv, v in zip(polylines[f.id], shown))
    stereo, cleared, covered = clear_line_ends(stereo, calib, lines, images)
    withdrawn = {}
    for cid, (side, other) in covered.items():
        if cid in registration.outliers and other is not None:
            c2, n = registration.outliers[cid]
            withdrawn[cid] = (f"its points in the {side} image all lie on the image of {other}, and its 3D line "
                              f"disagreed with the pose the other features give (chi-square {c2:.0f} over {n} "
                              f"residuals): {other}'s image paired with its own in the other image")
    if not withdrawn:
        return stereo, cleared, {}
    gone = {k for k, cid in lines.items() if cid in withdrawn}
    stereo = replace(stereo, features=tuple(f for k, f in enumerate(stereo.features) if k not in gone),
                     withdrawn=tuple(withdrawn.items()))
    return stereo, cleared, withdrawn


def guided_stereo(stereo, registration, seen, inv, calib, polylines=None):
    """``stereo`` with the unmeasured line edges in view measured on their stretches of longer image lines.

    Collinear edges of a part merge into one line in each image, whose 3D
    line then matches no single CAD edge; under the registered pose each
    edge's image picks its own stretch
    (:func:`partinspect.vision.guided.guided_lines`). ``seen``: the
    visibility of each CAD feature (:func:`partinspect.cad.visibility.visibility`),
    or None to look for every unmeasured line edge: a hidden one takes no
    points where a seen edge's image runs near its own (every line edge's
    image is given to ``guided_lines`` to keep them apart). ``polylines``:
    :func:`edge_polylines` at the registered pose, if already made.

    Returns
    -------
    stereo : StereoResult
    found : dict of str to int
        CAD id -> index of the 3D line measured for it (empty: ``stereo``
        returned unchanged).
    """
    from partinspect.vision.guided import guided_lines

    done = {cid for kind in ("circle", "line") for cid in registration.assignment[kind].values()}
    todo = [f for f in inv.features if f.kind == "line" and f.id not in done and (seen is None or seen[f.id].in_view)]
    if not todo:
        return stereo, {}
    # Every line edge's image, hidden ones too: a point near two edges' images is either's.
    polylines = polylines or edge_polylines(inv, registration.part_to_camera, calib)
    others = {f.id: polylines[f.id] for f in inv.features if f.kind == "line"}
    expected = {f.id: others[f.id] for f in todo}
    more, found, _ = guided_lines(stereo, calib, expected, set(_image_owners(stereo, registration)), others=others)
    return more, found


def _edges_found(inv):
    """What a model without features has instead, e.g. "its edges: 1 seam (circle)"."""
    parts = [f"{n} {kind}" for kind, n in inv.skipped_edges.items()]
    parts += [f"{n} seam ({kind})" for kind, n in inv.seam_edges.items()]
    if inv.degenerated_edges:
        parts.append(f"{inv.degenerated_edges} degenerated")
    return "its edges: " + ", ".join(parts) if parts else "it has no edges"


def decide_verdict(decisions, any_unmeasured=False):
    """Overall verdict from per-characteristic decisions.

    A single fail fails the part; otherwise any inconclusive characteristic,
    or a part that could not be measured at all, is inconclusive: a part is
    never passed on what was not measured.
    """
    decisions = list(decisions)
    if "fail" in decisions:
        return "fail"
    if any_unmeasured or "inconclusive" in decisions or not decisions:
        return "inconclusive"
    return "pass"


def nominal_geometry(feature):
    """The CAD geometry of a feature as report.json writes it (part frame, mm)."""

    def vec(v):
        return [round(float(x), 9) for x in v]

    if feature.kind == "line":
        return {"start": vec(feature.start), "end": vec(feature.end)}
    g = {"center": vec(feature.center), "normal": vec(feature.normal), "radius": round(float(feature.radius), 9)}
    if feature.kind == "arc":
        g.update(start=vec(feature.start), end=vec(feature.end))
    return g


def _characteristics(inv, tol_path):
    """The resolved spec (or the ISO 2768-mK default) and every characteristic to evaluate."""
    from partinspect.tolerances import spec as spec_mod
    from partinspect.tolerances.resolve import general_characteristics, resolve_spec

    spec = spec_mod.load_spec(tol_path) if tol_path is not None else spec_mod.default_spec()
    resolved = resolve_spec(spec, inv, tol_path)
    return resolved, list(resolved.characteristics) + general_characteristics(inv, resolved)


# ----------------------------------------------------------------- stages


def _monte_carlo(stereo, calib, draws):
    """The stereo result with Monte Carlo covariances in place of the first-order ones.

    Returns the new result and the ratios of Monte Carlo to first-order
    standard uncertainties of the random inputs over all parameters (for
    the report). The systematic (Type B) covariance of a feature is not
    sampled and is added to the Monte Carlo covariance unchanged.
    """
    from dataclasses import replace

    from partinspect.vision.montecarlo import monte_carlo

    feats, ratios = list(stereo.features), []
    for mc in monte_carlo(stereo, calib, draws=draws, seed=0):
        f = feats[mc.feature]
        C = 0.5 * (mc.cov_mc + mc.cov_mc.T)
        # The draws cover the random inputs only; the Type B part (rim shading) is added as it was.
        if getattr(f, "param_cov_systematic", None) is not None:
            C = C + f.param_cov_systematic
        extra = {"radius_std": float(np.sqrt(C[6, 6]))} if f.kind != "line" else {}
        feats[mc.feature] = replace(f, param_cov=C, covariance=C[:3, :3], axis_cov=C[3:6, 3:6], **extra)
        ratios.extend(r for r in mc.std_ratio if np.isfinite(r))
    return replace(stereo, features=tuple(feats)), np.array(ratios)


def _pose_hint(pose_hint, shape, calib):
    if pose_hint is None or isinstance(pose_hint, np.ndarray):
        return pose_hint
    from partinspect.simulate.pose import parse_pose

    try:
        return parse_pose(pose_hint, shape, calib)
    except InputError as e:
        raise InputError(e.path, e.problem.replace("--pose", "--pose-hint")) from None


def _register(stereo, inv, resolved, images, pose_hint=None):
    """Pose of the part and which CAD feature each measured one is."""
    from partinspect.cad.registration import RegistrationError, register

    circles = [f for f in stereo.features if f.kind != "line"]
    lines = [f for f in stereo.features if f.kind == "line"]
    datums = None if resolved.spec.datums is None else list(resolved.datums)
    try:
        return register(circles, lines, inv, datums=datums, pose_hint=pose_hint)
    except RegistrationError as e:
        raise InputError(images, f"cannot align the CAD model to the images: {e.problem}") from None


def _measured_any(registration, feature_ids):
    ids = set(registration.assignment["circle"].values()) | set(registration.assignment["line"].values())
    return any(fid in ids for fid in feature_ids)


def _characteristic_entry(decision):
    d = decision.to_dict()
    # One "reason" a reader can act on: why it is not measured, else why it was decided so.
    d["reason"] = d.get("reason") or decision.reason
    return d


def _vec(v, digits=9):
    return [round(float(x), digits) + 0.0 for x in v]


def _mat(m, digits=15):
    return [[float(f"{x:.{digits}g}") for x in row] for row in np.asarray(m, float)]


def registration_entry(reg):
    """report.json's "registration": the pose, its uncertainty and fit statistics."""
    std = reg.pose_std
    return {
        "part_to_camera": _mat(reg.part_to_camera, 12),
        "rms": round(float(reg.rms), 9),
        "weighted_rms": round(float(reg.weighted_rms), 6),
        "chi2": round(float(reg.chi2), 6),
        "dof": int(reg.dof),
        "datums": list(reg.datums),
        "outliers": [{"feature": fid, "chi2": round(float(c2), 3), "residuals": int(n)}
                     for fid, (c2, n) in sorted(reg.outliers.items())],
        "pose_covariance": _mat(reg.pose_cov),
        "rotation_std_deg": _vec(np.degrees(std[:3]), 9),
        "translation_std": _vec(std[3:], 9),
        "frame": "pose error xi = (rotation vector [rad], translation [mm]) in the part frame",
    }


def _image_feature_reasons(stereo):
    """(side, image feature index) -> why it was not matched, in words."""
    from partinspect.vision.matching import REASONS

    out = {(u.side, u.feature): REASONS.get(u.reason, u.reason) + (f" ({u.detail})" if u.detail else "")
           for u in stereo.matching.unmatched}
    for m, why in stereo.failed:
        out[("left", m.left)] = out[("right", m.right)] = f"matched, but {why}"
    return out


COVERED_FRACTION = 0.5
"""An image feature that runs along at least this fraction of a CAD edge's
image (within 2 px) but mostly elsewhere found that edge as part of a
longer one: collinear edges of the part (a step's two lips, a slot's two
sides in line) merge into one line in the images."""


def _image_owners(stereo, registration):
    """(side, image feature index) -> the CAD id its 3D feature was registered as."""
    owners = {}
    for kind in ("circle", "line"):
        for i, cid in registration.assignment[kind].items():
            f = registration.measured_feature(kind, i)
            owners[("left", f.left)] = owners[("right", f.right)] = cid
    return owners


def _edge_points_along(measured, uv, lo, hi, reach=1.5):
    """Whether the detector's edge points run along at least COVERED_FRACTION of an edge's image.

    The edge was detected, but its points were left out of every line and
    arc: a short edge between two corners loses its ends to them
    (:func:`partinspect.vision.contours._crowded`) and what is left is too
    few points for a fit.
    """
    from scipy.spatial import cKDTree

    xy = measured.edges.xy
    box = np.all((xy >= lo) & (xy <= hi), axis=1)
    if len(uv) == 0 or box.sum() < 2:
        return False
    return bool(np.mean(cKDTree(xy[box]).query(uv)[0] < reach) >= COVERED_FRACTION)


def _unmeasured_reason(feature, vis, calib, pose, stereo, unmatched_reasons, owners=None):
    """Why a CAD feature has no measurement: out of view, or what became of its edge in the images.

    ``owners``: :func:`_image_owners`, to name the edge a longer image
    feature that also covers this one was measured as.
    """
    if not vis.in_view:
        return "not visible: " + vis.reason()
    noise = max(float(stereo.left.noise), float(stereo.right.noise))
    if not vis.shows_edge(noise):
        return (f"in view, but with too little grey-level step across it to be detected ({vis.contrast[0]:.0f} and "
                f"{vis.contrast[1]:.0f} grey levels in the left and right image; image noise {noise:.1f}): "
                "its two faces look alike under this lighting")
    withdrawn = dict(getattr(stereo, "withdrawn", ())).get(feature.id)
    if withdrawn:
        return f"measured, then taken out: {withdrawn}"
    from scipy.spatial import cKDTree

    from partinspect.simulate.truth import feature_geometry, sample_edge
    from partinspect.vision.calibration import project_points

    pts, _ = sample_edge(feature.kind, feature_geometry(feature))
    R, t = pose[:3, :3], pose[:3, 3]
    found, longer_sides = [], 0
    for side, K, D, Rc, tc in (("left", calib.K1, calib.D1, np.eye(3), np.zeros(3)), ("right", calib.K2, calib.D2, calib.R, calib.T)):
        uv = project_points(pts @ R.T + t, K, D, Rc, tc)
        tree = cKDTree(uv[np.isfinite(uv).all(axis=1)])
        feats = (stereo.left if side == "left" else stereo.right).features
        near = [i for i, f in enumerate(feats) if len(f.uv) and np.median(tree.query(f.uv)[0]) < 2.0]
        reasons = [unmatched_reasons[(side, i)] for i in near if (side, i) in unmatched_reasons]
        if not near:
            ok = np.isfinite(uv).all(axis=1)
            lo, hi = (uv[ok].min(axis=0) - 2.0, uv[ok].max(axis=0) + 2.0) if ok.any() else (np.inf, -np.inf)
            longer = [i for i, f in enumerate(feats) if len(f.uv) and np.all(f.uv.max(axis=0) >= lo)
                      and np.all(f.uv.min(axis=0) <= hi)
                      and np.mean(cKDTree(f.uv).query(uv[ok])[0] < 2.0) >= COVERED_FRACTION]
            if longer:
                i = longer[0]
                owner = (owners or {}).get((side, i))
                if owner:
                    fate = f"measured as {owner}"
                elif (side, i) in unmatched_reasons:
                    fate = f"not matched: {unmatched_reasons[(side, i)]}"
                else:
                    fate = "which matched no single CAD edge"
                found.append(f"{side} image: found as part of a longer edge that runs on past it, {fate}")
                longer_sides += 1
            elif _edge_points_along(stereo.left if side == "left" else stereo.right, uv[ok], lo, hi):
                length = float(np.sum(np.linalg.norm(np.diff(uv[ok], axis=0), axis=1)))
                why = ("too few of them clear of the edges meeting it at its ends for a line fit"
                       if feature.kind == "line" else "the segmentation kept no arc of them")
                found.append(f"{side} image: edge points found along it, but {why} (its image is {length:.0f} px long)")
            else:
                found.append(f"no edge found along it in the {side} image")
        elif reasons:
            found.append(f"{side} image: {reasons[0]}")
    # Its own stretch of a longer image line found but not measured says more
    # than "found as part of a longer edge"; a reason the matching gave an
    # image feature of its own (along the epipolar lines, say) says more still.
    stretch = dict(getattr(stereo, "guided_failed", ())).get(feature.id)
    if stretch and longer_sides == len(found):
        return f"its own stretch of a longer straight edge was found in both images, but not measured: {stretch}"
    return "; ".join(found) if found else "seen in both images but not matched to the CAD model"


def feature_entries(inv, stereo, registration, seen, decisions, calib):
    """report.json's "features": nominal and measured geometry (part frame) with covariances."""
    parts = {p.cad_id: p for p in registration.features_in_part_frame() if p.cad_id is not None}
    index = {"circle": [f for f in stereo.features if f.kind != "line"], "line": [f for f in stereo.features if f.kind == "line"]}
    worst = {}
    rank = {"pass": 0, "inconclusive": 1, "fail": 2}
    for d in decisions:
        for fid in d.evaluation.characteristic.features:
            if rank[d.decision] >= rank.get(worst.get(fid), -1):
                worst[fid] = d.decision
    reasons = _image_feature_reasons(stereo)
    owners = _image_owners(stereo, registration)
    out = []
    for f in inv.features:
        entry = {"id": f.id, "kind": f.kind, "nominal": nominal_geometry(f), "visibility": {
            "left": round(seen[f.id].seen[0], 3), "right": round(seen[f.id].seen[1], 3)}}
        p = parts.get(f.id)
        if p is None:
            entry.update(measured=None, status="not measured",
                         reason=_unmeasured_reason(f, seen[f.id], calib, registration.part_to_camera, stereo, reasons,
                                                       owners))
        else:
            f3 = index[p.kind][p.index]
            if p.kind == "circle":
                m = {"center": _vec(p.center), "normal": _vec(p.normal), "radius": round(p.radius, 9),
                     "covariance": _mat(p.covariance), "radius_std": float(f"{p.radius_std:.6g}")}
            else:
                m = {"point": _vec(p.point), "direction": _vec(p.direction), "start": _vec(p.start), "end": _vec(p.end),
                     "covariance": _mat(p.covariance)}
            m.update(n_points=int(len(f3.correspondences)), datum=bool(p.datum), measured_as=f3.kind)
            entry.update(measured=m, status=worst.get(f.id, "measured"))
            if f3.guided is not None:
                entry["reason"] = ("measured on its own stretch of a longer straight edge in the images (edges in "
                                   "line with it merge into one there), the stretch its CAD edge's image covers")
        out.append(entry)
    return out



def _curve_3d(f, n=96):
    """Points along a measured Feature3D (rig frame, mm) for drawing."""
    if f.kind == "line":
        return f.start + np.linspace(0.0, 1.0, n)[:, None] * (f.end - f.start)
    from partinspect.frames import orthonormal_frame

    e1, e2, _ = orthonormal_frame(f.normal)
    a = np.linspace(f.angle_start, f.angle_end, n)
    return f.center + f.radius * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)


def figure_data(left, right, calib, inv, stereo, registration, features):
    """The data behind the report's figures (:mod:`partinspect.reports.figures`).

    Images as recorded; overlays in distorted pixels (each measured feature
    is its 3D fit projected back through the lens model, so the overlay
    shows the reconstruction, not just the detected edge); 3D data in the
    part frame.
    """
    from partinspect.simulate.truth import feature_geometry, sample_edge
    from partinspect.vision.calibration import project_points

    status = {e["id"]: e["status"] for e in features}
    cad_of = {}
    for kind, key in (("circle", lambda f: f.kind != "line"), ("line", lambda f: f.kind == "line")):
        measured = [f for f in stereo.features if key(f)]
        for i, cid in registration.assignment[kind].items():
            cad_of[id(measured[i])] = cid
    cams = {"left": (calib.K1, calib.D1, np.eye(3), np.zeros(3)), "right": (calib.K2, calib.D2, calib.R, calib.T)}
    overlays, residuals, used = [], [], {"left": set(), "right": set()}
    for f in stereo.features:
        label = cad_of.get(id(f), "")
        X = _curve_3d(f)
        for side, index in (("left", f.left), ("right", f.right)):
            used[side].add(index)
            K, D, R, t = cams[side]
            overlays.append({"image": side, "xy": project_points(X, K, D, R, t), "kind": f.kind, "label": label,
                             "status": status.get(label, "measured") if label else "unmatched"})
            fit = (stereo.left if side == "left" else stereo.right).features[index].fit
            residuals.append({"label": label or f"unregistered {f.kind}", "image": side, "residuals": np.asarray(fit.residuals),
                              "sigma": float(np.median(fit.point_std))})
    for side in ("left", "right"):
        for i, imf in enumerate((stereo.left if side == "left" else stereo.right).features):
            if i not in used[side]:
                overlays.append({"image": side, "xy": imf.uv, "kind": imf.kind, "label": "", "status": "unmatched"})
    points3d = [{"label": p.cad_id, "points": p.points, "covs": p.point_covs, "status": status.get(p.cad_id, "measured")}
                for p in registration.features_in_part_frame() if p.cad_id is not None and p.points is not None]
    cad_edges = [{"label": f.id, "polyline": sample_edge(f.kind, feature_geometry(f), n=120)[0]} for f in inv.features]
    return {"left": left, "right": right, "overlays": overlays, "residuals": residuals, "points3d": points3d, "cad_edges": cad_edges}
