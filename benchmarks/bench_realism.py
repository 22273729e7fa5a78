"""Honesty on real parts and cameras: calibration error, broken edges, metal, defocus, photon noise.

Every other benchmark renders with an exact calibration, sharp edges, matte
faces, perfect focus and Gaussian noise. This one renders the sample parts
at their bundled poses (``examples/*/truth.json``, their ``part.tol.yaml``)
and NIST parts (ISO 2768-mK spec of ``bench_stress._nist_spec``): ftc_09
in the view of ``bench_stress.py``'s render 19 (38 features), others in
``bench_drift.NIST_VIEW``'s (ctc_01 framed there on one hole shows one
hole, too little to align; ftc_11 is symmetric about one axis) under the realism options of ``inspect
render``, one at a time and together:

- ``exact``: the plain render (Gaussian noise 2 grey levels, exact calibration);
- ``calib-error``: the same images, ``calibration.yaml`` as a board session
  states it (:func:`partinspect.simulate.folder.stated_calibration`, one
  seed per draw) with its stated uncertainties;
- ``edge-break``: every convex edge of the rendered solid rounded R 0.1 mm
  (the STEP file stays the sharp nominal model; the spec states the break,
  ``edge_break: {min: 0.1, max: 0.1}``, as the drawing would, unless
  ``--unstated-break``);
- ``aluminium``: milled aluminium (microfacet highlights, machining marks);
- ``defocus``: a 25 mm lens at f/16 focused at the rig's fixation point
  (404.5 mm), the f-number scaled with the image width (f/8 at 1224 px
  wide: the pixel is twice as large) so the blur circle is the same in
  pixels at every size: 0 px at the focus, up to 2.5 px (bracket) and
  3.2 px (plate) at their far ends (printed per render, from truth.json's
  ``defocus.coc_px``); ftc_11, 3 mm thick, stays nearly in focus;
- ``photon``: an industrial camera (EMVA 1288 linear model): full well
  10000 e-, gain 0.0255 DN/e- (the full well reads 255 DN, a 200 DN face
  ~7800 e-, about 2.3 DN of noise), read noise 5 e-, cos^4 vignetting;
- ``all``: edge break, aluminium, defocus, photon and calibration error together;
- ``all-oversize`` (plate only): ``all`` with ``circle-4.diameter=0.1``,
  a hole 0.1 mm over nominal against its +0.05/0 tolerance, which must fail.

The noiseless radiance of each (part, radiance) is ray-cast once
(:func:`partinspect.simulate.folder.render_noiseless`) and cached in
``--dir`` as .npz; each draw adds its own noise (Gaussian, or
:func:`partinspect.simulate.photon.photon_sensor`) and, where the condition
has it, its own stated calibration, writes the pair and inspects it with
:func:`partinspect.pipeline.run_inspection`.

Printed per condition: per characteristic type, true value within +-U
(claimed 95.45 %), error RMS (mm or deg), normalised error RMS and largest
|error / u| (``bench_stress.honesty_by_type``); hole centres' normalised
error (chi-square/3 RMS, share inside the 95.45 % ellipsoid); features not
measured, by reason (``bench_stress._reason_counts``); decisions: false
rejects (true value inside the limits, decided fail), false accepts (true
value outside, decided pass), unmeasured characteristics passed (must be
0); and whether the oversize hole fails.

Usage::

    python3 benchmarks/bench_realism.py --size 1224x1024 --draws 3 --dir /tmp/realism
    python3 benchmarks/bench_realism.py --parts plate --conditions exact,calib-error --draws 100 --dir /tmp/realism
    python3 benchmarks/bench_realism.py --parts ftc_09 --conditions exact,all --size 1224x1024
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from bench_drift import CHI2_3, NIST_VIEW
from bench_formation import score
from bench_stress import PARTS, _nist_spec, _pose, _reason_counts, coverage_cell, honesty_by_type, plan, table, true_value

ROOT = Path(__file__).resolve().parents[1]
NOISE = 2.0
"""Grey levels, the Gaussian noise of every condition without the photon sensor (``inspect render``'s default)."""
EDGE_BREAK = "R0.1"
MATERIAL = "aluminium:1"
F_NUMBER = 16.0
"""At 2448 px wide; scaled with the width so the blur in pixels is the same at every size."""
FOCUS = None
"""mm; None: the rig's fixation point (404.5 mm, the middle of the parts' depth)."""
PHOTON = "10000,0.0255,5"
OVERSIZE = "circle-4.diameter=0.1"

CONDITIONS = {
    # name: (radiance key, photon sensor, calibration error, deviations)
    "exact": ("exact", False, False, ()),
    "calib-error": ("exact", False, True, ()),
    "edge-break": ("edge-break", False, False, ()),
    "aluminium": ("aluminium", False, False, ()),
    "defocus": ("defocus", False, False, ()),
    "photon": ("exact", True, False, ()),
    "all": ("all", True, True, ()),
    "all-oversize": ("all", True, True, (OVERSIZE,)),
}
OVERSIZE_PARTS = ("plate",)
STRESS_VIEW = {"ftc_09": 19}
"""NIST parts seen as in this render of ``bench_stress.py``'s default run (20 renders, seed 0): ftc_09 shows
38 features there. Other NIST parts take ``bench_drift.NIST_VIEW``."""


def _options(key, width):
    """render_noiseless's realism options of a radiance key."""
    from partinspect.poses import fixation_point
    from partinspect.simulate.rig import default_rig

    focus = FOCUS or float(fixation_point(default_rig((2448, 2048)))[2])
    lens = f"{F_NUMBER * width / 2448.0:g},{focus:.1f}"
    return {
        "exact": {},
        "edge-break": {"edge_break": EDGE_BREAK},
        "aluminium": {"material": MATERIAL},
        "defocus": {"defocus": lens},
        "all": {"edge_break": EDGE_BREAK, "material": MATERIAL, "defocus": lens},
    }[key]


def part_setup(part, work, size):
    """(STEP file, pose 4x4, tolerances file or None) of a sample part or a NIST part."""
    if part in ("plate", "bracket"):
        ex = ROOT / "examples" / part
        P = np.asarray(json.loads((ex / "truth.json").read_text())["part_to_camera"], float)
        return ex / "part.step", P, None
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.simulate.rig import default_rig

    step, framing = PARTS[part]
    shape = load_step(step)
    inv = inventory(shape)
    view = plan(20, 0)[STRESS_VIEW[part]] if part in STRESS_VIEW else {"framing": framing, **NIST_VIEW}
    P = _pose({"part": part, **view}, shape, inv, default_rig(size))
    return step, P, _nist_spec(inv, work / f"{part}.tol.yaml")


def with_stated_break(step, tolerances, work, part):
    """The part's spec with the rendered edge break stated (``edge_break``), as the drawing would state it."""
    base = Path(tolerances) if tolerances else Path(step).with_name(Path(step).stem + ".tol.yaml")
    text = base.read_text() if base.is_file() else "units: mm\n"
    size = float(EDGE_BREAK.lstrip("RC"))
    out = work / f"{part}-edge-break.tol.yaml"
    out.write_text(text.rstrip("\n") + f"\nedge_break: {{min: {size}, max: {size}}}\n")
    return out


def radiance(part, key, deviations, work, size):
    """(left, right, truth) of one (part, radiance, deviations), ray-cast once and cached in ``work``."""
    from partinspect.simulate.folder import render_noiseless
    from partinspect.simulate.truth import to_json

    tag = f"{part}-{key}{'-oversize' if deviations else ''}-{size[0]}x{size[1]}"
    path, tpath = work / f"{tag}.npz", work / f"{tag}.truth.json"
    if path.is_file() and tpath.is_file():
        z = np.load(path)
        return z["left"], z["right"], json.loads(tpath.read_text())
    step, P, _ = part_setup(part, work, size)
    t0 = time.perf_counter()
    (left, right), _, truth = render_noiseless(step, pose=P, deviations=list(deviations), image_size=size,
                                               **_options(key, size[0]))
    left, right = (np.asarray(i, np.float32) for i in (left, right))
    np.savez_compressed(path, left=left, right=right)
    tpath.write_text(to_json(truth))
    truth = json.loads(tpath.read_text())
    coc = truth.get("defocus", {}).get("coc_px")
    print(f"rendered {tag} in {time.perf_counter() - t0:.0f} s; brightest {np.percentile(left, 99.5):.0f} DN"
          + (f"; blur circle left {coc['left'][0]:.2f}-{coc['left'][1]:.2f} px" if coc else ""), flush=True)
    return left, right, truth


def write_draw(left, right, condition, draw, rig, folder):
    """The pair of one draw (noise, and the stated calibration) written into ``folder``."""
    import cv2

    from partinspect.simulate.folder import stated_calibration
    from partinspect.simulate.photon import parse_photon, photon_sensor
    from partinspect.simulate.render import camera_vignetting, sensor
    from partinspect.vision.calibration import write_calibration

    _, photon, calib_error, _ = CONDITIONS[condition]
    rng = np.random.default_rng(7000 + draw)
    folder.mkdir(parents=True, exist_ok=True)
    sensor_ = parse_photon(PHOTON) if photon else None
    for index, (name, img) in enumerate((("left.png", left), ("right.png", right))):
        if sensor_ is None:
            x = sensor(img, NOISE, rng)
        else:
            x = photon_sensor(img, sensor_, rng, camera_vignetting(rig, index))
        cv2.imwrite(str(folder / name), x)
    write_calibration(folder / "calibration.yaml", stated_calibration(rig, draw) if calib_error else rig)


def decisions(report, truth):
    """False rejects, false accepts, unmeasured passes and the oversize hole's decision of one report."""
    out = {"false_reject": [], "false_accept": [], "unmeasured_pass": [], "oversize": None}
    for c in report["characteristics"]:
        tv = true_value(c, truth)
        if c["measured"] is None and c["decision"] == "pass":
            out["unmeasured_pass"].append(c["id"])
        if c["type"] == "diameter" and c.get("features") == ["circle-4"]:
            out["oversize"] = c["decision"]
        if tv is None:
            continue
        lo = -np.inf if c.get("lower_limit") is None else c["lower_limit"]
        hi = np.inf if c.get("upper_limit") is None else c["upper_limit"]
        conforming = lo <= tv <= hi
        if conforming and c["decision"] == "fail":
            out["false_reject"].append(c["id"])
        if not conforming and c["decision"] == "pass":
            out["false_accept"].append(c["id"])
    return out


def _errors(rows):
    """Per type: RMS and median of |measured - true| (the characteristic's unit, mm or deg)."""
    by = defaultdict(list)
    for r in rows:
        by[r["type"]].append(r["measured"] - r["true"])
    return {t: (float(np.sqrt(np.mean(np.square(e)))), float(np.median(np.abs(e)))) for t, e in by.items()}


def _results():
    return defaultdict(lambda: {"rows": [], "centres": [], "runs": 0, "failed": 0, "reasons": defaultdict(int),
                                "decisions": defaultdict(list)})


def add(results, entry):
    """Add one draw's scores (as ``--json`` writes them) to ``results[(condition, part)]``."""
    r = results[(entry["condition"], entry["part"])]
    r["runs"] += 1
    if "refused" in entry:
        r["failed"] += 1
        return
    r["rows"] += entry["rows"]
    r["centres"] += entry["centres"]
    for k, v in entry["reasons"].items():
        r["reasons"][k] += v
    for k, v in entry["decisions"].items():
        r["decisions"][k] += v if isinstance(v, list) else [v]


def summarise(results, title):
    print(f"\n#### bench_realism: {title}\n")
    for condition in [c for c in CONDITIONS if any(k[0] == c for k in results)]:
        keys = [k for k in results if k[0] == condition]
        rows = sum((results[k]["rows"] for k in keys), [])
        centres = np.asarray(sum((results[k]["centres"] for k in keys), []))
        runs = sum(results[k]["runs"] for k in keys)
        failed = sum(results[k]["failed"] for k in keys)
        print(f"== {condition} ({', '.join(k[1] for k in keys)}; {runs} inspections, {failed} refused)")
        header, trows = honesty_by_type(rows)
        err = _errors(rows)
        header = ["type", "n", "error RMS", "median |error|"] + header[3:]
        trows = [[r[0], r[2], f"{err[r[0]][0]:.4f}", f"{err[r[0]][1]:.4f}"] + r[3:] for r in trows if r[0] in err]
        if len(centres):
            trows.append(["centre (3D)", len(centres), "-", "-", coverage_cell(np.sum(centres <= CHI2_3), len(centres)),
                          f"{np.sqrt(np.mean(centres / 3)):.2f}", "-", f"{np.sqrt(centres.max() / 3):.1f}"])
        table(header, trows)
        reasons = defaultdict(int)
        for k in keys:
            for r, n in results[k]["reasons"].items():
                reasons[r] += n
        if reasons:
            print("not measured (features, all draws): "
                  + "; ".join(f"{r}: {n}" for r, n in sorted(reasons.items(), key=lambda x: -x[1])))
        d = defaultdict(list)
        for k in keys:
            for name, v in results[k]["decisions"].items():
                d[name] += v
        print(f"false rejects {len(d['false_reject'])} {sorted(set(d['false_reject']))}; "
              f"false accepts {len(d['false_accept'])} {sorted(set(d['false_accept']))}; "
              f"unmeasured passed {len(d['unmeasured_pass'])}")
        if condition.endswith("oversize"):
            print(f"oversize hole circle-4 (+0.1 mm, tolerance +0.05/0): decisions {d['oversize']}")
        print()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", default="plate,bracket",
                    help="plate, bracket and NIST parts of bench_stress.py (ctc_01, ctc_03, ftc_09, ftc_11)")
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--unstated-break", action="store_true",
                    help="inspect edge-broken renders with the part's spec as it is (no edge_break stated)")
    ap.add_argument("--first", type=int, default=0, help="first draw's number (noise seed 7000 + n, calibration seed n)")
    ap.add_argument("--size", default="2448x2048", help="WIDTHxHEIGHT, e.g. 1224x1024 for quicker runs")
    ap.add_argument("--dir", default=None, help="keep the radiance, the pairs and the reports here (reused)")
    ap.add_argument("--json", default=None, help="also write every draw's scores to this file")
    ap.add_argument("--tables", default=None, metavar="JSON[,JSON...]",
                    help="print the tables of earlier runs' --json files (draws pooled) and stop")
    args = ap.parse_args()
    if args.tables:
        results, seen = _results(), set()
        for name in args.tables.split(","):
            for entry in json.loads(Path(name).read_text()):
                key = (entry["part"], entry["condition"], entry["draw"])
                if key not in seen:  # a draw is the same in every run that makes it
                    seen.add(key)
                    add(results, entry)
        summarise(results, f"pooled from {args.tables}")
        return
    from partinspect.errors import InputError
    from partinspect.pipeline import run_inspection
    from partinspect.simulate.rig import default_rig

    size = tuple(int(v) for v in args.size.lower().split("x"))
    conditions = args.conditions.split(",")
    unknown = [c for c in conditions if c not in CONDITIONS]
    if unknown:
        ap.error(f"unknown condition(s) {unknown}; known: {', '.join(CONDITIONS)}")
    work = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="realism-"))
    work.mkdir(parents=True, exist_ok=True)
    rig = default_rig(size)
    results = _results()
    log = []
    for part in args.parts.split(","):
        step, _, tolerances = part_setup(part, work, size)
        for condition in conditions:
            key, _, _, deviations = CONDITIONS[condition]
            if deviations and part not in OVERSIZE_PARTS:
                continue
            left, right, truth = radiance(part, key, deviations, work, size)
            for draw in range(args.first, args.first + args.draws):
                folder = work / f"{part}-{condition}-{size[0]}x{size[1]}-{draw}"
                write_draw(left, right, condition, draw, rig, folder / "images")
                t0 = time.perf_counter()
                try:
                    spec = tolerances
                    if "edge_break" in _options(key, size[0]) and not args.unstated_break:
                        spec = with_stated_break(step, tolerances, work, part)
                    report = run_inspection(step, folder / "images", folder / "out", tolerances=spec).report
                except InputError as e:
                    print(f"{part} {condition} draw {draw}: refused: {e}", flush=True)
                    entry = {"part": part, "condition": condition, "draw": draw, "refused": str(e)}
                    add(results, entry)
                    log.append(entry)
                    continue
                rows, centres = score(report, truth)
                dec = decisions(report, truth)
                reasons = _reason_counts(report)
                entry = {"part": part, "condition": condition, "draw": draw, "rows": rows, "centres": centres,
                         "reasons": reasons, "decisions": dec}
                add(results, entry)
                log.append(entry)
                worst = max(rows, key=lambda x: abs(x["measured"] - x["true"]) / x["u"]) if rows else None
                print(f"{part} {condition} draw {draw}: {len(rows)} judged in {time.perf_counter() - t0:.0f} s"
                      + (f", worst {worst['id']} {(worst['measured'] - worst['true']) / worst['u']:+.1f} u"
                         if worst else "")
                      + f", not measured {sum(reasons.values())}, false rejects {len(dec['false_reject'])}"
                      + (f", circle-4 diameter {dec['oversize']}" if deviations else ""), flush=True)
                if not args.dir:
                    shutil.rmtree(folder)
            if args.json:
                Path(args.json).write_text(json.dumps(log, indent=1))
    summarise(results, f"parts {args.parts}; {args.draws} draws; {args.size}")
    if not args.dir:
        shutil.rmtree(work)


if __name__ == "__main__":
    main()
