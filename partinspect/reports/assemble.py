"""report.json assembled: inputs with their hashes, the run's entries, the summary.

Every input file is named with its SHA-256, so a report can be traced to
the exact bytes it judged. Numbers are rounded as they are written, so the
same run gives the same file byte for byte (with ``SOURCE_DATE_EPOCH`` set,
the time stamp too).
"""

import datetime as _dt
import os

import numpy as np

from partinspect.digest import sha256_file

__all__ = ["SCHEMA", "sha256_file", "report_time", "with_timings", "input_entries", "vec", "mat", "assemble_report"]

SCHEMA = "report/1"


def with_timings(report, timings):
    """report.json with the run's ``timings`` (`partinspect.timings.Timings`) added.

    Left out when ``SOURCE_DATE_EPOCH`` is set: wall-clock seconds would
    make the file differ from run to run.
    """
    if os.environ.get("SOURCE_DATE_EPOCH") is not None:
        return report
    return {**report, "timings": timings.to_dict()}


def report_time():
    """Now (UTC, whole seconds), or SOURCE_DATE_EPOCH when set."""
    # SOURCE_DATE_EPOCH makes reports byte-reproducible (reproducible-builds.org convention).
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch is not None:
        return _dt.datetime.fromtimestamp(int(epoch), _dt.timezone.utc)
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0)


def input_entries(part, left, right, calibration=None, tolerances=None):
    """report.json's "inputs": each input file's role, path and SHA-256.

    Parameters
    ----------
    part, left, right : Path
        The STEP file and the two images.
    calibration, tolerances : Path, optional
        The calibration and tolerance files, where there are such files.

    Returns
    -------
    list of dict
    """
    inputs = [{"role": "part", "path": str(part), "sha256": sha256_file(part)}]
    for role, path in (("left image", left), ("right image", right)):
        inputs.append({"role": role, "path": str(path), "sha256": sha256_file(path)})
    if calibration is not None:
        inputs.append({"role": "calibration", "path": str(calibration), "sha256": sha256_file(calibration)})
    if tolerances is not None:
        inputs.append({"role": "tolerances", "path": str(tolerances), "sha256": sha256_file(tolerances)})
    return inputs


def vec(v, digits=9):
    """A vector as report.json writes it: rounded to ``digits`` decimals, no -0.0."""
    return [round(float(x), digits) + 0.0 for x in v]


def mat(m, digits=15):
    """A matrix as report.json writes it: ``digits`` significant digits."""
    return [[float(f"{x:.{digits}g}") for x in row] for row in np.asarray(m, float)]


def assemble_report(*, part, verdict, inputs, image, tolerances, uncertainty, adaptive, registration, features,
                    characteristics, not_inspected, skipped_edges, calibration=None, rig_refinement=None):
    """report.json (schema report/1) from its parts, with the summary counted.

    Parameters
    ----------
    part : str
        The STEP file's name.
    verdict : str
        "pass", "fail" or "inconclusive".
    inputs : list of dict
        :func:`input_entries`.
    image : dict
        ``width``, ``height``, ``bit_depth`` of the images.
    tolerances, uncertainty, adaptive, registration : dict
        The spec used, how uncertainties were obtained, the adaptive rounds,
        the registration entry.
    calibration : dict, optional
        The calibration checked against the images (its epipolar residual,
        verdict and any correction); left out when not checked.
    rig_refinement : dict, optional
        The rig re-estimated from the part's circles (``inspect
        --refine-rig``), or why it was not; left out when not asked for.
    features, characteristics, not_inspected : list of dict
    skipped_edges : dict
        Edges of the model that are neither lines nor circles, by kind.

    Returns
    -------
    dict
    """
    return {
        "schema": SCHEMA,
        "part": part,
        "units": "mm",
        "verdict": verdict,
        "created": report_time().isoformat(),
        "inputs": inputs,
        "images": image,
        "tolerances": tolerances,
        "uncertainty": uncertainty,
        "adaptive": adaptive,
        **({"calibration_check": calibration} if calibration is not None else {}),
        **({"rig_refinement": rig_refinement} if rig_refinement is not None else {}),
        "registration": registration,
        "features": features,
        "characteristics": characteristics,
        "not_inspected": not_inspected,
        "skipped_edges": skipped_edges,
        "summary": {
            "features": len(features),
            "features_measured": sum(f["measured"] is not None for f in features),
            "characteristics": len(characteristics),
            "not_inspected": len(not_inspected),
            **{d: sum(c["decision"] == d for c in characteristics) for d in ("pass", "fail", "inconclusive")},
        },
    }
