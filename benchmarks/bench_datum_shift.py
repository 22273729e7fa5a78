"""The datum shift's value and uncertainty against the truth, over noise draws.

The sample plate's three small holes (circle-2, -6, -10) are measured 0.12
mm off their places in x together (``simulate.measured.measure_features``:
the features as the chain would measure them, with their covariances,
aligned on the plate's lines), each with a 0.1 mm position
``datums: [A, B(M), C(M)]``, datum B the 12 mm hole (circle-4) and C the
10 mm hole's rim (circle-8), both with MMB at their nominal size. B and C are
made ``GROW`` mm larger, so each allows ``GROW / 2`` of shift. The true value
of each position is :func:`partinspect.tolerances.datum_shift.best_shift` of
the exact inputs. Over ``--draws`` noise draws the claim checked is the
DESIGN honesty bar: the true value inside measured +- U in about 95 % of
cases and (measured - true) / u with an RMS of 0.8-1.25.

Usage::

    python3 benchmarks/bench_datum_shift.py [--draws 40] [--grow 0.1]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SPEC = """\
datum_features: {A: [line-1], B: [circle-4], C: [circle-8]}
features:
  circle-4: {diameter: {upper: 0.5, lower: 0}}
  circle-8: {diameter: {upper: 0.5, lower: 0}}
  circle-2: {position: {tolerance: 0.1, datums: [A, B(M), C(M)]}}
  circle-6: {position: {tolerance: 0.1, datums: [A, B(M), C(M)]}}
  circle-10: {position: {tolerance: 0.1, datums: [A, B(M), C(M)]}}
"""
PATTERN = ("circle-2", "circle-6", "circle-10")
SHIFT = np.array([0.12, 0.0, 0.0])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=40)
    ap.add_argument("--grow", type=float, default=0.1, help="mm the datum holes are over their MMB size")
    args = ap.parse_args(argv)

    from partinspect.cad.features import inventory
    from partinspect.cad.registration import register
    from partinspect.cad.step import load_step
    from partinspect.poses import default_pose
    from partinspect.simulate.measured import measure_features
    from partinspect.simulate.rig import default_rig
    from partinspect.tolerances.datum_shift import best_shift, plane_basis
    from partinspect.tolerances.evaluate import evaluate
    from partinspect.tolerances.resolve import characteristics_for
    from partinspect.tolerances.spec import parse_spec

    shape = load_step(ROOT / "examples" / "plate" / "part.step")
    inv = inventory(shape)
    T = default_pose(shape, default_rig())
    ids = [f["id"] for f in json.loads((ROOT / "examples" / "plate" / "truth.json").read_text())["features"]
           if f["visible_both"]]
    chars = [c for c in characteristics_for(parse_spec(SPEC), inv) if c.type == "position"]
    E = plane_basis(inv["circle-2"].normal)
    P = np.array([inv[f].center for f in PATTERN]) @ E.T
    D = np.array([inv[f].center for f in ("circle-4", "circle-8")]) @ E.T
    truth = best_shift(P, P + SHIFT[:2], np.zeros(3), np.full(3, 0.1), D, D, np.full(2, args.grow / 2)).values
    rng = np.random.default_rng(11)
    z, inside, seconds = [], [], []
    for draw in range(args.draws):
        m = measure_features(inv, T, ids, rng, n_points=0, shifts={f: SHIFT for f in PATTERN})
        circles = list(m.circles)
        for fid in ("circle-4", "circle-8"):
            i = m.circle_ids.index(fid)
            circles[i] = replace(circles[i], radius=circles[i].radius + args.grow / 2)
        reg = register(circles, m.lines, inv, datums=[x for x in ids if x.startswith("line")], pose_hint=T)
        t0 = time.perf_counter()
        evs = evaluate(chars, reg, inv, seed=draw)
        seconds.append(time.perf_counter() - t0)
        for e, true in zip(evs, truth):
            z.append((e.measured - true) / e.standard_uncertainty)
            inside.append(abs(e.measured - true) <= e.expanded_uncertainty)
    z = np.array(z)
    print(f"grow {args.grow} mm (allowance {args.grow / 2:.3f} mm), {args.draws} draws x 3 holes; "
          f"true values {np.round(truth, 5).tolist()}")
    print(f"  (measured - true) / u: RMS {np.sqrt(np.mean(z ** 2)):.3f}, mean {np.mean(z):+.3f}; "
          f"true value within +- U: {100 * np.mean(inside):.1f} %")
    print(f"  evaluation of the 3 positions (datum shift, {len(seconds)} runs): median {np.median(seconds):.2f} s")


if __name__ == "__main__":
    main()
