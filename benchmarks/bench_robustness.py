"""Robustness run: the command line on many generated parts and every NIST file, as a user would run it.

Parts come from :mod:`partinspect.simulate.parts` (plates, stepped lugs,
L-brackets, round flanges and blocks with holes of every kind, slots,
pockets, bosses, steps, chamfers and fillets, drawn from a seed), plus the
issue-46 lug (planned), the issue-46 flange (rendered and inspected) and
the bundled plate (planned). Each command runs as a child process,
``python3 -m partinspect ...``, with the bundled rig
(``examples/plate/images/calibration.yaml``), or with ``--rigs random``
each generated part through its own rig (:func:`part_rig`):

- ``inspect features PART --json`` on every part;
- ``inspect plan PART --rig RIG`` on the first ``--n-plan`` generated parts;
- ``inspect render PART OUT --pose POSE --noise 2`` then ``inspect PART
  OUT/images`` on the first ``--n-inspect``, each at a random pose that
  ``inspect plan`` could reach, with the whole part in both images
  (:func:`partinspect.simulate.parts.random_pose`);
- ``inspect features`` and ``inspect plan`` on every STEP file in the
  NIST folder (``/work/shared/data/step``, else ``tests/data/step``), the
  plan with bench_stress's spec for them (ISO 2768-mK, and +-0.1 mm on the
  radii below 0.5 mm, which ISO 2768 does not cover).

What it prints, as tables that can be quoted:

- internal errors: an exit code other than 0, 1, 2 or 3, or a traceback or
  ``internal error`` on stderr; exit 2 with one clear line is a handled
  outcome and is listed with its line; a command stopped from outside
  (killed, interrupted) is named, not counted, and run again next time;
- non-finite numbers in any JSON output (the features' ``--json``,
  ``plan.json``, ``best_pose.json``, ``truth.json``, ``report.json``), read
  by a strict parser that takes ``NaN``/``Infinity`` as a finding, with
  where they are;
- characteristics with neither a decision nor a reason (``report.json``),
  and planned characteristics neither decidable nor given a reason
  (``plan.json``);
- the slowest stage of each part (from the progress lines every command
  prints with ``PARTINSPECT_PROGRESS=1``);
- for the rendered parts, honesty per characteristic type: the true value
  (from ``truth.json``, as :func:`bench_stress.true_value` gives it) within
  measured +- U (claim 95.45 %), the RMS of error / u (1 when u is right),
  and false accepts (a pass whose true value is outside the limits), and
  the features not measured, by reason.

Usage::

    python3 benchmarks/bench_robustness.py                          # 100 plans, 30 inspections: hours
    python3 benchmarks/bench_robustness.py --n-plan 5 --n-inspect 3 --dir /tmp/robust
    python3 benchmarks/bench_robustness.py --dir /tmp/robust --summary   # tables from what is there
    python3 benchmarks/bench_robustness.py --commands inspect --dir /tmp/robust   # the 30 renders only

``--dir`` keeps every part, output and result (one ``result.json`` per
command run) and reuses them: an interrupted run continues where it
stopped, and ``--summary`` prints the tables from the results already
there without running anything. By default everything goes to a temporary
folder that is removed. Options also read environment variables
(``ROBUST_N_PLAN``, ``ROBUST_N_INSPECT``, ``ROBUST_SEED``, ``ROBUST_DIR``,
``ROBUST_TIMEOUT``); ``--no-nist`` leaves the NIST files out.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# Beside this file: the stress run's coverage claim and tables.
from bench_stress import COVERAGE_CLAIM, honesty_by_type, table

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
RIG = ROOT / "examples" / "plate" / "images" / "calibration.yaml"
PLATE = ROOT / "examples" / "plate" / "part.step"
NIST_DIRS = [Path("/work/shared/data/step"), ROOT / "tests" / "data" / "step"]
NOISE = 2.0
HANDLED = {0, 1, 2, 3}
# Exit statuses of a command stopped from outside (kill, a terminal's
# interrupt): not the command's own fault, and not kept for reuse.
STOPPED = {-9, -15, -2}


# ------------------------------------------------------------------- JSON


class _NonFinite:
    def __init__(self, text):
        self.text = text


def strict_json(text):
    """Parse JSON as the standard defines it; return ``(data, paths)``, paths of every NaN/Infinity found.

    Python's ``json`` accepts ``NaN``, ``Infinity`` and ``-Infinity``,
    which are not JSON; they are read here as markers and their places
    listed (``characteristics[3].measured``).
    """
    data = json.loads(text, parse_constant=_NonFinite)
    found = []

    def walk(x, path):
        if isinstance(x, _NonFinite):
            found.append(f"{path or '.'} = {x.text}")
        elif isinstance(x, dict):
            for k, v in x.items():
                walk(v, f"{path}.{k}" if path else str(k))
        elif isinstance(x, list):
            for i, v in enumerate(x):
                walk(v, f"{path}[{i}]")

    walk(data, "")
    return data, found


# ------------------------------------------------------------------- jobs


_STAGE = re.compile(r"^\[\s*([0-9.]+) s\] (.*)$")


def stages(stderr, total):
    """``[(message, seconds)]`` of a command's progress lines, each lasting until the next (the last until the end)."""
    marks = [(float(m.group(1)), m.group(2)) for m in map(_STAGE.match, stderr.splitlines()) if m]
    out = []
    for k, (t, msg) in enumerate(marks):
        end = marks[k + 1][0] if k + 1 < len(marks) else total
        out.append((msg, max(0.0, end - t)))
    return out


def _key(argv):
    """A command's arguments with the repository's and the results folder's paths left out.

    A result is then reused wherever the repository lies and wherever the
    ``--dir`` folder was moved or copied to (its ``parts/`` and ``runs/``).
    """
    return [re.sub(r"^.*?/(parts|runs)/", r"<dir>/\1/", str(a).replace(str(ROOT), "<repository>")) for a in argv]


def run_command(argv, folder, timeout, stdout_json=None):
    """Run ``python3 -m partinspect ARGV`` once (or reuse ``folder/result.json``); a dict of what happened."""
    folder = Path(folder)
    done = folder / "result.json"
    if done.is_file():
        res = json.loads(done.read_text())
        if _key(res["argv"]) == _key(argv) and res["rc"] not in STOPPED:
            return res
    folder.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PARTINSPECT_PROGRESS": "1", "PYTHONPATH": str(ROOT)}
    env.pop("PARTINSPECT_DEBUG", None)
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-m", "partinspect", *map(str, argv)], capture_output=True, text=True,
                           env=env, timeout=timeout, cwd=folder)
        rc, out, err = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as e:
        rc, out, err = None, e.stdout or "", (e.stderr or "")
        out, err = (out.decode() if isinstance(out, bytes) else out), (err.decode() if isinstance(err, bytes) else err)
    seconds = time.perf_counter() - t0
    lines = [ln for ln in err.splitlines() if not _STAGE.match(ln)]
    stopped = rc in STOPPED
    internal = rc is not None and not stopped and (rc not in HANDLED or "Traceback" in err or "internal error" in err)
    res = {"argv": _key(argv), "rc": rc, "seconds": seconds, "timeout": rc is None, "stopped": stopped,
           "internal": internal, "stderr": "\n".join(lines[-30:]), "stages": stages(err, seconds),
           "nonfinite": [], "bad_json": []}
    if stdout_json is not None and rc == 0:
        (folder / stdout_json).write_text(out)
    if not stopped:
        (folder / "result.json").write_text(json.dumps(res, indent=1))
    return res


def check_json(res, folder, names):
    """Set a result's strict-JSON findings of the named output files in ``folder``."""
    res["nonfinite"], res["bad_json"] = [], []
    for name in names:
        path = Path(folder) / name
        if not path.is_file():
            continue
        try:
            _, found = strict_json(path.read_text())
        except ValueError as e:
            res["bad_json"].append(f"{name}: {e}")
            continue
        res["nonfinite"] += [f"{name}: {f}" for f in found]
    return res


# ------------------------------------------------------------------ parts


def make_parts(base, n, seed):
    """Write the named and the ``n`` generated parts' STEP files (reusing them); ``[(name, kind, path)]``."""
    from partinspect.simulate.parts import flange, lug, random_part, write_part

    out = []
    named = [("issue-lug", lug), ("issue-flange", flange)]
    for name, make in named:
        path = base / "parts" / name / "part.step"
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            write_part(make(), path)
        out.append((name, name.split("-")[1], path))
    for i in range(n):
        s = seed * 100_000 + i
        path = base / "parts" / f"gen-{i:03d}" / "part.step"
        meta = path.parent / "part.json"
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            part = write_part(random_part(s), path)
            meta.write_text(json.dumps({"seed": s, "kind": part.kind,
                                        "features": [f.kind for f in part.features]}))
        out.append((f"gen-{i:03d}", json.loads(meta.read_text())["kind"], path))
    return out


def write_pose(step, folder, seed, rig=RIG):
    """A random reachable pose of the part, in view of ``rig``, as a pose file ``inspect render --pose`` reads."""
    from partinspect.cad.step import load_step
    from partinspect.simulate.parts import random_pose
    from partinspect.vision.calibration import read_calibration

    path = Path(folder) / "pose.json"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        P, fp = random_pose(seed, load_step(step), read_calibration(rig))
        path.write_text(json.dumps({"part_to_camera": P.tolist(), "fixture": fp.label}))
    return path


RIG_STREAM = 4646
"""Second word of a generated part's rig seed (the first is the part's own seed)."""


def part_rig(step, folder, rigs):
    """The rig a part is planned, posed and rendered with: the bundled one, or (``rigs == "random"``, generated
    parts) its own :func:`partinspect.simulate.rig.random_rig`, kept as ``rig.yaml`` in its run folder.

    The rig frames the part's bounding-sphere diameter and is drawn from the part's seed, so a part keeps
    its rig whichever commands run and in which order.
    """
    import numpy as np

    meta = Path(step).parent / "part.json"
    if rigs != "random" or not meta.is_file():
        return RIG
    path = Path(folder) / "rig.yaml"
    if not path.is_file():
        from partinspect.cad.step import load_step
        from partinspect.poses import bounds_of
        from partinspect.simulate.rig import random_rig
        from partinspect.vision.calibration import write_calibration

        b = bounds_of(load_step(step))
        rng = np.random.default_rng([json.loads(meta.read_text())["seed"], RIG_STREAM])
        path.parent.mkdir(parents=True, exist_ok=True)
        write_calibration(path, random_rig(rng, float(np.linalg.norm(b[1] - b[0]))))
    return path


def jobs(parts, n_plan, n_inspect, nist):
    """The commands to run, in order: ``(part name, kind, command, step)``.

    The named parts first; then the generated parts that are rendered, each
    with all its commands, a NIST file's after every fifth of them; then
    the NIST files left; then the generated parts only planned. A run
    stopped early has a mix of all.
    """
    out = [("issue-lug", "lug", "features", None), ("issue-lug", "lug", "plan", None),
           ("issue-flange", "flange", "features", None), ("issue-flange", "flange", "inspect", None),
           ("plate", "plate", "plan", PLATE)]
    gen = [p for p in parts if p[0].startswith("gen-")]
    nist = list(nist)

    def nist_jobs():
        f = nist.pop(0)
        return [(f.stem, "nist", "features", f), (f.stem, "nist", "plan", f)]

    def gen_jobs(i, name, kind):
        return ([(name, kind, "features", None)] + ([(name, kind, "plan", None)] if i < n_plan else [])
                + ([(name, kind, "inspect", None)] if i < n_inspect else []))

    for i, (name, kind, _) in enumerate(gen[:n_inspect]):
        out += gen_jobs(i, name, kind)
        if i % 5 == 4 and nist:
            out += nist_jobs()
    while nist:
        out += nist_jobs()
    for i, (name, kind, _) in enumerate(gen[n_inspect:], start=n_inspect):
        out += gen_jobs(i, name, kind)
    return out


def run_job(base, job, steps, timeout, seed, rigs="bundled"):
    """Run one job's command(s); a list of result dicts, each with its part, kind and command."""
    name, kind, command, step = job
    step = step or steps[name]
    folder = base / "runs" / name
    rig = part_rig(step, folder, rigs)
    results = []
    if command == "features":
        res = run_command(["features", step, "--json"], folder / "features", timeout, stdout_json="features.json")
        results.append(check_json(res, folder / "features", ["features.json"]))
    elif command == "plan":
        spec = nist_spec(step, folder) if kind == "nist" else None
        res = run_command(["plan", step, "--rig", rig, "-o", folder / "plan"] + (["--tolerances", spec] if spec else []),
                          folder / "plan-run", timeout)
        results.append(check_json(res, folder / "plan", ["plan.json", "best_pose.json"]))
        results[-1]["plan_findings"] = plan_findings(folder / "plan" / "plan.json")
    elif command == "inspect":
        pose = write_pose(step, folder, seed, rig)
        render = folder / "render"
        res = run_command(["render", step, render, "--pose", pose, "--noise", NOISE, "--seed", seed]
                          + (["--rig", rig] if rig != RIG else []), folder / "render-run", timeout)
        results.append(check_json(res, render, ["truth.json"]))
        if res["rc"] == 0:
            res = run_command([step, render / "images", "-o", folder / "inspection"], folder / "inspect-run",
                              timeout)
            res = check_json(res, folder / "inspection", ["report.json"])
            res["report"] = report_findings(folder / "inspection" / "report.json", render / "truth.json")
            results.append(res)
    for r, cmd in zip(results, [command] if command != "inspect" else ["render", "inspect"]):
        r.update(part=name, kind=kind, command=cmd)
    return results


def nist_spec(step, folder):
    """A NIST part's spec file, or None: ISO 2768-mK and +-0.1 mm on radii below 0.5 mm (bench_stress's).

    ISO 2768-1 gives no general tolerance below 0.5 mm and ``inspect plan``
    refuses to guess one, as a user of such a part would have to give it.
    """
    from bench_stress import _nist_spec

    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step

    path = Path(folder) / "tolerances.yaml"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        _nist_spec(inventory(load_step(step)), path)
    # Without such radii ISO 2768-mK alone is the spec: no --tolerances.
    return None if "features: {}" in path.read_text() else path


def plan_findings(path):
    """Planned characteristics neither decidable nor given a reason, from plan.json."""
    if not Path(path).is_file():
        return None
    try:
        data, _ = strict_json(Path(path).read_text())
    except ValueError:
        return None
    silent = []
    for pose in ("start", "best"):
        for c in (data.get(pose) or {}).get("characteristics", []):
            if not c.get("decidable") and not (c.get("reason") or "").strip():
                silent.append(f"{pose}: {c.get('id')}")
    return {"silent": silent}


def report_findings(path, truth_path):
    """What report.json says, against the render's truth: characteristics, honesty rows, silent ones."""
    from bench_stress import true_value

    if not Path(path).is_file():
        return None
    try:
        rep, _ = strict_json(Path(path).read_text())
        truth = json.loads(Path(truth_path).read_text())
    except ValueError:
        return None
    rows, silent = [], []
    for c in rep.get("characteristics", []):
        decision, reason = c.get("decision"), (c.get("reason") or "").strip()
        if decision not in ("pass", "fail", "inconclusive") and not reason:
            silent.append(f"{c.get('id')}: no decision and no reason")
        elif decision == "inconclusive" and not reason:
            silent.append(f"{c.get('id')}: inconclusive without a reason")
        tv = true_value(c, truth)
        row = {"id": c["id"], "type": c["type"], "decision": decision, "true": tv,
               "lower": c.get("lower_limit"), "upper": c.get("upper_limit")}
        # A value that depends on which of several poses is right is not claimed for this CAD id: no honesty row.
        ambiguous = bool((c.get("details") or {}).get("ambiguity"))
        if (isinstance(c.get("measured"), (int, float)) and isinstance(c.get("standard_uncertainty"), (int, float))
                and not ambiguous):
            row.update(measured=c["measured"], u=c["standard_uncertainty"], U=c["expanded_uncertainty"])
        rows.append(row)
    unmeasured = {}
    for f in rep.get("features", []):
        if f.get("measured") is None:
            reason = re.sub(r"^(not visible: )?(left|right) image: ", "", f.get("reason") or "no reason")
            key = re.split(r"[:(;]", reason)[0].strip()[:70]
            unmeasured[key] = unmeasured.get(key, 0) + 1
    reg = rep.get("registration") or {}
    return {"verdict": rep.get("verdict"), "characteristics": rows, "silent": silent, "unmeasured": unmeasured,
            "footprint": footprint(truth, Path(truth_path).parent / "images" / "calibration.yaml"),
            "symmetry": bool(reg.get("symmetry")), "ambiguity": len((reg.get("ambiguity") or {}).get("competing", [])),
            "features": len(rep.get("features", [])),
            "measured": sum(f.get("measured") is not None for f in rep.get("features", []))}


def footprint(truth, calibration):
    """mm on the part per pixel of the left image at the part frame's origin, or None without the calibration."""
    from partinspect.vision.calibration import read_calibration

    if not Path(calibration).is_file():
        return None
    return float(truth["part_to_camera"][2][3]) / float(read_calibration(calibration).K1[0, 0])


FOOTPRINTS = ((0.0, 0.06), (0.06, 0.1), (0.1, 1.0))
"""Classes of the part's pixel footprint, mm/px, the honesty is also printed by (the bundled rig: 0.055)."""


# ---------------------------------------------------------------- summary


def _one_line(text, n=150):
    text = " ".join((text or "").split())
    return text if len(text) <= n else text[: n - 3] + "..."


def summarise(results):
    """Print the tables; return the number of findings (internal errors, non-finite numbers, silent characteristics)."""
    by_cmd = {}
    for r in results:
        if r["rc"] in STOPPED:  # results kept before stopped commands were told apart
            r["stopped"], r["internal"] = True, False
        by_cmd.setdefault((r["kind"] == "nist", r["command"]), []).append(r)
    print(f"\n=== partinspect robustness run: {len({r['part'] for r in results})} parts, {len(results)} commands ===\n")
    rows = []
    for (nist, cmd), rs in sorted(by_cmd.items()):
        rcs = {}
        for r in rs:
            key = "timeout" if r["timeout"] else str(r["rc"])
            rcs[key] = rcs.get(key, 0) + 1
        secs = [r["seconds"] for r in rs]
        rows.append(["NIST" if nist else "generated", cmd, len(rs), ", ".join(f"{k}: {v}" for k, v in sorted(rcs.items())),
                     sum(r["internal"] for r in rs), sum(len(r["nonfinite"]) + len(r["bad_json"]) for r in rs),
                     f"{np.median(secs):.1f} / {max(secs):.1f}"])
    table(["parts", "command", "runs", "exit codes", "internal errors", "non-finite", "median / max s"], rows)

    internal = [r for r in results if r["internal"]]
    for r in internal:
        print(f"INTERNAL ERROR {r['part']} ({r['kind']}) {r['command']}: exit {r['rc']}: {_one_line(r['stderr'], 400)}")
    for r in results:
        for f in r["nonfinite"] + r["bad_json"]:
            print(f"NON-FINITE {r['part']} {r['command']}: {f}")
    silent = [(r, s) for r in results for s in ((r.get("report") or {}).get("silent", [])
                                                 + (r.get("plan_findings") or {}).get("silent", []))]
    for r, s in silent:
        print(f"NO DECISION, NO REASON {r['part']} {r['command']}: {s}")
    handled = [r for r in results if r["rc"] == 2 and not r["internal"]]
    if handled:
        print("\nRuns that stopped with one clear line (exit 2):")
        for r in handled:
            print(f"  {r['part']} ({r['kind']}) {r['command']}: {_one_line(r['stderr'])}")
    timeouts = [r for r in results if r["timeout"]]
    for r in timeouts:
        print(f"TIMEOUT {r['part']} {r['command']} after {r['seconds']:.0f} s")
    for r in results:
        if r.get("stopped"):
            print(f"STOPPED FROM OUTSIDE {r['part']} {r['command']} (exit {r['rc']}) after {r['seconds']:.0f} s: "
                  "not counted, run again next time")
    print()

    # The slowest stage of each part.
    parts = {}
    for r in results:
        parts.setdefault(r["part"], []).append(r)
    rows = []
    for name, rs in parts.items():
        st = [(s, r["command"], msg) for r in rs for msg, s in r["stages"]]
        slow = max(st) if st else (0.0, "-", "-")
        rows.append([name, rs[0]["kind"], " ".join(f"{r['command']} {r['seconds']:.0f}" for r in rs),
                     f"{slow[1]}: {_one_line(slow[2], 70)}", f"{slow[0]:.1f}"])
    print("Slowest stage per part (commands' wall time in s; the stage from the progress lines):")
    table(["part", "kind", "commands (s)", "slowest stage", "s"], rows)

    # Honesty on the rendered parts.
    inspected = [r for r in results if r["command"] == "inspect" and r.get("report")]
    if inspected:
        rows = []
        for r in inspected:
            rep = r["report"]
            chars = [c for c in rep["characteristics"] if "measured" in c and c["true"] is not None]
            inside = sum(abs(c["measured"] - c["true"]) <= c["U"] for c in chars)
            dec = {}
            for c in rep["characteristics"]:
                dec[c["decision"]] = dec.get(c["decision"], 0) + 1
            rows.append([r["part"], r["kind"], f"exit {r['rc']}", f"{rep['measured']}/{rep['features']}",
                         ", ".join(f"{k} {v}" for k, v in sorted(dec.items())), f"{inside}/{len(chars)}",
                         "yes" if rep["symmetry"] else "-",
                         f"{rep.get('ambiguity', 0) + 1} poses" if rep.get("ambiguity") else "-",
                         "-" if rep.get("footprint") is None else f"{rep['footprint']:.3f}"])
        print(f"Rendered and inspected parts (noise {NOISE:g}):")
        table(["part", "kind", "exit", "feat. meas.", "decisions", "true in +-U", "symmetric model", "ambiguous",
               "mm/px"], rows)

        print(f"Honesty per characteristic type (claim {100 * COVERAGE_CLAIM:.2f} % inside measured +- U, "
              "RMS of error/u 1):")
        table(*honesty_by_type(c for r in inspected for c in r["report"]["characteristics"]))
        scales = [r["report"].get("footprint") for r in inspected]
        if len({round(f, 3) for f in scales if f is not None}) > 1:
            for lo, hi in FOOTPRINTS:
                within = [r for r, f in zip(inspected, scales) if f is not None and lo <= f < hi]
                if within:
                    print(f"Parts seen at {lo:g}-{hi:g} mm per pixel ({len(within)}):")
                    table(*honesty_by_type(c for r in within for c in r["report"]["characteristics"]))

        false_accept, false_reject = [], []
        for r in inspected:
            for c in r["report"]["characteristics"]:
                if c["true"] is None:
                    continue
                lo = -np.inf if c["lower"] is None else c["lower"]
                hi = np.inf if c["upper"] is None else c["upper"]
                ok = lo <= c["true"] <= hi
                if c["decision"] == "pass" and not ok:
                    false_accept.append((r["part"], c))
                if c["decision"] == "fail" and ok:
                    false_reject.append((r["part"], c))
        unmeasured = {}
        for r in inspected:
            for k, v in r["report"]["unmeasured"].items():
                unmeasured[k] = unmeasured.get(k, 0) + v
        table(["figure", "value"], [
            ["false accepts (pass, true value outside the limits)", len(false_accept)],
            ["false rejects (fail, true value inside the limits)", len(false_reject)]]
            + [[f"features not measured: {k}", v] for k, v in sorted(unmeasured.items(), key=lambda kv: -kv[1])])
        for label, items in (("false accept", false_accept), ("false reject", false_reject)):
            for part, c in items:
                print(f"{label}: {part} {c['id']}: measured {c.get('measured')} +- {c.get('U')}, true {c['true']}")
    n_nonfinite = sum(len(r["nonfinite"]) + len(r["bad_json"]) for r in results)
    print(f"internal errors {len(internal)}, non-finite numbers {n_nonfinite}, "
          f"characteristics with neither decision nor reason {len(silent)}, timeouts {len(timeouts)}")
    return len(internal) + n_nonfinite + len(silent)


def _args():
    import argparse

    env = os.environ.get
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-plan", type=int, default=int(env("ROBUST_N_PLAN", "100")),
                    help="generated parts through inspect plan (default 100)")
    ap.add_argument("--n-inspect", type=int, default=int(env("ROBUST_N_INSPECT", "30")),
                    help="generated parts rendered (noise 2) and inspected (default 30)")
    ap.add_argument("--seed", type=int, default=int(env("ROBUST_SEED", "0")),
                    help="seed of the parts, poses and noise (default 0)")
    ap.add_argument("--dir", default=env("ROBUST_DIR"),
                    help="keep parts, outputs and results here and reuse them (default: a temporary folder)")
    ap.add_argument("--timeout", type=float, default=float(env("ROBUST_TIMEOUT", "1800")),
                    help="seconds one command may take (default 1800)")
    ap.add_argument("--no-nist", action="store_true", help="leave the NIST files out")
    ap.add_argument("--summary", action="store_true", help="only print the tables from the results in --dir")
    ap.add_argument("--rigs", choices=("bundled", "random"), default=env("ROBUST_RIGS", "bundled"),
                    help="the generated parts' rig: the bundled one (default) or each its own random rig "
                         "(partinspect.simulate.rig.random_rig: other sensors, lenses, distances, baselines at any "
                         "angle, distortion)")
    ap.add_argument("--commands", default="features,plan,inspect",
                    help="the commands to run, of features, plan, inspect (default all); the others are passed "
                         "over in their places, so every part keeps the pose and noise seed of the full run")
    return ap.parse_args()


def main():
    args = _args()
    base = Path(args.dir).resolve() if args.dir else Path(tempfile.mkdtemp(prefix="partinspect-robust-"))
    base.mkdir(parents=True, exist_ok=True)
    nist_dir = next((d for d in NIST_DIRS if d.is_dir()), None)
    nist = [] if args.no_nist or nist_dir is None else sorted(nist_dir.glob("*.stp")) + sorted(nist_dir.glob("*.step"))
    try:
        commands = set(args.commands.split(","))
        # Parts past the rendered ones only have features and plan jobs, after every rendered one's.
        n = max(args.n_plan if commands & {"features", "plan"} else 0, args.n_inspect)
        if args.summary:
            found = sorted(base.glob("runs/*/*/result.json"))
            results = []
            for f in found:
                r = json.loads(f.read_text())
                if "part" not in r:
                    continue
                if r["command"] == "inspect":  # read again: the findings as this version states them
                    run = f.parent.parent
                    r["report"] = report_findings(run / "inspection" / "report.json", run / "render" / "truth.json")
                results.append(r)
            return 1 if summarise(results) else 0
        parts = make_parts(base, n, args.seed)
        steps = {name: path for name, _, path in parts}
        steps["plate"] = PLATE
        results = []
        todo = jobs(parts, args.n_plan, args.n_inspect, nist)
        for k, job in enumerate(todo):
            if job[2] not in commands:
                continue
            for r in run_job(base, job, steps, args.timeout, args.seed * 100_000 + k, args.rigs):
                results.append(r)
                flag = " INTERNAL ERROR" if r["internal"] else (" TIMEOUT" if r["timeout"] else "")
                flag += " NON-FINITE" if r["nonfinite"] or r["bad_json"] else ""
                print(f"[{k + 1}/{len(todo)}] {r['part']:28s} {r['command']:8s} exit {r['rc']} "
                      f"{r['seconds']:6.1f} s{flag}", flush=True)
            _save_parts(base, job, results)
        return 1 if summarise(results) else 0
    finally:
        if not args.dir:
            shutil.rmtree(base, ignore_errors=True)


def _save_parts(base, job, results):
    """Write the job's results back to their result.json with part, kind, command and findings (for --summary)."""
    name, _, command, _ = job
    for r in results:
        if r["part"] != name or (r["command"] != command and not (command == "inspect" and r["command"] == "render")):
            continue
        sub = {"features": "features", "plan": "plan-run", "render": "render-run", "inspect": "inspect-run"}[r["command"]]
        path = base / "runs" / name / sub / "result.json"
        if path.parent.is_dir():
            path.write_text(json.dumps(r, indent=1))


if __name__ == "__main__":
    sys.exit(main())
