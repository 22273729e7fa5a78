"""A NIST part inspected against its own PMI, nominal and with one hole out of tolerance.

NIST CTC 03 (AP242, inch PMI on mm geometry) is rendered in the simulator's
default pose twice: as modelled, and with one hole rim's diameter made
larger than its PMI limits allow (``circle-8`` +0.3 mm; its PMI is
diameter 1.5 +-0.005 in, dim-7 of the file). Both renders are inspected
without a spec file, so the PMI gives the limits where it has them and
ISO 2768 the rest.

The claim checked: the nominal render has no fail (pass or inconclusive,
each inconclusive with its reason); the deviated one fails on that
diameter alone, and the failing limit names its PMI item.

Usage::

    python3 benchmarks/bench_pmi.py [--keep DIR] [--delta 0.3]

About 2-3 min per render and 20 s per inspection on this machine.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
PART = ROOT / "tests" / "data" / "step" / "nist_ctc_03_asme1_ap242-e2.stp"
FEATURE = "circle-8"


def run(out, deviations):
    from partinspect.pipeline import run_inspection
    from partinspect.simulate.folder import render_to_folder

    t0 = time.perf_counter()
    render_to_folder(PART, out, noise=1.0, seed=0, deviations=deviations)
    t1 = time.perf_counter()
    result = run_inspection(PART, out / "images", out / "inspection")
    t2 = time.perf_counter()
    report = json.loads((out / "inspection" / "report.json").read_text())
    return result, report, t1 - t0, t2 - t1


def summary(name, report, render_s, inspect_s):
    chars = report["characteristics"]
    decisions = Counter(c["decision"] for c in chars)
    sources = Counter("PMI" if c["source"] == "PMI" else ("spec" if c["source"] == "spec" else "ISO 2768") for c in chars)
    print(f"{name}: verdict {report['verdict']}; {dict(decisions)}; limits from {dict(sources)}; "
          f"{len(report['tolerances'].get('not_evaluated', []))} PMI items not evaluated; "
          f"render {render_s:.0f} s, inspect {inspect_s:.0f} s")
    for c in chars:
        if c["decision"] == "fail" or c["features"] == [FEATURE]:
            print(f"  {c['id']}: {c['decision']}, measured {c['measured']:.4f} +- {c['expanded_uncertainty']:.4f}, "
                  f"limits [{c['lower_limit']}, {c['upper_limit']}], {c['rule']}")
    unexplained = [c["id"] for c in chars if c["decision"] == "inconclusive" and not c.get("reason")]
    return decisions, unexplained


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keep", metavar="DIR", help="keep the renders and reports here")
    ap.add_argument("--delta", type=float, default=0.3, help=f"{FEATURE} diameter change, mm (default 0.3)")
    args = ap.parse_args(argv)
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_pmi_"))
    ok = True
    try:
        _, nominal, r0, i0 = run(base / "nominal", ())
        d0, why0 = summary("nominal", nominal, r0, i0)
        ok &= d0.get("fail", 0) == 0 and not why0
        _, deviated, r1, i1 = run(base / "deviated", [f"{FEATURE}.diameter={args.delta}"])
        d1, why1 = summary(f"{FEATURE} diameter {args.delta:+g} mm", deviated, r1, i1)
        fails = [c for c in deviated["characteristics"] if c["decision"] == "fail"]
        ok &= [c["id"] for c in fails] == [f"{FEATURE}.diameter"] and fails[0]["source"] == "PMI" and not why1
    finally:
        if not args.keep:
            shutil.rmtree(base, ignore_errors=True)
    print("claim holds" if ok else "CLAIM FAILS")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
