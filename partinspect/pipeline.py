"""One inspection run: load -> measure -> register -> evaluate -> report.

The measurement stages (2D edges and fits, stereo 3D, registration,
characteristics) plug in here as they land. Until a stage exists the run
says so: features not measured are listed as "not measured", their
characteristics are inconclusive, and no number is ever invented.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

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
            f"{counts['features_measured']} of {counts['features']} features measured; "
            f"report: {self.out_dir / 'report.html'}"
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


def run_inspection(part, images, out="inspection", *, tolerances=None, progress=quiet):
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

    inv = inventory(load_step(part))
    if not inv.features:
        raise InputError(part, f"no line or circle edges to measure ({_edges_found(inv)})")

    characteristics = []
    spec_info = {"file": None, "general": "ISO2768-mK", "decision_rule": "iso14253"}
    if tol_path is not None:
        progress(f"reading tolerances {tol_path.name}")
    characteristics, spec_info = _characteristics(inv, tol_path, spec_info)

    # No measurement stage has landed yet: every feature is reported as not
    # measured and every characteristic stays inconclusive for that reason.
    features = [
        {
            "id": f.id,
            "kind": f.kind,
            "nominal": nominal_geometry(f),
            "measured": None,
            "status": "not measured",
            "reason": "the stereo measurement chain is not implemented yet",
        }
        for f in inv.features
    ]
    for c in characteristics:
        c.update(measured=None, deviation=None, standard_uncertainty=None, expanded_uncertainty=None)
        c.update(decision="inconclusive", reason="not measured")

    inputs = [{"role": "part", "path": str(part), "sha256": sha256_file(part)}]
    for role, path in (("left image", images / IMAGE_NAMES[0]), ("right image", images / IMAGE_NAMES[1])):
        inputs.append({"role": role, "path": str(path), "sha256": sha256_file(path)})
    if calib_file is not None:
        inputs.append({"role": "calibration", "path": str(calib_file), "sha256": sha256_file(calib_file)})
    if tol_path is not None:
        inputs.append({"role": "tolerances", "path": str(tol_path), "sha256": sha256_file(tol_path)})

    verdict = decide_verdict([c["decision"] for c in characteristics], any_unmeasured=True)
    report = {
        "schema": "report/1",
        "part": part.name,
        "units": "mm",
        "verdict": verdict,
        "created": _report_time().isoformat(),
        "inputs": inputs,
        "images": {"width": left.shape[1], "height": left.shape[0], "bit_depth": bit_depth},
        "tolerances": spec_info,
        "registration": None,
        "features": features,
        "characteristics": characteristics,
        "skipped_edges": inv.to_dict().get("skipped", {}),
        "summary": {
            "features": len(features),
            "features_measured": sum(f["measured"] is not None for f in features),
            "characteristics": len(characteristics),
            **{d: sum(c["decision"] == d for c in characteristics) for d in ("pass", "fail", "inconclusive")},
        },
    }
    progress("writing reports")
    out_dir = prepare_output_dir(out)
    write_reports(out_dir, report)
    return InspectionResult(verdict, report, out_dir)


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


def _characteristics(inv, tol_path, spec_info):
    """Characteristic definitions from the spec plus ISO 2768 general tolerances."""
    try:
        from partinspect.tolerances import spec as spec_mod
    except ImportError:  # the tolerance module has not landed
        return [], spec_info
    if tol_path is not None:
        spec = spec_mod.load_spec(tol_path)
    else:
        spec = spec_mod.default_spec()
    chars = spec_mod.characteristics_for(spec, inv, tol_path)
    info = {"file": None if tol_path is None else str(tol_path), "general": spec.general, "decision_rule": spec.decision_rule}
    return [c.to_dict() for c in chars], info
