"""One ``inspect plan`` run: load the part, the rig and the tolerances, predict, search.

Data flows one way: inputs are read and checked first (a bad input is one
:class:`~partinspect.errors.InputError` naming the file), then the part is
tessellated for the ray caster, the starting pose predicted and, unless
told not to, the fixture poses searched (:mod:`.search`). The report
writers (:mod:`.report`) take the :class:`PlanResult`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from partinspect.errors import InputError
from partinspect.planning.edge_model import DetectorModel
from partinspect.planning.predict import DEFAULT_RATIO

__all__ = ["PlanResult", "run_plan", "EXIT_ALL_DECIDABLE", "EXIT_SOME_UNDECIDABLE"]

EXIT_ALL_DECIDABLE = 0
"""Every characteristic is decidable in the proposed pose."""
EXIT_SOME_UNDECIDABLE = 3
"""Some characteristic is undecidable in every pose tried."""


@dataclass(frozen=True, eq=False)
class PlanResult:
    """What one plan run found.

    Attributes
    ----------
    part, rig, tolerances : Path or None
        The input files.
    calibration : StereoCalibration
    inventory : Inventory
    characteristics : list of Characteristic
    datums : tuple of str or None
    model : DetectorModel
    max_ratio : float
    center : ndarray, shape (3,)
        The part's bounding-box centre, part frame (pivot of the poses).
    start : PosePrediction
    search : SearchResult or None
        None when the search was not asked for.
    check : PoseCheck or None
        The proposed pose's prediction checked on rendered noise draws
        (:func:`partinspect.planning.check.check_pose`); None when not asked
        for. With it, the check's decisions are the plan's.
    views : ViewPlan or None
        The fewest views that decide the characteristics
        (:func:`partinspect.planning.views.plan_views`); None when not
        asked for. With it, its decisions are the plan's.
    not_evaluated : tuple of NotEvaluated
        What the STEP file's PMI holds that no edge characteristic checks
        (`partinspect.tolerances.from_pmi`), with the reasons.
    """

    part: Path
    rig: Path
    tolerances: Path | None
    calibration: object
    inventory: object
    characteristics: list
    datums: tuple | None
    model: DetectorModel
    max_ratio: float
    center: np.ndarray
    start: object
    search: object = None
    check: object = None
    views: object = None
    not_evaluated: tuple = ()

    @property
    def best(self):
        return self.search.best if self.search is not None else self.start

    @property
    def all_decidable(self):
        """Every inspected characteristic decidable in the proposed pose or views (after the check, if one was run)."""
        if self.views is not None:
            return not self.views.undecided
        return self.check.all_decidable if self.check is not None else self.best.all_decidable

    @property
    def exit_code(self):
        return EXIT_ALL_DECIDABLE if self.all_decidable else EXIT_SOME_UNDECIDABLE

    def summary_line(self):
        n = len(self.characteristics)
        s = f"start pose: {self.start.n_decidable} of {n} characteristics decidable (U <= {self.max_ratio:g} x tolerance)"
        if self.search is not None:
            s += (f"; best of {len(self.search.poses)} poses ({self.best.label}): {self.best.n_decidable} of {n}"
                  f"; {len(self.search.never)} undecidable in every pose")
        else:
            s += f"; {len(self.start.undecidable())} undecidable"
        if self.views is not None:
            s += (f"; {len(self.views.views)} view(s) of {len(self.views.candidates)} candidates decide "
                  f"{len(self.views.decided_by)} of {n}; {len(self.views.undecided)} undecided")
        if self.check is not None:
            s += (f"; after the check on {self.check.draws} rendered draws: "
                  f"{sum(c.decidable for c in self.check.characteristics)} of {n} decidable")
        return s


def _check_inputs(part, rig, tolerances, max_ratio, model, check=0):
    part = Path(part)
    if not part.is_file():
        raise InputError(part, "STEP file not found" if not part.exists() else "not a regular file")
    if not (isinstance(max_ratio, (int, float)) and 0 < max_ratio <= 1 and math.isfinite(max_ratio)):
        raise InputError(None, f"--ratio must be a number in (0, 1], got {max_ratio!r}")
    if not (model.noise > 0 and math.isfinite(model.noise)):
        raise InputError(None, f"--noise must be a positive number of grey levels, got {model.noise!r}")
    if model.contrast is not None and not (model.contrast > 0 and math.isfinite(model.contrast)):
        raise InputError(None, f"--contrast must be a positive number of grey levels, got {model.contrast!r}")
    if not (model.blur >= 0 and model.sigma > 0):
        raise InputError(None, "--blur must be >= 0 and --sigma > 0 (pixels)")
    if not (isinstance(check, int) and (check == 0 or check >= 3)):
        raise InputError(None, f"--check must be 0 (no check) or at least 3 draws, got {check!r}")
    if check and model.contrast is not None:
        raise InputError(None, "--check renders the faces' shading and cannot honour a fixed --contrast")
    rig = Path(rig)
    if not rig.exists():
        raise InputError(rig, "calibration file not found")
    from partinspect.tolerances.loading import find_tolerances

    return part, rig, find_tolerances(part, tolerances)


def _check_search(rotation, max_tilt, step, views, tilts, check):
    """The search's and the views' options, each refused by name (exit code 2)."""
    for name, v in (("--rotation", rotation), ("--max-tilt", max_tilt)):
        if not (0 <= v <= 180 and math.isfinite(v)):
            raise InputError(None, f"{name} must be between 0 and 180 degrees, got {v!r}")
    if not (0 < step <= 180):
        raise InputError(None, f"--step must be between 0 and 180 degrees, got {step!r}")
    if not (isinstance(views, int) and 0 <= views <= 8):
        raise InputError(None, f"--views must be a number of views from 1 to 8, got {views!r}")
    if views and not (tilts and all(math.isfinite(t) and -180.0 <= t <= 180.0 for t in tilts)):
        raise InputError(None, f"--tilts must be angles from -180 to 180 degrees, got {tilts!r}")
    if views and check:
        raise InputError(None, "--check renders one pose; it cannot be combined with --views")


def run_plan(part, rig, *, tolerances=None, pose=None, max_ratio=DEFAULT_RATIO, model=None, search=True,
             rotation=180.0, max_tilt=30.0, step=30.0, check=0, seed=0, renderer=None, views=0, tilts=(0.0, 180.0),
             progress=None):
    """Predict the uncertainty of every characteristic and search the fixture poses.

    Parameters
    ----------
    part : str or Path
        STEP file.
    rig : str or Path
        Calibration (``calibration.yaml``, or a folder holding it); it must
        give the image size.
    tolerances : str or Path, optional
        Tolerance spec; default ``PART.tol.yaml`` beside the STEP file. The
        STEP file's PMI tolerances what the spec does not, ISO 2768-mK the
        rest, as for `inspect`.
    pose : str, optional
        ``--pose`` text (``RX,RY,RZ[,TX,TY,TZ]`` or a JSON file with
        ``part_to_camera``, e.g. a render's ``truth.json``); default the
        simulator's default pose.
    max_ratio : float
        Decidable when ``U <= max_ratio * tolerance``.
    model : DetectorModel, optional
    search : bool
        Search fixture poses (else only the starting pose is predicted).
    rotation, max_tilt, step : float
        Search limits, degrees (see :func:`.search.search_poses`).
    check : int
        Check the proposed pose's prediction on this many rendered noise
        draws (0: no check; else at least 3).
    seed : int
        Seed of the check's noise draws.
    renderer : partinspect.planning.check.Renderer, optional
        Makes the check's images; needed when ``check`` is not 0.
    views : int
        Choose up to this many views (turns of the part at ``step``
        degrees, upright and upside down) instead of one pose
        (:mod:`.views`); 0: one pose.
    tilts : sequence of float
        With ``views``: the tilts about the fixture's X axis the candidate
        views are taken at, degrees (0 upright, 180 upside down, 90 or -90
        on a side).
    progress : callable, optional

    Returns
    -------
    PlanResult

    Raises
    ------
    InputError
        Any bad input, naming the file.
    """
    say = progress or (lambda message: None)
    model = model or DetectorModel()
    if check and renderer is None:
        raise ValueError("a check needs a renderer to make its images")
    part, rig, tol_path = _check_inputs(part, rig, tolerances, max_ratio, model, check)
    _check_search(rotation, max_tilt, step, views, tilts, check)

    from partinspect.vision.calibration import read_calibration

    calib = read_calibration(rig)
    if calib.image_size is None:
        raise InputError(rig, "the calibration gives no image size (image_width, image_height), which the plan needs")
    from partinspect.poses import bounds_of, default_pose, parse_pose

    if pose is not None:
        parse_pose(pose, None, calib)  # a malformed --pose fails before the STEP file is loaded

    say(f"loading {part.name}")
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step

    shape = load_step(part)
    inv = inventory(shape)
    if not inv.features:
        raise InputError(part, "no line or circle edges to measure")
    from partinspect.tolerances.loading import load_characteristics

    # As `inspect` does: the STEP file's PMI for what the spec leaves out.
    resolved, chars = load_characteristics(inv, tol_path, part=part)
    datums = resolved.alignment_datums

    bounds = bounds_of(shape)
    start = parse_pose(pose, bounds, calib) if pose is not None else default_pose(bounds, calib)
    center = 0.5 * (bounds[0] + bounds[1])

    say("tessellating the part for the ray caster")
    from partinspect.cad.mesh import tessellate
    from partinspect.planning.predict import predict_pose
    from partinspect.planning.search import FixturePose, search_poses
    from partinspect.cad.raycast import RENDER_ANGULAR_TOLERANCE, RENDER_TOLERANCE
    from partinspect.cad.raycast import build_scene

    scene = build_scene(tessellate(shape, RENDER_TOLERANCE, RENDER_ANGULAR_TOLERANCE, inventory=inv))

    def predict(P, fp):
        return predict_pose(inv, scene, calib, P, chars, model=model, datums=datums,
                            datums_fallback=bool(resolved.datum_frame), max_ratio=max_ratio,
                            label=fp.label, angles=(fp.rotation, fp.tilt_x, fp.tilt_y))

    view_plan = None
    if views:
        from partinspect.planning.views import plan_views

        view_plan = plan_views(predict, start, center, views, step=step, tilts=tuple(tilts), inventory=inv,
                               progress=say)
        start_pred, result = view_plan.candidates[0], None
    elif search:
        result = search_poses(predict, start, center, rotation=rotation, max_tilt=max_tilt, step=step, progress=say)
        start_pred = result.start
    else:
        say("predicting the starting pose")
        start_pred, result = predict(start, FixturePose()), None
    checked = None
    if check:
        from partinspect.planning.check import check_pose

        best = result.best if result is not None else start_pred
        checked = check_pose(inv, scene, calib, best, chars, model, renderer, datums=datums, draws=check, seed=seed,
                             progress=say)
    return PlanResult(part, rig, tol_path, calib, inv, chars, datums, model, max_ratio, center, start_pred, result,
                      checked, view_plan, tuple(resolved.not_evaluated))
