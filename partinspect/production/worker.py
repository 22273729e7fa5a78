"""One part of a batch, as a worker process (local or on a Dask cluster) runs it.

:func:`inspect_part` is the one function both executors call: it runs
:func:`partinspect.pipeline.run_inspection` into ``OUT/SERIAL/`` and returns
a small picklable record for the results database. A worker stays alive
across parts, so its heavy imports happen once, and it keeps each STEP
file's model (inventory, mesh, PMI; `partinspect.cad.model`) keyed by the file's
sha256: a part number is loaded once per worker, not once per part.
"""

from __future__ import annotations

import hashlib
import os
import socket
import time
from collections import OrderedDict
from datetime import datetime, timezone
from pathlib import Path

from partinspect import __version__
from partinspect.atomic import remove_stale_temporaries
from partinspect.digest import sha256_file
from partinspect.errors import InputError

VIEWS_NOT_REFINED = "--refine-rig refines the rig from one image pair; this is a views folder"

# Models kept per worker; a line runs a few part numbers at a time.
CACHE_SIZE = 8
_MODELS = OrderedDict()
CHARACTERISTIC_KEYS = ("id", "type", "feature", "unit", "nominal", "measured", "deviation", "standard_uncertainty",
                       "expanded_uncertainty", "coverage_factor", "lower_limit", "upper_limit", "decision", "source",
                       "rule")


def sha256(path):
    """Hex sha256 of a file's bytes; None when it cannot be read."""
    try:
        return sha256_file(path)
    except OSError:
        return None


def cached_model(path):
    """The STEP file's CadModel (`partinspect.cad.model`), loaded once per content (sha256) in this process."""
    from partinspect.pipeline import load_cad_model

    key = sha256(path)
    if key in _MODELS:
        _MODELS.move_to_end(key)
        return _MODELS[key]
    model = load_cad_model(path)
    if key is not None:
        _MODELS[key] = model
        while len(_MODELS) > CACHE_SIZE:
            _MODELS.popitem(last=False)
    return model


def share_cpus(threads):
    """Make this worker process compute on ``threads`` CPUs (a local pool's initializer).

    OpenCV's thread pool gets ``threads`` threads; with fewer than two, the
    pipeline forks no second process (:mod:`partinspect.vision.forked`):
    the batch's other workers have the other CPUs.
    """
    import cv2

    from partinspect.vision import forked

    cv2.setNumThreads(threads)
    if threads < 2:
        forked.ENABLED = False


def inspect_part(job, out, refine_rig=False):
    """Inspect one part of a batch into ``out/SERIAL``; never raises for the part's own failure.

    Parameters
    ----------
    job : partinspect.production.manifest.Job
    out : str or Path
        The batch's output folder.
    refine_rig : bool
        Refine the rig from the part's circles as ``inspect --refine-rig``
        does (:func:`partinspect.pipeline.refined_rig`); a views folder
        cannot be, and is a part that could not be run, as at the command line.

    Returns
    -------
    dict
        ``part``: the ``parts`` row (status "done" or "failed", exit code,
        verdict, inputs' sha256, timing, worker, ``rig_refined``: None
        when not asked, else whether the run measured with the refined
        rig); ``characteristics``:
        report.json's characteristics (empty when the run could not be made).
    """
    from partinspect.multiview import is_views_folder, run_views
    from partinspect.pipeline import CALIBRATION_NAMES, run_inspection

    t0 = time.perf_counter()
    report_dir = Path(out) / job.serial
    error, report = None, None
    # An earlier try of this part, killed while writing, may have left temporaries.
    remove_stale_temporaries(report_dir)
    try:
        views = is_views_folder(job.images)
        if views and refine_rig:
            raise InputError(job.images, VIEWS_NOT_REFINED)
        more = {} if views else {"refine_rig": refine_rig}
        result = (run_views if views else run_inspection)(job.step, job.images, report_dir, tolerances=job.spec,
                                                          load_cad=cached_model, **more)
        report = result.report
        status, code, verdict = "done", result.exit_code, result.verdict
    except InputError as exc:
        status, code, verdict, error = "failed", 2, None, str(exc)
    except Exception as exc:  # one part's internal error must not end the batch
        status, code, verdict = "failed", 2, None
        error = f"internal error: {type(exc).__name__}: {' '.join(str(exc).split())}"
    spec = job.spec or _spec_used(report)
    part = {
        "serial": job.serial, "step_file": str(job.step), "step_sha256": sha256(job.step),
        "images": str(job.images), "left_sha256": images_digest(job.images, ("left.png",)),
        "right_sha256": images_digest(job.images, ("right.png",)),
        "calibration_sha256": images_digest(job.images, CALIBRATION_NAMES),
        "spec_file": None if spec is None else str(spec), "spec_sha256": None if spec is None else sha256(spec),
        "measured_at": job.time or datetime.now(timezone.utc).replace(tzinfo=None, microsecond=0),
        "software_version": __version__, "status": status, "exit_code": code, "verdict": verdict, "error": error,
        "report_dir": str(report_dir) if report is not None else None,
        "seconds": round(time.perf_counter() - t0, 3), "worker": f"{socket.gethostname()}:{os.getpid()}",
        "subgroup": job.subgroup, "rig_refined": _rig_refined(report) if refine_rig else None,
    }
    chars = [] if report is None else [{k: c.get(k) for k in CHARACTERISTIC_KEYS} for c in report["characteristics"]]
    return {"part": part, "characteristics": chars}


def images_digest(images, names):
    """Hex sha256 of a part's input file in its images folder; for a views folder, of every view's.

    Parameters
    ----------
    images : Path
        A pair's folder, or a views folder (:func:`partinspect.multiview.is_views_folder`).
    names : sequence of str
        The file's accepted names, first found wins (``left.png``; the
        calibration's names).

    Returns
    -------
    str or None
        A pair's file's sha256. A views folder's: the sha256 of its own file
        (a calibration shared by the views) and of each view's, as lines
        ``name:sha256`` (``.`` for the folder itself), in the views' order;
        None when no such file exists.
    """
    from partinspect.multiview import is_views_folder, view_folders

    def own(folder):
        path = next((folder / n for n in names if (folder / n).is_file()), None)
        return None if path is None else sha256(path)

    if not is_views_folder(images):
        return own(images)
    folders = [(".", images)] + [(f.name, f) for f in view_folders(images)]
    lines = [f"{name}:{d}" for name, f in folders if (d := own(f)) is not None]
    return hashlib.sha256("\n".join(lines).encode()).hexdigest() if lines else None


def _rig_refined(report):
    """Whether the run measured with the rig refined from the part (report.json's ``rig_refinement``)."""
    return None if report is None else bool(report.get("rig_refinement", {}).get("refined", False))


def _spec_used(report):
    if report is None:
        return None
    return next((Path(i["path"]) for i in report.get("inputs", []) if i.get("role") == "tolerances"), None)
