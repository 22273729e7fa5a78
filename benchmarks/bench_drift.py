"""A drifted rig: the sample parts inspected with a stated calibration that no longer fits the images.

The bundled pairs (``examples/*/images``, rendered with the exact rig of
their ``calibration.yaml``: one noise draw each), with ``--seeds N`` the
sample parts rendered at the bundled pose and rig with ``N`` noise seeds
(noise 2, 2448 x 2048, ``inspect render --seed`` 101, 102, ...; the rays
cast once and kept in ``--dir``), or a NIST part rendered once the way
``bench_stress.py`` renders it (framed on one of its holes, noise 2,
``NIST_VIEW``, or the part's own view in ``NIST_FRAMING``; ``--size``),
are inspected with that calibration moved as a rig drifts after
calibrating:

- ``shift``: the right camera's principal point moved down by ``d`` px,
  which moves every epipolar line across itself by about ``d`` px (the
  drift the run corrects);
- ``roll``: the right camera turned about its optical axis so that points
  at the image's side edges move by ``d`` px across the epipolar lines
  (a drift that varies over the image: the run corrects it where its
  tangencies determine the slope, and carries it where they only show it).

For every drift level the benchmark prints, beside the exact calibration's
row from the same run: features measured (of the CAD edges) and circles
measured; the true epipolar residual (median over the visible edges of the
true partners' band offset difference under the stated calibration; and
over the edges of the features the run measured, per pixel of their left
image, as the check's edge points count) and the run's estimate with its u,
the spread of its fitted residual field over the part's edges, and its
verdict; the field (at the left principal point and its slope along the
epipolar lines) against the true residual's least-squares line, and the
true line at the median place of the check's own edge points (where the
estimate is read: the two medians above are over other edges, which a
sloping field reads differently); per characteristic type the
share of true values within +-U (the claim: 95.45 %) and the RMS of
(measured - true) / u; and false accepts (a pass whose true value lies
outside the limits). With ``--refine-rig`` every run re-estimates the rig
from the part's circles (``inspect --refine-rig``), and the row adds the
refinement's rotation correction, deg, and its joint chi-square against the
stated calibration.

Those rows are printed per inspection without ``--seeds`` (or with
``--verbose``). After each part and kind, the runs are pooled per drift
level over the pairs, the exact calibration apart from the drawn ones:
runs (stopped), features and circles measured (mean, min), false accepts,
and per characteristic type within +-U and the RMS of err/u; then every
characteristic outside +-U in more than half of the runs that judged it,
with its err/u in each pair's runs. Last, the drawn calibrations' runs
pooled over parts and pairs per kind and level.

Usage::

    python3 benchmarks/bench_drift.py                         # plate and bracket, both kinds, 0-2 px
    python3 benchmarks/bench_drift.py --parts plate --kinds shift --levels 0,0.5,2
    python3 benchmarks/bench_drift.py --seeds 4 --draws 2 --levels 0,1,2 --dir /tmp/drift-seeds
    python3 benchmarks/bench_drift.py --parts plate --kinds roll --levels 1 --draws 1 --refine-rig
    python3 benchmarks/bench_drift.py --parts ftc_09 --kinds roll --levels 0,0.5,1,2 --draws 1
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

# Beside this file: the stress run's rule for a render's true values, and its renders of NIST parts.
from bench_stress import PARTS, render_one, true_value

ROOT = Path(__file__).resolve().parents[1]


def stated_calibration(calib, kind, d):
    """The calibration as stated after the rig drifted by ``d`` px of ``kind`` (its uncertainty kept).

    Moving the stated rig by ``d`` is the rig drifting by ``-d`` from it
    (:func:`partinspect.simulate.calibration.drifted_rig`).
    """
    from partinspect.simulate.calibration import drifted_rig

    moved = drifted_rig(calib, kind, d)
    return replace(moved, std=calib.std, cov=calib.cov)


def true_residual(true_calib, stated, truth, ids=None):
    """Median over the visible edges of right minus left band offset of true partners under ``stated``, px.

    The partners are the edge points where the true rig records them
    (its own distortion), read as the run reads them: mapped to ideal
    pixels with the stated intrinsics and distortion. A drawn calibration
    states a distortion the true rig has not, which moves the ideal pixels
    by up to tenths of a pixel across the image; reading the true ideal
    pixels as the stated calibration's took a residual the run never sees.
    Points outside either image are left out.

    ``ids``: only these features' edges (the ones a run measured: where its
    check states the residual), each sample weighted by the length it
    stands for in the left image (the check's edge points are pixels);
    else every feature visible in both images, per sample (one per 0.25 mm
    of edge, 24-400 per edge).
    """
    r, _, w = true_samples(true_calib, stated, truth, ids)
    if ids is None:
        return float(np.median(r))
    order = np.argsort(r)
    c = np.cumsum(w[order])
    return float(r[order][np.searchsorted(c, 0.5 * c[-1])])


def true_field(true_calib, stated, truth, ids):
    """The true residual fitted as the check fits it, ``a + b s`` (s along the epipolar lines), px and px per px.

    Least squares over ``ids``' edges, each sample weighted by its length in
    the left image (:func:`true_residual`).
    """
    r, s, w = true_samples(true_calib, stated, truth, ids)
    A = np.c_[np.ones(len(s)), s] * np.sqrt(w)[:, None]
    return np.linalg.lstsq(A, r * np.sqrt(w), rcond=None)[0]


def true_samples(true_calib, stated, truth, ids=None):
    """(residual px, place along the lines px, left-image length px) of the true partners on the edges (:func:`true_residual`)."""
    from partinspect.cad.edge_sampling import sample_edge
    from partinspect.vision.calibration import project_points
    from partinspect.vision.epipolar_drift import along_lines
    from partinspect.vision.ideal import to_ideal
    from partinspect.vision.matching import epipolar_geometry

    geo = epipolar_geometry(stated)
    P = np.asarray(truth["part_to_camera"], float)
    size = np.asarray(true_calib.image_size, float)
    out = []
    for f in truth["features"]:
        if not (f["visible_both"] if ids is None else f["id"] in ids):
            continue
        g = {k: (np.asarray(v, float) if isinstance(v, list) else v) for k, v in f["rendered"].items()}
        X = sample_edge(f["kind"], g)[0] @ P[:3, :3].T + P[:3, 3]
        x = project_points(X, true_calib.K1, true_calib.D1, np.eye(3), np.zeros(3))
        y = project_points(X, true_calib.K2, true_calib.D2, np.asarray(true_calib.R, float),
                           np.asarray(true_calib.T, float).ravel())
        ok = np.all((x >= 0) & (x <= size) & (y >= 0) & (y <= size), axis=1)
        if ok.any():
            xi = to_ideal(x[ok], stated.K1, stated.D1)
            step = np.linalg.norm(np.diff(x, axis=0), axis=1)
            w = (0.5 * (np.r_[step[:1], step] + np.r_[step, step[-1:]]))[ok] if len(x) > 1 else np.ones(1)
            out.append((geo.band_right(to_ideal(y[ok], stated.K2, stated.D2)) - geo.band_left(xi),
                        along_lines(geo, xi), w))
    return tuple(np.concatenate(v) for v in zip(*out))


NIST_VIEW = {"elevation": 45.0, "azimuth": 30.0, "roll": 10.0, "offset": [0.0, 0.0, 0.0], "noise": 2.0,
             "distortion": False, "seed": 1, "deviate": 0.0, "pick": 0.0}
"""How a NIST part is rendered (bench_stress's settings for one render)."""
NIST_FRAMING = {"ftc_09": {"elevation": 30.0, "azimuth": 90.0, "pick": 42.5 / 62}}
"""A NIST part's own view where NIST_VIEW shows too little: ftc_09 is a 3 mm
plate whose face is its XZ plane, seen at 45 degrees elevation nearly edge
on (two lines); from 30 degrees over +Y its face turns 30 degrees from the
cameras, framed (bench_stress's ``pick``, a share of its circles) on
circle-43 (x 38, z 57 mm), the hole rows at z 57 and 91 mm around it."""


def part_inputs(part, tmp, size=(2448, 2048)):
    """(STEP file, images folder, truth, tolerances file or None) of a bundled example or a NIST part."""
    if part in ("plate", "bracket"):
        ex = ROOT / "examples" / part
        return ex / "part.step", ex / "images", json.loads((ex / "truth.json").read_text()), None
    step, framing = PARTS[part]
    folder = Path(tmp) / f"render-{part}"
    view = {**NIST_VIEW, **NIST_FRAMING.get(part, {})}
    run = render_one({"index": 0, "part": part, "step": str(step), "framing": framing, **view}, folder, size)
    return step, folder / "images", json.loads((folder / "truth.json").read_text()), run["tolerances"]


def inspect(part, images, stated, work, tolerances=None, refine_rig=False):
    """run_inspection on a copy of the pair with the stated calibration; (report or None, message)."""
    from partinspect.errors import InputError
    from partinspect.pipeline import run_inspection
    from partinspect.vision.calibration import write_calibration

    folder = work / "images"
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for name in ("left.png", "right.png"):
        shutil.copy(images / name, folder / name)
    write_calibration(folder / "calibration.yaml", stated)
    try:
        return run_inspection(part, folder, work / "out", tolerances=tolerances, refine_rig=refine_rig).report, ""
    except InputError as e:
        return None, str(e)


CHI2_3 = 8.0249
"""The 95.45 % point of the chi-square distribution with 3 degrees of freedom."""


def row(report, truth, true_res):
    """One table row's numbers from a report."""
    out = {"true_res": true_res}
    truth_features = {f["id"]: f for f in truth["features"]}
    if report is None:
        return out
    feats = report["features"]
    out["features"] = sum(f["measured"] is not None for f in feats)
    out["circles"] = sum(f["measured"] is not None and f["kind"] != "line" for f in feats)
    cc = report.get("calibration_check", {})
    out.update(est=cc.get("epipolar_residual_px"), u=cc.get("standard_uncertainty_px"), verdict=cc.get("verdict"),
               spread=cc.get("residual_spread_px"),
               field=[cc.get(k) for k in ("residual_at_principal_point_px", "residual_at_principal_point_standard_uncertainty_px",
                                          "residual_slope_px_per_1000px",
                                          "residual_slope_standard_uncertainty_px_per_1000px")])
    rr = report.get("rig_refinement")
    if rr is not None:
        out["rig"] = (f"rig {rr['rotation_correction_deg']:.5f} deg, chi2 {rr['chi_square']:.1f}/{rr['dof']}"
                      if rr["refined"] else f"rig not refined: {rr['reason']}")
    judged = []
    false_accepts = 0
    for c in report["characteristics"]:
        tv = true_value(c, truth)
        if tv is None or c["measured"] is None:
            continue
        judged.append((c["type"], c["id"], abs(c["measured"] - tv) <= c["expanded_uncertainty"],
                       (c["measured"] - tv) / c["standard_uncertainty"]))
        lo, up = c.get("lower_limit"), c.get("upper_limit")
        outside = (lo is not None and tv < lo) or (up is not None and tv > up)
        false_accepts += int(c["decision"] == "pass" and outside)
    for f in feats:
        m, t = f["measured"], truth_features.get(f["id"])
        if m is None or f["kind"] == "line" or t is None or "center" not in m:
            continue
        e = np.asarray(m["center"], float) - np.asarray(t["rendered"]["center"], float)
        d2 = float(e @ np.linalg.solve(np.asarray(m["covariance"], float), e))
        judged.append(("centre", f"{f['id']}.centre", d2 <= CHI2_3, np.sqrt(d2 / 3.0)))
    out["judged"] = judged
    out["false_accepts"] = false_accepts
    return out


def field_text(r):
    """The check's residual field against the true one's (at the principal point, px; slope, px per 1000 px)."""
    if None in r.get("field", [None]):
        return ""
    a, ua, b, ub = r["field"]
    ta, tb = r["true_field"]
    text = f"; field: at pp {a:+.3f} +- {ua:.3f} (true {ta:+.3f}), slope {b:+.3f} +- {ub:.3f} (true {1000 * tb:+.3f})/1000 px"
    if b and r.get("est") is not None:
        # The estimate is the field at the median place of the check's own edge points; the true field there is
        # the like-for-like truth (true_res and true_measured are medians over other edges of a sloping field).
        s = 1000.0 * (r["est"] - a) / b
        text += f"; at the check's edges (s {s:+.0f} px) true {ta + tb * s:+.3f}"
    return text


def by_type(judged):
    """{type: (within +-U, judged, RMS of err/u)} of ``(type, id, inside, z)`` tuples (:func:`row`)."""
    out = {}
    for t in sorted({j[0] for j in judged}):
        v = [j for j in judged if j[0] == t]
        out[t] = (sum(j[2] for j in v), len(v), float(np.sqrt(np.mean([j[3] ** 2 for j in v]))))
    return out


def types_text(judged):
    """``type within/n (z RMS)`` per type, comma separated."""
    return ", ".join(f"{t} {a}/{n} ({z:.2f})" for t, (a, n, z) in by_type(judged).items())


def run_text(d, name, pair, r, dt):
    """One inspection's printed row (``--verbose``)."""
    if "features" not in r:
        return f"{d:8.2f} {name:>11} {pair:>9} {r['true_res']:9.3f}   run stopped: {r['message']}"
    est = "-" if r["est"] is None else f"{r['est']:9.3f}"
    u = "-" if r["u"] is None else f"{r['u']:7.3f}"
    spread = "-" if r["spread"] is None else f"{r['spread']:6.3f}"
    return (f"{d:8.2f} {name:>11} {pair:>9} {r['true_res']:9.3f} {r['true_measured']:8.3f} {est:>9} {u:>7} "
            f"{spread:>6} {r['verdict'] or '-':>12} "
            f"{r['features']:8d} {r['circles']:7d} {r['false_accepts']:9d} {dt:5.1f}  {types_text(r['judged'])}"
            + (f"; {r['rig']}" if "rig" in r else "") + field_text(r))


def pooled_text(rows):
    """Runs pooled: runs (stopped), features and circles measured (mean, min), false accepts, per type."""
    done = [r for r in rows if "features" in r]
    if not done:
        return f"{len(rows):4d} runs, every one stopped"
    f = [r["features"] for r in done]
    c = [r["circles"] for r in done]
    return (f"{len(rows):4d} ({len(rows) - len(done)}) {np.mean(f):6.1f} ({min(f):2d}) {np.mean(c):5.1f} ({min(c):2d}) "
            f"{sum(r['false_accepts'] for r in done):5d}  {types_text([j for r in done for j in r['judged']])}")


def often_outside(runs, share=0.5):
    """Characteristics outside +-U in more than ``share`` of the runs that judged them, with each pair's z.

    ``runs``: (pair, row) tuples. Returns ``[(id, outside, judged, {pair: [z, ...]})]``.
    """
    seen = defaultdict(list)
    for pair, r in runs:
        for _, cid, inside, z in r.get("judged", ()):
            seen[cid].append((pair, inside, z))
    out = []
    for cid, v in sorted(seen.items()):
        bad = sum(not inside for _, inside, _ in v)
        if bad > share * len(v):
            zs = defaultdict(list)
            for pair, _, z in v:
                zs[pair].append(z)
            out.append((cid, bad, len(v), dict(zs)))
    return out


def seed_pairs(part, seeds, work, size=(2448, 2048), noise=2.0):
    """``part``'s pair at its bundled pose and rig, one per noise seed: ([(label, images folder)], truth).

    The rays are cast once (:func:`bench_views.radiance`, cached in
    ``work``); seed ``s``'s pair is what ``inspect render --seed s`` senses
    from them (the left image's noise drawn first), written with the exact
    rig's calibration.yaml.
    """
    import cv2

    from bench_views import radiance
    from partinspect.simulate.render import sensor
    from partinspect.vision.calibration import write_calibration

    left, right, rig, truth = radiance(part, 0, (0.0, 0.0, 0.0), size, work)
    pairs = []
    for s in range(SEED0, SEED0 + seeds):
        folder = work / f"{part}-{size[0]}x{size[1]}-noise{noise:g}-seed{s}"
        if not (folder / "calibration.yaml").is_file():
            folder.mkdir(parents=True, exist_ok=True)
            rng = np.random.default_rng(s)
            for name, img in (("left.png", left), ("right.png", right)):
                cv2.imwrite(str(folder / name), sensor(img, noise, rng))
            write_calibration(folder / "calibration.yaml", rig)
        pairs.append((f"seed {s}", folder))
    return pairs, truth


SEED0 = 101
"""The first noise seed of ``--seeds`` (the bundled pairs are ``inspect render --seed 1``)."""


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="plate,bracket",
                    help="plate, bracket, or a NIST part of bench_stress.py (ctc_01, ctc_03, ftc_09, ftc_11)")
    ap.add_argument("--kinds", default="shift,roll")
    ap.add_argument("--levels", default="0,0.25,0.5,1,2")
    ap.add_argument("--draws", type=int, default=3, help="calibrations drawn as a board session states them")
    ap.add_argument("--seeds", type=int, default=0,
                    help="plate and bracket: render N noise draws at the bundled pose (0: the bundled pair)")
    ap.add_argument("--verbose", action="store_true", help="print every inspection's row (always without --seeds)")
    ap.add_argument("--refine-rig", action="store_true", help="inspect with --refine-rig")
    ap.add_argument("--size", default="2448x2048", help="a NIST part's render size (the sample parts' pairs are bundled)")
    ap.add_argument("--dir", help="keep renders here (reused when there): a NIST part's, or --seeds' pairs")
    args = ap.parse_args()
    from partinspect.simulate.calibration import simulated_calibration
    from partinspect.vision.calibration import read_calibration

    levels = [float(v) for v in args.levels.split(",")]
    verbose = args.verbose or args.seeds == 0
    pooled = defaultdict(list)
    size = tuple(int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        for part in args.parts.split(","):
            step, images, truth, tolerances = part_inputs(part, args.dir or tmp, size)
            pairs = [("bundled", images)]
            if args.seeds and part in ("plate", "bracket"):
                pairs, truth = seed_pairs(part, args.seeds, Path(args.dir or tmp))
            calib = read_calibration(pairs[0][1])
            stated0 = [("exact", calib)] + [
                (f"draw {k}", simulated_calibration(calib, np.random.default_rng(k))) for k in range(args.draws)]
            for kind in args.kinds.split(","):
                print(f"\n== {part}, drift {kind}, {len(pairs)} pair(s)", flush=True)
                if verbose:
                    print(f"{'drift px':>8} {'calibration':>11} {'pair':>9} {'true res':>9} {'measured':>8} {'estimate':>9} "
                          f"{'u':>7} {'spread':>6} {'verdict':>12} "
                          f"{'features':>8} {'circles':>7} {'false acc':>9} {'s':>5}  coverage / z RMS per type")
                runs = defaultdict(list)
                for d in levels:
                    for name, base in stated0:
                        stated = stated_calibration(base, kind, d)
                        for pair, folder in pairs:
                            t0 = time.perf_counter()
                            report, message = inspect(step, folder, stated, Path(tmp) / f"{part}-{kind}-{d}-{name}",
                                                      tolerances, args.refine_rig)
                            r = row(report, truth, true_residual(calib, stated, truth))
                            r["message"] = message
                            if report is not None:
                                ids = {f["id"] for f in report["features"] if f["measured"]}
                                r["true_measured"] = true_residual(calib, stated, truth, ids)
                                r["true_field"] = true_field(calib, stated, truth, ids)
                            if verbose:
                                print(run_text(d, name, pair, r, time.perf_counter() - t0), flush=True)
                            runs[(d, name == "exact")].append((pair, r))
                            if name != "exact":
                                pooled[(kind, d)].append(r)
                print(f"-- pooled over {len(pairs)} pair(s): runs (stopped), features mean (min), circles mean (min), "
                      "false accepts, within +-U (z RMS) per type")
                for (d, exact), v in sorted(runs.items()):
                    print(f"{d:8.2f} {'exact' if exact else 'drawn':>6} " + pooled_text([r for _, r in v]), flush=True)
                for cid, bad, n, zs in often_outside([x for v in runs.values() for x in v]):
                    print(f"   outside +-U in {bad} of {n} runs: {cid}, z per pair: "
                          + "; ".join(f"{p} {' '.join(f'{z:+.1f}' for z in v)}" for p, v in zs.items()))
    print("\n== pooled over parts, pairs and drawn calibrations: within +-U (z RMS)")
    print("kind, drift px: runs (stopped), features mean (min), circles mean (min), false accepts, per type")
    for (kind, d), rows in sorted(pooled.items()):
        print(f"{kind} {d:.2f} " + pooled_text(rows))


if __name__ == "__main__":
    main()
