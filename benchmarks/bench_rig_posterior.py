"""``--refine-rig``'s posterior over repeated calibration draws, and why principal points are held.

Reduced-size renders of the plate (exact rig, noise 2; ``--renders`` of
them, seeds ``--seed`` onwards, taken in turn) are inspected ``--n``
times, each time with the calibration a different simulated board
session states (``simulated_calibration``, seed k: off the true rig by one
draw of its stated covariance), rolled after calibrating by 0.5, 1, 1.5 or
2 px in turn (``bench_drift.stated_calibration``), once without and once
with ``--refine-rig``. Printed:

- per draw: what was refined, each refined parameter's normalised error
  ``(refined - true) / u`` against the true rig (in the refinement's own
  coordinates: rotation vector, ``T`` across its direction, principal
  points), and the characteristics' coverage without and with refinement;
- pooled over the draws: per refined parameter and over all, the RMS of
  the normalised errors (1 when the posterior u is right) and the share
  within +-2u (95.45 % claimed); per characteristic type (and the holes'
  part-frame centres, by their 3x3 covariance) the share within +-U and
  the RMS of error / u, without and with refinement; false accepts;
- the principal points' evidence (``--evidence`` draws): on the pair
  measured as a run measures it, the adjustment of all nine rig
  parameters at once, each principal point's posterior u over its prior
  u (the refinement's gate refines it below ``DETERMINED`` = 0.5), its
  largest posterior correlation with a rotation or ``T`` parameter, and
  the same ratio when the rotation and ``T`` are held at their true
  values (the principal points alone), which tells whether the images
  cannot see a principal point at all or only cannot tell it from a turn.

Usage::

    python3 benchmarks/bench_rig_posterior.py                  # 28 draws, 1224 x 1024
    python3 benchmarks/bench_rig_posterior.py --n 4 --evidence 2
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

# Beside this file: the drift benchmark's stated calibration, inspection and row of figures.
from bench_drift import inspect, row, stated_calibration

ROOT = Path(__file__).resolve().parents[1]
LEVELS = (0.5, 1.0, 1.5, 2.0)
"""Roll after calibrating, px at the image's side edges, taken in turn by the draws."""
NAMES = ("rx", "ry", "rz", "tb1", "tb2", "cx1", "cy1", "cx2", "cy2")


def render(folder, size, seed):
    """The plate rendered with the exact rig (noise 2); its images folder and truth."""
    from partinspect.cli import main

    step = ROOT / "examples" / "plate" / "part.step"
    if not (folder / "truth.json").is_file():
        assert main(["render", str(step), str(folder), "--size", size, "--seed", str(seed), "--noise", "2",
                     "-q"]) == 0
    return step, folder / "images", json.loads((folder / "truth.json").read_text())


def true_coordinates(stated, true):
    """The true rig in the refinement's coordinates about ``stated`` (report units: deg, mm, px), by name."""
    from partinspect.vision.rig_refinement import rig_coordinates

    _, basis = rig_coordinates(stated)
    T = np.ravel(true.T)
    v = np.r_[np.degrees(cv2.Rodrigues(np.asarray(true.R, float))[0].ravel()), basis[0] @ T, basis[1] @ T,
              true.K1[0, 2], true.K1[1, 2], true.K2[0, 2], true.K2[1, 2]]
    return dict(zip(NAMES, v))


def refined_errors(report, stated, true):
    """{name: (refined - true) / u} of the refined parameters; {} when nothing was refined."""
    rr = report.get("rig_refinement", {})
    if not rr.get("refined"):
        return {}
    truth = true_coordinates(stated, true)
    return {p["name"]: (p["refined"] - truth[p["name"]]) / p["standard_uncertainty"] for p in rr["parameters"]}


def held_ratios(report):
    """{name: posterior u / prior u} of the parameters the gate held, from their stated reason."""
    out = {}
    for f in report.get("rig_refinement", {}).get("fixed", []):
        m = re.search(r"standard uncertainty ([0-9.]+) of the", f["reason"])
        if m:
            out[f["name"]] = float(m.group(1))
    return out


def principal_point_evidence(images, stated, true):
    """The principal points' posterior u over the prior's: jointly with the rig, and alone.

    The pair is measured as a run measures it (the drift check, then the
    stereo chain with its rig); every measured circle is taken.

    Returns
    -------
    dict
        ``joint``: ratio per principal point with all nine parameters free;
        ``corr``: its largest |correlation| with a rotation or ``T``
        parameter, and which; ``alone``: the ratio with the rotation and
        ``T`` held at the true rig, known exactly.
    """
    from partinspect.vision.epipolar_drift import check_calibration, matched_arcs
    from partinspect.vision.images import read_pair
    from partinspect.vision.rig_adjustment import circle_observations, rig_coordinates, rig_vector
    from partinspect.vision.rig_refinement import _prior_covariances, _refine_free
    from partinspect.vision.stereo import measure_stereo

    left, right, _ = read_pair(images, stated)
    check = check_calibration(stated, matched_arcs(measure_stereo(left, right, stated)))
    stereo = measure_stereo(left, right, check.calib)
    obs = circle_observations(stereo, [i for i, f in enumerate(stereo.features) if f.kind != "line"], check.calib)
    Z, basis = rig_coordinates(stated)
    C, Cp = _prior_covariances(stated, check.calib, Z, basis, check.verdict == "drifted")
    s0, length = rig_vector(stated, basis), float(np.linalg.norm(stated.T))
    thetas = [np.r_[o.fit.center, 0.0, 0.0, o.fit.radius] for o in obs]
    setting = (obs, check.calib, s0, basis, length, C, Cp, np.linalg.inv(Z))
    prior = np.sqrt(np.diag(Cp)[:9])
    out = {"joint": {}, "corr": {}, "alone": {}}
    _, _, _, _, cov, _, _ = _refine_free(setting, rig_vector(check.calib, basis), thetas, list(range(9)))
    std = np.sqrt(np.diag(cov)[:9])
    corr = cov[:9, :9] / np.outer(std, std)
    for k in range(5, 9):
        out["joint"][NAMES[k]] = std[k] / prior[k]
        j = int(np.argmax(np.abs(corr[k, :5])))
        out["corr"][NAMES[k]] = (abs(corr[k, j]), NAMES[j])
    # The rig's orientation known exactly: the true one, in the stated rig's coordinates, with no error to
    # consider (the principal points start at their stated values).
    s_true = rig_vector(true, basis)
    s_true[5:] = s0[5:]
    known = C.copy(), Cp.copy()
    for M in known:
        M[:5, :] = 0.0
        M[:, :5] = 0.0
    setting = (obs, check.calib, s0, basis, length, *known, np.linalg.inv(Z))
    _, _, _, _, cov, _, _ = _refine_free(setting, s_true, thetas, [5, 6, 7, 8])
    for c, k in enumerate(range(5, 9)):
        out["alone"][NAMES[k]] = np.sqrt(cov[c, c]) / prior[k]
    return out


def summary(values):
    v = np.asarray(values, float)
    return f"RMS {np.sqrt(np.mean(v ** 2)):.2f}, within +-2u {100 * np.mean(np.abs(v) <= 2):.0f} % of {len(v)}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=28, help="calibration draws (seeds 0..n-1)")
    ap.add_argument("--evidence", type=int, default=8, help="draws on which the principal points are examined")
    ap.add_argument("--size", default="1224x1024")
    ap.add_argument("--seed", type=int, default=11, help="the first render's noise seed")
    ap.add_argument("--renders", type=int, default=1, help="renders (noise draws), taken in turn by the draws: "
                    "with one, every draw shares its image noise, and the refined parameters' errors with it")
    ap.add_argument("--dir", help="keep the render and reports here")
    args = ap.parse_args()
    from partinspect.simulate.calibration import simulated_calibration
    from partinspect.vision.calibration import read_calibration

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.dir or tmp)
        true = None
        errors, held = defaultdict(list), defaultdict(list)
        honesty = {False: (defaultdict(list), defaultdict(list)), True: (defaultdict(list), defaultdict(list))}
        false_accepts = {False: 0, True: 0}
        evidence = []
        print(f"{'draw':>4} {'render':>6} {'roll px':>7} {'verdict':>9} {'s':>5}  "
              "refined parameters' (refined - true) / u; characteristics within +-U without -> with")
        for k in range(args.n):
            d = LEVELS[k % len(LEVELS)]
            r_seed = args.seed + k % args.renders
            step, images, truth = render(work / ("render" if r_seed == args.seed else f"render-{r_seed}"), args.size,
                                         r_seed)
            true = read_calibration(images) if true is None else true
            stated = stated_calibration(simulated_calibration(true, np.random.default_rng(k)), "roll", d)
            cells = {}
            t0 = time.perf_counter()
            for refine in (False, True):
                report, message = inspect(step, images, stated, work / f"draw-{k}-{int(refine)}", None, refine)
                if report is None:
                    cells[refine] = message
                    continue
                r = row(report, truth, 0.0)
                cover, z = honesty[refine]
                for t, (a, n) in r["cover"].items():
                    cover[t].append((a, n))
                    z[t].append(r["z_rms"][t] ** 2 * n)
                false_accepts[refine] += r["false_accepts"]
                cells[refine] = (f"{sum(a for a, _ in r['cover'].values())}/{sum(n for _, n in r['cover'].values())}"
                                 f" ({r['false_accepts']} fa)")
                if refine:
                    e = refined_errors(report, stated, true)
                    for name, v in e.items():
                        errors[name].append(v)
                    for name, v in held_ratios(report).items():
                        held[name].append(v)
                    rr = report.get("rig_refinement", {})
                    cells["rig"] = (", ".join(f"{n} {v:+.2f}" for n, v in e.items()) if e
                                    else f"not refined: {rr.get('reason', '?')[:70]}")
                    cells["verdict"] = report.get("calibration_check", {}).get("verdict", "-")
            if k < args.evidence:
                evidence.append(principal_point_evidence(images, stated, true))
            print(f"{k:4d} {r_seed:6d} {d:7.2f} {cells.get('verdict', '-'):>9} {time.perf_counter() - t0:5.1f}  "
                  f"{cells.get('rig', '-')}; {cells.get(False)} -> {cells.get(True)}", flush=True)

    print("\n== refined parameters against the true rig, pooled: (refined - true) / u")
    pooled = [v for vs in errors.values() for v in vs]
    for name in NAMES:
        if errors[name]:
            print(f"{name:>4}: {summary(errors[name])}")
    if pooled:
        print(f" all: {summary(pooled)}")
    print("\n== held by the gate: posterior u / prior u (refined below 0.5)")
    for name in NAMES:
        if held[name]:
            v = np.asarray(held[name])
            print(f"{name:>4}: held in {len(v)} draws, ratio median {np.median(v):.2f} (min {v.min():.2f}, max {v.max():.2f})")
    print("\n== characteristics (and part-frame hole centres) within +-U (z RMS), without -> with --refine-rig")
    for t in sorted(set(honesty[False][0]) | set(honesty[True][0])):
        cells = []
        for refine in (False, True):
            cover, z = honesty[refine]
            a, n = sum(a for a, _ in cover[t]), sum(n for _, n in cover[t])
            cells.append(f"{100 * a / max(n, 1):5.1f} % of {n} ({np.sqrt(sum(z[t]) / max(n, 1)):.2f})")
        print(f"{t:>14}: {cells[0]} -> {cells[1]}")
    print(f"false accepts: {false_accepts[False]} -> {false_accepts[True]}")
    if evidence:
        print(f"\n== principal points over {len(evidence)} draws: posterior u / prior u, all nine free "
              f"[largest |corr| with the rig]; alone (rotation and T known)")
        for name in NAMES[5:]:
            joint = [e["joint"][name] for e in evidence]
            alone = [e["alone"][name] for e in evidence]
            corr = [e["corr"][name] for e in evidence]
            partners = sorted({c[1] for c in corr})
            print(f"{name:>4}: joint {np.median(joint):.2f} ({min(joint):.2f}-{max(joint):.2f}) "
                  f"[|corr| {np.median([c[0] for c in corr]):.3f} with {'/'.join(partners)}]; "
                  f"alone {np.median(alone):.2f} ({min(alone):.2f}-{max(alone):.2f})")


if __name__ == "__main__":
    main()
