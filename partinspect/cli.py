"""The `inspect` command: argument parsing, exit codes and progress; no maths.

Heavy libraries (cadquery, embreex, cv2) are imported only by the subcommand
that needs them, so ``inspect --help`` answers at once.

Exit codes (DESIGN.md): 0 every characteristic passes; 1 at least one fails;
3 no fail but some inconclusive; 2 the run could not be made (bad input or
usage), with one line on stderr naming the file and the problem.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

# The console script imports this module first: --timings counts from here.
_START = time.perf_counter()

from partinspect import __version__
from partinspect.errors import InputError

# One BLAS thread per process, set before NumPy loads its OpenBLAS: the
# chain's dense products are small and gain nothing from a second thread,
# and an OpenBLAS worker left spinning after a two-thread product takes the
# CPU the chain's second process needs (vision.forked); a user's own
# setting is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

EXIT_PASS, EXIT_FAIL, EXIT_ERROR, EXIT_INCONCLUSIVE = 0, 1, 2, 3

SUBCOMMANDS = ("features", "render", "calibrate", "plan", "spec", "batch", "spc")

MAIN_DESCRIPTION = """\
Inspect a machined part against its STEP model from one calibrated stereo
image pair. Writes report.html, report.json and junit.xml into OUT.

IMAGES_DIR holds left.png, right.png and calibration.yaml (or OpenCV
stereo_calib's intrinsics.yml + extrinsics.yml); or several views, one
sub-folder per pair (view-1/, view-2/, ...) with a shared calibration.yaml
or one each: each view is measured, and the features fused. Tolerances come from
--tolerances, else PART.tol.yaml beside the STEP file (part.tol.yaml for
part.step); the STEP file's semantic PMI (AP242) for what that leaves out;
ISO 2768-mK general tolerances for the rest.

other commands:
  inspect features PART.step [--json]     list the CAD features and their ids
  inspect features PART.step --pmi        list the STEP file's PMI and the features each applies to
  inspect spec PART.step [-o FILE]        write the PMI as an editable tolerance spec
  inspect render PART.step OUT_DIR [...]  render a synthetic stereo pair with exact ground truth
  inspect calibrate PAIRS_DIR -o calibration.yaml --board 9x6 --square 25
                                          calibrate the stereo rig from board image pairs,
                                          with the parameters' standard uncertainties
  inspect plan PART.step --rig calibration.yaml [--pose POSE] [--ratio 0.25]
                                          predict each characteristic's U before measuring,
                                          and search the fixture pose where all are decidable
  inspect batch MANIFEST -o OUT [--db URL] [--resume] [--workers N] [--scheduler tcp://HOST:PORT]
                [--refine-rig]
                                          inspect many parts (CSV/YAML manifest or SERIAL/images/
                                          folders), record them in a results database, write an SPC page
  inspect spc DB [-o OUT] [--export FILE.csv|FILE.parquet]
                                          statistical process control page of a results database,
                                          or its table of every part and characteristic
  (inspect COMMAND --help for each)

exit codes: 0 pass, 1 fail, 3 inconclusive, 2 the run could not be made."""


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are one line, exit code 2."""

    def error(self, message):
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _main_parser():
    p = _Parser(
        prog="inspect",
        usage="inspect PART.step IMAGES_DIR [-o OUT] [--tolerances FILE] [--quiet]\n       inspect {features,render,calibrate,plan,spec,batch,spc} ...",
        description=MAIN_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("part", metavar="PART.step", help="the part's CAD model (STEP AP203/AP214/AP242)")
    p.add_argument("images", metavar="IMAGES_DIR", help="folder with left.png, right.png, calibration.yaml")
    p.add_argument("-o", "--output", metavar="OUT", default="inspection", help="output folder (default: ./inspection)")
    p.add_argument("--tolerances", metavar="FILE", help="tolerance spec (YAML); default PART.tol.yaml beside the STEP file")
    p.add_argument(
        "--pose-hint",
        metavar="POSE",
        help="the part's approximate pose, to skip the search or settle a symmetric part: a JSON file with "
        "part_to_camera (a render's truth.json, a plan's best_pose.json) or RX,RY,RZ,TX,TY,TZ as inspect render",
    )
    p.add_argument(
        "--uncertainty",
        choices=("first-order", "montecarlo"),
        default="first-order",
        help="how the 3D features' covariances are obtained: first-order propagation (default) or a "
        "Monte Carlo of the edge points and calibration (JCGM 101; slower)",
    )
    p.add_argument("--draws", metavar="N", type=int, default=200, help="Monte Carlo draws per feature (default 200)")
    p.add_argument("--refine-rig", action="store_true",
                   help="re-estimate the rig's relative orientation from the part's own circles (a bundle adjustment, "
                   "the stated calibration as prior, the baseline's length kept) and measure with it; the report "
                   "shows the correction beside the stated calibration")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--timings", action="store_true",
                   help="print each stage's wall-clock seconds on stderr at the end (report.json holds them always)")
    p.add_argument("--debug", action="store_true", help="show a traceback on internal errors")
    p.add_argument("--version", action="version", version=f"partinspect {__version__}")
    return p


def _features_parser():
    p = _Parser(prog="inspect features", description="List the line, circle and arc edges of a STEP model with their ids.")
    p.add_argument("part", metavar="PART.step")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--pmi", action="store_true", help="list the semantic PMI (AP242) and the features each item applies to")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    return p


def _spec_parser():
    p = _Parser(prog="inspect spec", description="Write the tolerance spec equivalent to a STEP file's semantic PMI "
                "(AP242), with each limit's PMI item and what is not evaluated as comments.")
    p.add_argument("part", metavar="PART.step")
    p.add_argument("-o", "--output", metavar="FILE", help="the spec file to write (default: print it)")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    return p


def _render_parser():
    p = _Parser(
        prog="inspect render",
        description=(
            "Render a synthetic stereo pair of a STEP part with exact ground truth: writes "
            "OUT_DIR/images/{left,right}.png, OUT_DIR/images/calibration.yaml and OUT_DIR/truth.json."
        ),
    )
    p.add_argument("part", metavar="PART.step")
    p.add_argument("out", metavar="OUT_DIR")
    p.add_argument(
        "--pose",
        metavar="POSE",
        help="RX,RY,RZ[,TX,TY,TZ]: degrees about the part's bounding-box centre, then its position in mm in "
        "the left camera frame; or a JSON file with part_to_camera (default: a tilted view of the part)",
    )
    p.add_argument("--noise", metavar="SIGMA", type=float, default=None,
                   help="sensor noise, grey levels (default 2; not with --photon)")
    p.add_argument("--seed", metavar="S", type=int, default=0, help="noise seed (default 0)")
    p.add_argument(
        "--deviate",
        metavar="ID.PARAM=DELTA",
        action="append",
        default=[],
        help="render a part that differs from the STEP file, e.g. circle-3.diameter=0.08 or "
        "circle-2.center=0.1,0,0 (mm; repeatable)",
    )
    p.add_argument("--distortion", action="store_true", help="render through a realistic lens distortion")
    p.add_argument("--calib-error", metavar="SEED", type=int, default=None,
                   help="write calibration.yaml as a board calibration of the rig states it (seeded), not the exact rig; "
                   "truth.json keeps the true rig")
    p.add_argument("--drift", metavar="KIND=PX", default=None,
                   help="render with the right camera drifted after calibration: shift=PX (its principal point moved "
                   "down) or roll=PX (turned about its axis, PX at the image's side edges); calibration.yaml states "
                   "the rig before")
    p.add_argument("--edge-break", metavar="R|C", default=None,
                   help="render every convex edge rounded by R mm (0.1 or R0.1) or chamfered (C0.2), as machined "
                   "(ISO 13715); the STEP file stays sharp, truth.json lists edges that could not be broken")
    p.add_argument("--material", metavar="NAME[:SEED]", default=None,
                   help="matte (default, Lambertian), aluminium (milled) or steel (ground): a microfacet highlight "
                   "and seeded machining marks")
    p.add_argument("--defocus", metavar="N,FOCUS_MM", default=None,
                   help="thin lenses of f-number N focused at FOCUS_MM from each camera: the blur grows with depth "
                   "(e.g. 8,400)")
    p.add_argument("--photon", metavar="FULL_WELL,GAIN,READ", default=None,
                   help="Poisson-Gaussian sensor noise and cos^4 vignetting instead of --noise: full well (e-), gain "
                   "(DN/e-), read noise (e-), e.g. 10000,0.0255,5")
    p.add_argument("--light", metavar="X,Y,Z", default=None,
                   help="direction towards the light in the left camera frame (default near the cameras: "
                   "0.351,-0.084,-0.933); moves shading and highlights")
    p.add_argument("--size", metavar="WxH", default=None, help="image size in pixels (default 2448x2048)")
    p.add_argument("--rig", metavar="CALIBRATION", default=None,
                   help="render through this rig (a calibration.yaml with its image size, as exact) instead of the "
                   "simulator's: its size and distortion are the images'; not with --size or --distortion, and "
                   "--defocus needs --pixel-pitch")
    p.add_argument("--pixel-pitch", metavar="UM", type=float, default=None,
                   help="with --rig: its sensor's pixel pitch in micrometres (the datasheet's, e.g. 3.45), which "
                   "--defocus needs to turn the focal length in pixels into mm")
    p.add_argument("--views", metavar="RX,RY,RZ;...", default=None,
                   help="several views, one pair each in OUT_DIR/view-1/, view-2/, ...: the part turned in its own "
                   "frame by RX,RY,RZ degrees about its bounding-box centre (0,0,120: a turntable's 120 degrees about "
                   "its Z), on top of --pose; e.g. \"0,0,0;0,0,120;0,0,240\"")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    return p


def _check_realism(args):
    """Each realism option's text, parsed once here so a mistake is one line before any work."""
    from partinspect.simulate.defocus import parse_defocus
    from partinspect.simulate.edge_break import parse_edge_break
    from partinspect.simulate.material import parse_material
    from partinspect.simulate.photon import parse_photon

    for flag, value, parse in (("--edge-break", args.edge_break, parse_edge_break),
                               ("--material", args.material, parse_material),
                               ("--defocus", args.defocus, parse_defocus), ("--photon", args.photon, parse_photon)):
        if value is not None:
            try:
                parse(value)
            except ValueError as exc:
                raise InputError(None, f"{flag}: {exc}") from None
    if args.light is not None:
        from partinspect.simulate.folder import shading_with_light

        try:
            shading_with_light(args.light)
        except ValueError as exc:
            raise InputError(None, f"--{exc}") from None
    if args.photon is not None and args.noise is not None:
        raise InputError(None, "--noise and --photon exclude each other: --photon's noise follows the light")


def _parse_drift(text):
    if text is None:
        return None
    kind, _, px = text.partition("=")
    try:
        value = float(px)
        if kind not in ("shift", "roll") or not abs(value) <= 50:
            raise ValueError
    except ValueError:
        raise InputError(None, f"--drift: expected shift=PX or roll=PX with |PX| <= 50, got {text!r}") from None
    return kind, value


def _parse_tilts(text):
    # Numbers only: their range is run_plan's to check, for every caller.
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise InputError(None, f"--tilts: expected degrees from -180 to 180 separated by commas, got {text!r}") from None


def _calibrate_parser():
    p = _Parser(
        prog="inspect calibrate",
        description=(
            "Calibrate the stereo rig from image pairs of a calibration board: writes calibration.yaml "
            "(with the standard uncertainty of every parameter) and calibration.html beside it. "
            "PAIRS_DIR holds left*/right* images with matching names (left01.jpg, right01.jpg) "
            "or left/ and right/ subfolders."
        ),
    )
    p.add_argument("pairs", metavar="PAIRS_DIR")
    p.add_argument("-o", "--output", metavar="FILE", default="calibration.yaml", help="calibration file to write (default: ./calibration.yaml)")
    p.add_argument("--board", metavar="COLSxROWS", help="chessboard inner corners, e.g. 9x6")
    p.add_argument("--square", metavar="MM", type=float, required=True, help="square side in mm (T comes out in mm)")
    p.add_argument("--charuco", metavar="SQUARES_XxY", help="a ChArUco board of this many squares, e.g. 11x8 (instead of --board)")
    p.add_argument("--marker", metavar="MM", type=float, help="ChArUco marker side in mm")
    p.add_argument("--dictionary", metavar="DICT", default="DICT_5X5_100", help="ChArUco dictionary (default DICT_5X5_100)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr, no summary")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    return p


def _plan_parser():
    p = _Parser(
        prog="inspect plan",
        description=(
            "Before measuring: predict, for every toleranced characteristic, the expanded uncertainty U "
            "(k = 2) the rig would achieve with the part in a pose, from the measurement chain's own error "
            "model (edge noise -> fits -> triangulation -> registration); then search the part's rotation and "
            "tilt on the fixture for a pose where every characteristic is decidable (U <= RATIO x tolerance). "
            "Prints a table; writes OUT/plan.html, OUT/plan.json and OUT/best_pose.json. "
            "Exit code 0: every characteristic decidable in the proposed pose; 3: some are not in any pose tried; "
            "2: bad input."
        ),
    )
    p.add_argument("part", metavar="PART.step")
    p.add_argument("--rig", metavar="CALIBRATION", required=True,
                   help="the rig's calibration.yaml (or a folder holding it); must give the image size")
    p.add_argument("--tolerances", metavar="FILE", help="tolerance spec (YAML); default PART.tol.yaml beside the STEP file")
    p.add_argument("--pose", metavar="POSE",
                   help="starting pose: RX,RY,RZ[,TX,TY,TZ] (degrees, mm, as inspect render) or a JSON file with "
                   "part_to_camera (a render's truth.json, a plan's best_pose.json); default the simulator's pose")
    p.add_argument("--ratio", metavar="R", type=float, default=0.25,
                   help="decidable when U <= R x tolerance (default 0.25)")
    p.add_argument("-o", "--output", metavar="OUT", default="plan", help="output folder (default: ./plan)")
    p.add_argument("--noise", metavar="SIGMA", type=float, default=2.0, help="image noise, grey levels (default 2)")
    p.add_argument("--contrast", metavar="GREY", type=float,
                   help="grey-level step at every edge (default: from the shading of the faces)")
    p.add_argument("--blur", metavar="PX", type=float, default=0.6, help="optical blur (Gaussian sigma), px (default 0.6)")
    p.add_argument("--no-search", action="store_true", help="predict the starting pose only")
    p.add_argument("--rotation", metavar="DEG", type=float, default=180.0,
                   help="search rotations about the fixture axis within +-DEG (default 180: a full turn)")
    p.add_argument("--max-tilt", metavar="DEG", type=float, default=30.0,
                   help="search tilts about the fixture's X and Y axes up to DEG (default 30; 0: no tilt)")
    p.add_argument("--step", metavar="DEG", type=float, default=30.0, help="coarse rotation step (default 30)")
    p.add_argument("--check", metavar="N", type=int, default=0,
                   help="render the proposed pose and measure it on N noise draws (at least 3; some seconds each): "
                   "the predicted u set beside the measured spread, a spread beyond chance added to U (default 0: no check)")
    p.add_argument("--seed", metavar="S", type=int, default=0, help="noise seed of the check's draws (default 0)")
    p.add_argument("--views", metavar="N", type=int, default=0,
                   help="instead of one pose, the fewest views (up to N, at most 8) that together decide every "
                   "characteristic: the part turned at --step degrees, upright and upside down; prints the "
                   "inspect render --views text of them")
    p.add_argument("--tilts", metavar="DEG,...", default="0,180",
                   help="with --views: tilts about the fixture's X axis to take views at (default 0,180: upright and "
                   "upside down; 0,90,180,-90 adds the part laid on a side)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr, no table")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    return p


def _batch_parser():
    p = _Parser(
        prog="inspect batch",
        description=(
            "Inspect many parts: one report folder OUT/SERIAL/ each, every characteristic recorded in a results "
            "database (OUT/results.sqlite unless --db), and OUT/spc.html over the batch. MANIFEST is a CSV file "
            "with columns serial,step,images[,spec][,time][,subgroup], a YAML file with the same keys in a list under "
            "'parts:', or a folder of SERIAL/images/ with --step; paths are relative to the manifest. A bad line "
            "is reported (file:line: problem) and the rest run. Exit code: 2 if any part could not be run, else "
            "1 if any fails, else 3 if any is inconclusive, else 0."
        ),
    )
    p.add_argument("manifest", metavar="MANIFEST")
    p.add_argument("-o", "--output", metavar="OUT", default="batch", help="output folder (default: ./batch)")
    p.add_argument("--step", metavar="PART.step", help="the STEP file of every part of a SERIAL/images/ folder layout")
    p.add_argument("--db", metavar="URL", help="results database: a SQLite file or a URL such as "
                   "postgresql://user@host/line (default: OUT/results.sqlite)")
    p.add_argument("--resume", action="store_true", help="continue the last batch into OUT: inspect only the parts "
                   "not recorded as done")
    p.add_argument("--workers", metavar="N", type=int, help="local worker processes (default: one per core)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run the parts on this Dask distributed "
                   "cluster (its workers must see the same paths)")
    p.add_argument("--subgroup-size", metavar="N", type=int, help="SPC page: X-bar/R charts of consecutive parts "
                   "in subgroups of N (2 to 10); 1: individuals charts (default: the manifest's subgroup column "
                   "where it has one)")
    p.add_argument("--refine-rig", action="store_true", help="refine each part's rig from its own circles, as "
                   "inspect --refine-rig does (one image pair per part); the database's rig_refined column says "
                   "whether each part was measured with it")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr, no summary")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    return p


def _spc_parser():
    p = _Parser(
        prog="inspect spc",
        description=(
            "Statistical process control of a results database: per characteristic the run chart with limits and "
            "each part's +-U, Cp, Cpk, Pp, Ppk with confidence intervals (ISO 22514-2), an individuals or X-bar/R "
            "control chart with rule violations (ISO 7870-2) and the measuring system's U against the tolerance. Writes "
            "OUT/spc.html, OUT/spc.csv (one row per characteristic) and OUT/measurements.csv (one row per part "
            "and characteristic); --export writes that table alone as CSV or Parquet."
        ),
    )
    p.add_argument("db", metavar="DB", help="the results database: a SQLite file or a database URL")
    p.add_argument("-o", "--output", metavar="OUT", help="output folder (default: ./spc, none with --export alone)")
    p.add_argument("--export", metavar="FILE", help="one row per characteristic per part (serial, time stamp, "
                   "subgroup, value, u, U, limits, decision) as FILE.csv or FILE.parquet")
    p.add_argument("--subgroup-size", metavar="N", type=int, help="X-bar/R charts of consecutive parts in "
                   "subgroups of N (2 to 10); 1: individuals charts (default: the subgroups the manifest gave, "
                   "else individuals)")
    p.add_argument("-q", "--quiet", action="store_true", help="no summary")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    return p


def _run_batch(args):
    if not args.output:
        raise InputError(None, "-o: the output folder name is empty")
    from partinspect.production.batch import run_batch

    progress = _progress(args.quiet)
    result = run_batch(args.manifest, args.output, db=args.db, step=args.step, resume=args.resume,
                       workers=args.workers, scheduler=args.scheduler, progress=progress,
                       subgroup_size=args.subgroup_size, refine_rig=args.refine_rig,
                       on_problem=lambda line: print(f"inspect batch: {line}", file=sys.stderr, flush=True))
    if not args.quiet:
        try:
            print(result.summary_line(), flush=True)
        except BrokenPipeError:
            _silence_stdout()
    return result.exit_code


def _run_spc(args):
    if args.output == "":
        raise InputError(None, "-o: the output folder name is empty")
    from partinspect.production.spc_report import run_spc

    # The page goes to -o, or ./spc when no --export asks for the table alone.
    out = args.output if args.output is not None or args.export is not None else "spc"
    written = run_spc(args.db, out, subgroup_size=args.subgroup_size, export_to=args.export)
    if not args.quiet:
        print(f"wrote {' and '.join(str(p) for p in written)}", flush=True)
    return EXIT_PASS


def _run_plan(args):
    if not args.output:
        raise InputError(None, "-o: the output folder name is empty")
    from partinspect.atomic import check_output_dir

    check_output_dir(args.output)
    from partinspect.planning.edge_model import DetectorModel
    from partinspect.planning.plan import run_plan
    from partinspect.planning.report import plan_table, write_plan

    model = DetectorModel(noise=args.noise, blur=args.blur, contrast=args.contrast)
    renderer = None
    if args.check:
        # The check's images come from the simulator: the planner itself
        # does not depend on it.
        from partinspect.planning.check import Renderer
        from partinspect.simulate.render import render_radiance_pair, sensor

        renderer = Renderer(render_radiance_pair, sensor)
    result = run_plan(args.part, args.rig, tolerances=args.tolerances, pose=args.pose, max_ratio=args.ratio,
                      model=model, search=not args.no_search, rotation=args.rotation, max_tilt=args.max_tilt,
                      step=args.step, check=args.check, seed=args.seed, renderer=renderer, views=args.views,
                      tilts=_parse_tilts(args.tilts), progress=_progress(args.quiet))
    out = write_plan(args.output, result)
    if not args.quiet:
        _say_pmi_problems(os.path.basename(str(args.part)), result.not_evaluated, "plan.json")
        try:
            print(plan_table(result))
            print(f"\n{result.summary_line()}; report: {out / 'plan.html'}", flush=True)
        except BrokenPipeError:
            _silence_stdout()
    return result.exit_code


def _parse_grid(option, text, minimum):
    try:
        a, b = (int(v) for v in text.lower().split("x"))
        if a < minimum or b < minimum:
            raise ValueError
    except ValueError:
        raise InputError(None, f"{option}: expected COLSxROWS (each at least {minimum}), got {text!r}") from None
    return a, b


def _calibration_board(args):
    if not args.square > 0:
        raise InputError(None, f"--square must be a positive length in mm, got {args.square}")
    if args.charuco:
        cols, rows = _parse_grid("--charuco", args.charuco, 3)
        if args.marker is None or not 0 < args.marker < args.square:
            raise InputError(None, "--charuco needs --marker MM, smaller than --square")
        import cv2

        if not args.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, args.dictionary):
            raise InputError(None, f"--dictionary: unknown ArUco dictionary {args.dictionary!r} (e.g. DICT_5X5_100)")
        from partinspect.vision.stereo_calibration import Board

        return Board("charuco", cols, rows, args.square, args.marker, args.dictionary)
    if not args.board:
        raise InputError(None, "give the board: --board COLSxROWS (chessboard inner corners) or --charuco SQUARES_XxY")
    cols, rows = _parse_grid("--board", args.board, 2)
    from partinspect.vision.stereo_calibration import Board

    return Board("chessboard", cols, rows, args.square)


def _run_calibrate(args):
    from pathlib import Path

    out = Path(args.output)
    if out.is_dir():
        raise InputError(out, "is a folder; -o names the calibration file to write, e.g. calibration.yaml")
    if not out.parent.is_dir():
        raise InputError(out, f"output folder {out.parent} does not exist")
    if not os.access(out.parent, os.W_OK | os.X_OK):
        raise InputError(out, f"output folder {out.parent} is not writable")
    board = _calibration_board(args)

    from partinspect.reports.calibration_report import write_calibration_report
    from partinspect.vision.calibration import write_calibration
    from partinspect.vision.stereo_calibration import calibrate_stereo

    result = calibrate_stereo(args.pairs, board, progress=_progress(args.quiet))
    html = out.with_name(out.stem + ".html")
    write_calibration(out, result.calibration)
    write_calibration_report(html, result, folder=args.pairs, calibration_file=out)
    if not args.quiet:
        for v in result.rejected:
            print(f"rejected pair {v.name}: {v.rejected}")
        print(
            f"calibrated from {len(result.used)} of {len(result.views)} image pairs ({len(result.rejected)} rejected): "
            f"RMS reprojection error {result.rms:.3f} px, mean epipolar error {result.epipolar_error:.3f} px, "
            f"baseline {result.calibration.baseline:.2f} mm"
        )
        print(f"wrote {out} and {html}")
    return EXIT_PASS


def _say_pmi_problems(part_name, not_evaluated, where):
    """The PMI items a run does not check, and the characteristics no tolerance covers, a line each on stderr."""
    from partinspect.tolerances.pmi_text import general_gaps_line, pmi_problems_line

    for line in (pmi_problems_line(part_name, not_evaluated, where), general_gaps_line(part_name, not_evaluated, where)):
        if line:
            print(f"inspect: {line}", file=sys.stderr, flush=True)


def _progress(quiet):
    from partinspect.progress import Progress

    # PARTINSPECT_PROGRESS=1 (or 0) overrides the terminal test: a wrapper
    # reading stderr through a pipe can still follow the stages.
    forced = {"1": True, "0": False}.get(os.environ.get("PARTINSPECT_PROGRESS", ""))
    return Progress(enabled=False if quiet else forced)


def _silence_stdout():
    # The reader of stdout is gone: point fd 1 at /dev/null so the final
    # flush at exit does not print "Exception ignored ... BrokenPipeError".
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


def _run_inspect(args):
    from partinspect.multiview import is_views_folder, run_views
    from partinspect.pipeline import run_inspection
    from partinspect.timings import Timings

    if not args.output:
        raise InputError(None, "-o: the output folder name is empty")
    if args.draws < 10:
        raise InputError(None, f"--draws {args.draws}: a Monte Carlo needs at least 10 draws")
    views = is_views_folder(args.images)
    if views and args.refine_rig:
        from partinspect.production.worker import VIEWS_NOT_REFINED

        raise InputError(args.images, VIEWS_NOT_REFINED)
    more = {} if views else {"refine_rig": args.refine_rig}
    result = (run_views if views else run_inspection)(
        args.part, args.images, args.output, tolerances=args.tolerances, progress=_progress(args.quiet),
        uncertainty=args.uncertainty, draws=args.draws, pose_hint=args.pose_hint, timings=(timings := Timings(_START)),
        **more,
    )
    if args.timings:
        print(timings.table(), file=sys.stderr)
    if not args.quiet:
        _say_pmi_problems(os.path.basename(str(args.part)), result.report.get("tolerances", {}).get("not_evaluated", ()),
                          "report.json")
        try:
            print(result.summary_line(), flush=True)
        except BrokenPipeError:
            # `inspect ... | head -0`: the reports are written and the verdict
            # stands; a closed pipe must not turn a fail into exit code 0.
            _silence_stdout()
    return result.exit_code


def _run_features(args):
    import json

    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.reports.tables import features_table

    inv = inventory(load_step(args.part))
    if args.pmi:
        from partinspect.tolerances.from_pmi import load_pmi_spec
        from partinspect.tolerances.pmi_text import pmi_listing

        pmi, ps = load_pmi_spec(args.part, inv)
        if args.json:
            print(json.dumps({**pmi.to_dict(), "applies_to": ps.applies_to,
                              "not_evaluated": [n.to_dict() for n in ps.not_evaluated]}, indent=2))
        else:
            print(pmi_listing(pmi, ps, args.part))
        return EXIT_PASS
    if args.json:
        print(json.dumps(inv.to_dict(), indent=2))
    else:
        print(features_table(inv))
    return EXIT_PASS


def _run_spec(args):
    from pathlib import Path

    from partinspect.atomic import write_bytes_atomic
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.tolerances.from_pmi import load_pmi_spec
    from partinspect.tolerances.pmi_text import spec_yaml

    part = Path(args.part)
    out = Path(args.output) if args.output else None
    if out is not None and out.exists() and out.resolve() == part.resolve():
        raise InputError(out, "is the STEP file itself; give another -o")
    inv = inventory(load_step(part))
    pmi, ps = load_pmi_spec(part, inv)
    if not pmi and not pmi.unread:
        raise InputError(part, "holds no semantic PMI to write a spec from")
    text = spec_yaml(ps, pmi, part.name)
    if out is None:
        print(text, end="")
    else:
        try:
            write_bytes_atomic(out, text.encode("utf-8"))
        except OSError as e:
            raise InputError(out, f"cannot write: {e.strerror or e}") from None
        print(f"wrote {out}: {len(ps.sources)} limits from {len(ps.applies_to)} PMI items, "
              f"{len(ps.not_evaluated)} not evaluated (listed in its comments)")
    return EXIT_PASS


def _parse_size(text):
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w < 16 or h < 16:
            raise ValueError
    except ValueError:
        raise InputError(None, f"--size: expected WIDTHxHEIGHT in pixels (at least 16x16), got {text!r}") from None
    return w, h


def _render_rig(args):
    """The rig ``--rig`` names, read and checked against the options it excludes; None without it."""
    if args.rig is None:
        if args.pixel_pitch is not None:
            raise InputError(None, "--pixel-pitch is the pixel pitch of --rig's sensor: give it with --rig")
        return None
    given = [name for name, value in (("--size", args.size), ("--distortion", args.distortion)) if value]
    if given:
        raise InputError(args.rig, f"--rig sets the image size and the lenses: not with {', '.join(given)}")
    if args.pixel_pitch is not None and not (math.isfinite(args.pixel_pitch) and 0.0 < args.pixel_pitch <= 100.0):
        raise InputError(None, f"--pixel-pitch: expected the sensor's pixel pitch in micrometres (above 0, at most "
                         f"100), got {args.pixel_pitch:g}")
    if args.defocus and args.pixel_pitch is None:
        raise InputError(args.rig, "--defocus needs the sensor's pixel pitch, which a calibration does not state: "
                         "give it with --pixel-pitch UM")
    from partinspect.vision.calibration import read_calibration

    rig = read_calibration(args.rig)
    if rig.image_size is None:
        raise InputError(args.rig, "the calibration gives no image size (image_width, image_height), which a render needs")
    return rig


def _run_render(args):
    if args.noise is not None and args.noise < 0:
        raise InputError(None, f"--noise must be >= 0 grey levels, got {args.noise}")
    _check_realism(args)
    size = _parse_size(args.size or "2448x2048")
    drift = _parse_drift(args.drift)
    rig = _render_rig(args)
    from partinspect.simulate.folder import render_to_folder, render_views_to_folder

    progress = _progress(args.quiet)
    if args.views is not None:
        from partinspect.poses import parse_views

        render, views = render_views_to_folder, {"views": parse_views(args.views)}
    else:
        render, views = render_to_folder, {}
    render(
        args.part,
        args.out,
        **views,
        pose=args.pose,
        noise=args.noise,
        seed=args.seed,
        deviations=args.deviate,
        distortion=args.distortion,
        image_size=size,
        calib_error=args.calib_error,
        drift=drift,
        edge_break=args.edge_break,
        material=args.material,
        defocus=args.defocus,
        photon=args.photon,
        light=args.light,
        progress=progress,
        rig=rig,
        pixel_pitch=None if args.pixel_pitch is None else args.pixel_pitch * 1e-3,
    )
    if not args.quiet and views:
        print(f"rendered {len(views['views'])} views, each a pair with its truth: "
              f"{os.path.join(args.out, 'view-1')} ... view-{len(views['views'])}")
    elif not args.quiet:
        print(f"rendered {os.path.join(args.out, 'images')} and {os.path.join(args.out, 'truth.json')}")
    return EXIT_PASS


def main(argv=None):
    """Entry point of the `inspect` console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in SUBCOMMANDS:
        command, rest = argv[0], argv[1:]
        parser = {"features": _features_parser, "render": _render_parser, "calibrate": _calibrate_parser,
                  "plan": _plan_parser, "spec": _spec_parser, "batch": _batch_parser, "spc": _spc_parser}[command]()
        run = {"features": _run_features, "render": _run_render, "calibrate": _run_calibrate,
               "plan": _run_plan, "spec": _run_spec, "batch": _run_batch, "spc": _run_spc}[command]
    else:
        parser, rest, run = _main_parser(), argv, _run_inspect
    args = parser.parse_args(rest)
    try:
        return run(args)
    except InputError as exc:
        print(f"inspect: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("inspect: interrupted; earlier outputs are left as they were", file=sys.stderr)
        return 130
    except BrokenPipeError:
        _silence_stdout()
        return EXIT_PASS
    except Exception as exc:  # an internal error: still one line, never a half-written report
        if args.debug or os.environ.get("PARTINSPECT_DEBUG"):
            raise
        print(
            f"inspect: internal error: {type(exc).__name__}: {' '.join(str(exc).split())} "
            "(please report it; --debug shows the traceback)",
            file=sys.stderr,
        )
        return EXIT_ERROR


def console():
    """The ``inspect`` console script: `main`, then the process ends.

    An inspection ends without the interpreter's teardown: unloading
    numba's, SciPy's and OpenCV's modules takes a few tenths of a second
    and frees only memory the system takes back anyway, and by then every
    report is written, closed and renamed into place. Subcommands (a batch
    with its cluster, a render) end the ordinary way.
    """
    code = main()
    if sys.argv[1:2] and sys.argv[1] in SUBCOMMANDS:
        sys.exit(code)
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (BrokenPipeError, ValueError):
        pass
    os._exit(code)

