"""Several views fused into one inspection: coverage, honesty and the gain in u.

Each sample part (plate, bracket) is rendered in three turntable views (the
example's pose, the part turned 0, 120 and 240 degrees about its Z; one rig)
noise-free once (:func:`partinspect.simulate.folder.render_noiseless`,
cached); each draw adds sensor noise (grey levels ``--noise``, a seed per
draw and view) and is inspected as a views folder
(:func:`partinspect.multiview.measure_views` and ``evaluate_views``: what
``inspect PART.step VIEWS/`` runs, without writing the reports).

Printed, per part:

- features measured per view and fused; "not inspected" per view alone (the
  single-pair run of the first ``--single`` draws) and fused;
- honesty of the fused characteristics per type against truth.json (true
  value within +-U, RMS of error / u), all and those combined from two or
  more views;
- for features measured in two or more views: their stated u fused against
  the best single view's, the ratio the covariances predict for a scalar
  (``1 / sqrt(sum 1 / u_v^2)``), and the RMS errors against the truth (fused
  and single view) over the draws: circle radii and centres;
- the views left out of a feature by the consistency test (at 99 %, about 1
  % per view and feature when every view is right);
- time per draw; with ``--timing N``, the time of all views of draw 0
  measured and fused against the sum of each view's alone, same run.

Run: ``python benchmarks/bench_views.py [--parts plate,bracket] [--draws 8]
[--size 816x683] [--noise 2] [--single 1] [--timing N] [--views "RX,RY,RZ;..."]
[--work DIR]``
(``--views`` as ``inspect render --views``; default the turntable above).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_stress import honesty_by_type, table, true_value  # noqa: E402

TURNS = [(0.0, 0.0, 0.0), (0.0, 0.0, 120.0), (0.0, 0.0, 240.0)]
"""Default views (``--views`` as ``inspect render --views`` takes them)."""


def radiance(part, k, turn, size, work):
    """(left, right, rig, truth) of view ``k`` of a sample part, ray-cast once and cached."""
    from partinspect.cad.step import load_step
    from partinspect.poses import turned_pose
    from partinspect.simulate.folder import render_noiseless
    from partinspect.simulate.rig import default_rig
    from partinspect.simulate.truth import to_json

    tag = work / f"{part}-view{k}-{'_'.join(f'{a:g}' for a in turn)}-{size[0]}x{size[1]}"
    rig = default_rig(size)
    if tag.with_suffix(".npz").is_file():
        z = np.load(tag.with_suffix(".npz"))
        return z["left"], z["right"], rig, json.loads(tag.with_suffix(".json").read_text())
    ex = ROOT / "examples" / part
    P = np.asarray(json.loads((ex / "truth.json").read_text())["part_to_camera"], float)
    pose = turned_pose(P, turn, load_step(ex / "part.step"))
    t0 = time.perf_counter()
    (left, right), rig, truth = render_noiseless(ex / "part.step", pose=pose, image_size=size)
    np.savez_compressed(tag.with_suffix(".npz"), left=np.float32(left), right=np.float32(right))
    tag.with_suffix(".json").write_text(to_json(truth))
    print(f"  rendered {part} view {k} ({','.join(f'{a:g}' for a in turn)}) in {time.perf_counter() - t0:.0f} s",
          flush=True)
    return left, right, rig, json.loads(tag.with_suffix(".json").read_text())


def write_views(part, size, noise, draw, work):
    """A views folder of one noise draw: view-k/{left,right}.png, one shared calibration.yaml; the truths."""
    import cv2

    from partinspect.simulate.render import sensor
    from partinspect.vision.calibration import write_calibration

    folder = work / f"{part}-{'_'.join(','.join(f'{a:g}' for a in t) for t in TURNS)}-draw{draw}"
    truths = []
    for k, turn in enumerate(TURNS, 1):
        left, right, rig, truth = radiance(part, k, turn, size, work)
        rng = np.random.default_rng([draw, k, 4243])
        (folder / f"view-{k}").mkdir(parents=True, exist_ok=True)
        for name, img in (("left.png", left), ("right.png", right)):
            cv2.imwrite(str(folder / f"view-{k}" / name), sensor(img, noise, rng))
        truths.append(truth)
    write_calibration(folder / "calibration.yaml", rig)
    return folder, truths


def inspect_views(step, folder, out, cad):
    from partinspect.multiview import evaluate_views, measure_views

    t0 = time.perf_counter()
    views = measure_views(step, folder, out, load_cad=cad)
    report, _ = evaluate_views(views, lambda m: None)
    return views, report, time.perf_counter() - t0


def feature_errors(views, truth, inv):
    """Per fused feature seen in 2+ views: stated u (fused, each view) and errors against the truth, radius and centre."""
    from partinspect.tolerances.evaluate import pick_feature
    from partinspect.tolerances.fusion import fuse

    regs = [v.measured.registration for v in views if v.measured is not None]
    parts = [r.features_in_part_frame() for r in regs]
    fused = fuse(parts, inv, rank={i: r.weighted_rms for i, r in enumerate(regs)})
    true = {f["id"]: f["rendered"] for f in truth["features"]}
    rows = []
    for fid, f in fused.items():
        if f.kind != "circle" or len(f.views) < 2:
            continue
        t = true[fid]
        single = [pick_feature(parts[v], fid) for v in f.views]
        rows.append({
            "feature": fid,
            "u_r": f.radius_std, "u_r_views": [p.radius_std for p in single],
            "e_r": f.radius - t["radius"], "e_r_views": [p.radius - t["radius"] for p in single],
            "u_c": float(np.sqrt(np.trace(f.covariance))),
            "u_c_views": [float(np.sqrt(np.trace(p.covariance))) for p in single],
            "e_c": float(np.linalg.norm(f.center - np.asarray(t["center"]))),
            "e_c_views": [float(np.linalg.norm(p.center - np.asarray(t["center"]))) for p in single],
        })
    return rows


def single_not_inspected(step, folder, work):
    """Each view alone, inspected as a pair: (features measured, not inspected) per view."""
    from partinspect.pipeline import run_inspection

    out = []
    for k in range(1, len(TURNS) + 1):
        sub = work / f"single-{folder.name}-{k}"
        sub.mkdir(exist_ok=True)
        for name in ("left.png", "right.png"):
            (sub / name).write_bytes((folder / f"view-{k}" / name).read_bytes())
        (sub / "calibration.yaml").write_bytes((folder / "calibration.yaml").read_bytes())
        r = run_inspection(step, sub, work / f"out-single-{folder.name}-{k}").report
        out.append((r["summary"]["features_measured"], r["summary"].get("not_inspected", 0)))
    return out


def timing(step, folder, work, cad, repeats):
    """Time of all views measured and fused against the sum of each view's alone, interleaved, ``repeats`` times."""
    import shutil

    n = len(TURNS)
    subsets = {}
    for name, ks in [*[(f"view-{j}", [j]) for j in range(1, n + 1)], ("all", list(range(1, n + 1)))]:
        sub = work / f"timing-{name}"
        shutil.rmtree(sub, ignore_errors=True)
        sub.mkdir()
        for j in ks:
            shutil.copytree(folder / f"view-{j}", sub / f"view-{j}")
        shutil.copy(folder / "calibration.yaml", sub / "calibration.yaml")
        subsets[name] = sub
    times = {k: [] for k in subsets}
    for _ in range(repeats):
        for k, sub in subsets.items():
            times[k].append(inspect_views(step, sub, work / "out-timing", cad)[2])
    med = {k: float(np.median(t)) for k, t in times.items()}
    alone = sum(med[f"view-{j}"] for j in range(1, n + 1))
    print(f"time (median of {repeats}, interleaved, CAD model loaded before): "
          + ", ".join(f"{k} alone {med[k]:.1f} s" for k in med if k != "all")
          + f"; all {n} fused {med['all']:.1f} s = {med['all'] / alone:.2f} x the sum alone ({alone:.1f} s)")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", default="plate,bracket")
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument("--size", default="816x683")
    ap.add_argument("--noise", type=float, default=2.0)
    ap.add_argument("--single", type=int, default=1, help="draws whose views are also inspected alone")
    ap.add_argument("--work", default="/tmp/bench_views")
    ap.add_argument("--timing", type=int, default=0, metavar="N",
                    help="also time all views of draw 0 against each alone, N times each (interleaved)")
    ap.add_argument("--views", default=None, help="RX,RY,RZ;... (default turntable 0,0,0;0,0,120;0,0,240)")
    args = ap.parse_args()
    if args.views:
        from partinspect.poses import parse_views

        TURNS[:] = [tuple(v) for v in parse_views(args.views)]
    size = tuple(int(v) for v in args.size.split("x"))
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    from partinspect.pipeline import load_cad_model

    print(f"=== bench_views: {len(TURNS)} views {'; '.join(','.join(f'{a:g}' for a in t) for t in TURNS)} deg, {size[0]}x{size[1]}, "
          f"noise {args.noise:g} grey levels, {args.draws} draws ===", flush=True)
    for part in args.parts.split(","):
        step = ROOT / "examples" / part / "part.step"
        model = {}

        def cad(path):
            if not model:
                model["m"] = load_cad_model(path)
            return model["m"]

        chars, feats, per_view, fused_n, not_insp, left_out, tested, times, singles = [], [], [], [], [], 0, 0, [], []
        whole = []
        for draw in range(args.draws):
            folder, truths = write_views(part, size, args.noise, draw, work)
            views, report, dt = inspect_views(step, folder, work / f"out-{part}-{draw}", cad)
            times.append(dt)
            per_view.append([v.get("features_measured", 0) for v in report["views"]])
            fused_n.append(report["summary"]["features_measured"])
            not_insp.append(report["summary"].get("not_inspected", 0))
            left_out += len(report["fusion"]["left_out"])
            whole += [(draw, v["name"], v["reason"]) for v in report["views"] if not v["used"]]
            tested += sum(len(f["measured"]["views"]) + len(f["measured"].get("left_out", []))
                          for f in report["features"] if f["measured"] is not None and
                          len(f["measured"]["views"]) + len(f["measured"].get("left_out", [])) > 1)
            for c in report["characteristics"]:
                tv = true_value(c, truths[0])
                row = {"type": c["type"], "true": tv, "views": len(c["views"])}
                if c["measured"] is not None:
                    row.update(measured=c["measured"], u=c["standard_uncertainty"], U=c["expanded_uncertainty"])
                chars.append(row)
            feats += feature_errors(views, truths[0], views[0].inputs.inv)
            if draw < args.single:
                singles.append(single_not_inspected(step, folder, work))
            print(f"  {part} draw {draw}: views {per_view[-1]} features, fused {fused_n[-1]}; not inspected "
                  f"{not_insp[-1]}; left out {len(report['fusion']['left_out'])}; {dt:.1f} s", flush=True)

        print(f"\n--- {part} ---")
        nf = len(report["features"])
        table(["", *[f"view-{k}" for k in range(1, len(TURNS) + 1)], "fused"],
              [["features measured (mean of draws, of " + str(nf) + ")",
                *[f"{np.mean([p[i] for p in per_view]):.1f}" for i in range(len(TURNS))], f"{np.mean(fused_n):.1f}"],
               ["not inspected (single runs / fused mean)",
                *[f"{np.mean([s[i][1] for s in singles]):.1f}" if singles else "-" for i in range(len(TURNS))],
                f"{np.mean(not_insp):.1f}"]])
        print("honesty of the fused characteristics, all:")
        table(*honesty_by_type(chars))
        print("honesty, characteristics combined from 2 or more views:")
        table(*honesty_by_type([c for c in chars if c["views"] >= 2]))
        if feats:
            def rms(x):
                return float(np.sqrt(np.mean(np.square(x))))

            u_r_best = [min(f["u_r_views"]) for f in feats]
            pred_r = [1 / np.sqrt(sum(1 / u**2 for u in f["u_r_views"])) for f in feats]
            u_c_best = [min(f["u_c_views"]) for f in feats]
            pred_c = [1 / np.sqrt(sum(1 / u**2 for u in f["u_c_views"])) for f in feats]
            e_best_r = [f["e_r_views"][int(np.argmin(f["u_r_views"]))] for f in feats]
            e_best_c = [f["e_c_views"][int(np.argmin(f["u_c_views"]))] for f in feats]
            print(f"circles measured in 2+ views: {len(feats)} (feature x draw)")
            table(["", "radius", "centre (sqrt trace)"], [
                ["median stated u fused / best view's", f"{np.median(np.divide([f['u_r'] for f in feats], u_r_best)):.3f}",
                 f"{np.median(np.divide([f['u_c'] for f in feats], u_c_best)):.3f}"],
                ["median predicted 1/sqrt(sum 1/u_v^2) / best view's", f"{np.median(np.divide(pred_r, u_r_best)):.3f}",
                 f"{np.median(np.divide(pred_c, u_c_best)):.3f}"],
                ["RMS error fused, um", f"{1000 * rms([f['e_r'] for f in feats]):.2f}",
                 f"{1000 * rms([f['e_c'] for f in feats]):.2f}"],
                ["RMS error best view alone, um", f"{1000 * rms(e_best_r):.2f}", f"{1000 * rms(e_best_c):.2f}"],
                ["RMS stated u fused / best view, um",
                 f"{1000 * rms([f['u_r'] for f in feats]):.2f} / {1000 * rms(u_r_best):.2f}",
                 f"{1000 * rms([f['u_c'] for f in feats]):.2f} / {1000 * rms(u_c_best):.2f}"],
                ["RMS of error / u, fused (per feature and draw)", f"{rms([f['e_r'] / f['u_r'] for f in feats]):.2f}",
                 f"{rms([f['e_c'] / f['u_c'] for f in feats]):.2f}"],
                ["RMS of error / u, best view alone",
                 f"{rms([f['e_r_views'][i] / f['u_r_views'][i] for f in feats for i in [int(np.argmin(f['u_r_views']))]]):.2f}",
                 f"{rms([f['e_c_views'][i] / f['u_c_views'][i] for f in feats for i in [int(np.argmin(f['u_c_views']))]]):.2f}"],
            ])
        print(f"views left out by the consistency test: {left_out} of {tested} view-features tested "
              f"({100 * left_out / max(tested, 1):.1f} %)")
        print(f"whole views left out: {len(whole)} of {len(TURNS) * args.draws}"
              + "".join(f"\n  draw {d} {n}: {why}" for d, n, why in whole))
        print(f"time per draw ({len(TURNS)} views, measured and fused): median {np.median(times):.1f} s", flush=True)
        if args.timing:
            timing(step, work / f"{part}-{'_'.join(','.join(f'{a:g}' for a in t) for t in TURNS)}-draw0", work, cad,
                   args.timing)
        print()


if __name__ == "__main__":
    main()
