"""Predicted uncertainties (`inspect plan`) against the real chain on rendered noise draws.

For each sample part in its default pose: every characteristic's standard
uncertainty u is predicted (:func:`partinspect.planning.predict.predict_pose`,
nothing rendered), then the part's noiseless radiance is ray-cast once and
``--draws`` noise draws run through the whole chain (measure_stereo ->
register -> evaluate, :func:`partinspect.planning.check.monte_carlo_check`).
Per characteristic the table shows

- ``pred u``: the predicted u from image noise alone (``DetectorModel(
  systematic=False)``: the points weighted as the chain weights them, the
  Type B part left out): the part that varies from one noise draw to the next;
  for a form value the spread over images of one scene with the Type B
  displacements held fixed (a fixed pattern changes which points set the
  zone, which widens that spread beyond the noise alone's);
- ``MC u``: the measured spread over the draws (standard deviation of the
  values; for position the RMS of 2 |d - mean d|, see check.py), and
  ``pred/MC`` (a ratio of spreads from n draws lies within the printed
  interval by chance alone);
- ``pred/MAD``: against the spread of the bulk of the draws (1.4826 x the
  median absolute deviation), which outlier draws (a segmentation that
  lost part of an edge, a corner point kept) do not inflate;
- ``95 % CI``: a bootstrap interval of ``pred/MC`` from the draws' own
  values (2000 resamples): the chi-square interval printed above the table
  holds for normal values, and a value whose draws have heavier tails (a
  form zone's noise-bias-corrected value, excess kurtosis up to 1.6 over
  200 draws of the sample parts; a distance 2.7) has a less certain
  spread. Neither interval counts the prediction's own Monte Carlo noise
  (a form value's u from 200 scenes of 5 images, 1.5-3.5 %);
- ``own 95 %``: the range of ``pred/MC`` the prediction itself allows
  for that many draws of one scene: for a straightness or circularity the
  central 95 % of the spreads its error model gives over 400 scenes
  (:func:`partinspect.tolerances.evaluate.form_scene_spreads`: the
  scene's fixed Type B displacements change which points set the zone,
  so a scene's spread may lie 20-40 % from the RMS over scenes that ``pred
  u`` is), for the others the chi-square interval with the values'
  sample kurtosis (:func:`~partinspect.planning.check.chance_interval`);
- ``u total``: the predicted u with the chain's Type B term for rim points
  beside shaded surfaces, which ``inspect plan`` reports; ``chain u``: the
  mean u the chain reported; ``RMS err``: the RMS error of the measured
  values about the true (nominal) value, which includes the render's
  systematic errors that the Type B term is there to cover, and ``tot/RMS``;
- the chain's honesty draw by draw: ``z RMS``, the RMS of the normalised
  errors ``(value - true) / u`` with the u the chain reported in that draw
  (1 for an honest u), and ``in +-U``, the share of draws whose true value
  lies within the chain's ``U = 2 u`` (95 % claimed). Comparing a mean u
  with an RMS error instead misleads where a draw that lost part of an
  edge is far off *and says so* with a larger u.

The acceptance of issue 9 is ``|pred/MC - 1| <= 0.2`` for every
characteristic of both parts. Where the chain's segmentation keeps a
different share of an edge from draw to draw, the spread is a mixture the
first-order prediction does not describe (``pred/MAD`` then tells).

Then the bad-pose demonstration (``--bad-pose``): the plate rendered from
a pose where its front edge runs along the epipolar lines and from one
where its holes are nearly edge-on; the chain's result on those images for
the characteristics the plan names, and the same after re-rendering in the
pose the plan proposes.

    python3 benchmarks/bench_plan.py [--draws 50] [--size 1224 1024] [--parts plate bracket]
                                     [--bad-pose] [--json FILE]
"""

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from partinspect.planning.check import chance_interval, monte_carlo_check, spread_interval
from partinspect.simulate.render import render_radiance_pair, sensor
from partinspect.planning.edge_model import DetectorModel  # noqa: E402
from partinspect.planning.predict import predict_pose  # noqa: E402
from partinspect.simulate.rig import default_rig  # noqa: E402
from tests.simulate.scenes import Part  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def characteristics(part):
    from partinspect.tolerances.resolve import characteristics_for, resolve_spec
    from partinspect.tolerances.spec import load_spec

    path = REPO / "examples" / part.name / "part.tol.yaml"
    spec = load_spec(path)
    chars = characteristics_for(spec, part.inv, path)
    datums = None if spec.datums is None else list(resolve_spec(spec, part.inv, path).datums)
    return chars, datums


def bootstrap_interval(chk, cid, pred, n_boot=2000, level=0.95, seed=0):
    """Percentile bootstrap interval of ``pred / spread`` over the draws' values (None with < 3)."""
    rng = np.random.default_rng(seed)
    if chk.types[cid] == "position":
        d = chk.offsets[cid]
        d = d[np.isfinite(d).all(axis=1)]
        if len(d) < 3:
            return None
        idx = rng.integers(0, len(d), (n_boot, len(d)))
        x = d[idx] - d[idx].mean(axis=1, keepdims=True)
        s = 2.0 * np.sqrt((x * x).sum(axis=2).sum(axis=1) / (len(d) - 1))
    else:
        v = chk.values[cid]
        v = v[np.isfinite(v)]
        if len(v) < 3:
            return None
        s = v[rng.integers(0, len(v), (n_boot, len(v)))].std(axis=1, ddof=1)
    r = pred / s[s > 0]
    return [float(q) for q in np.quantile(r, [(1 - level) / 2, (1 + level) / 2])]


def robust_spread(chk, cid):
    """1.4826 x the median absolute deviation: the spread of the bulk of the draws, outlier draws aside."""
    def mad(x):
        x = x[np.isfinite(x)]
        return 1.4826 * float(np.median(np.abs(x - np.median(x)))) if len(x) >= 3 else float("nan")

    if chk.types[cid] == "position":
        d = chk.offsets[cid]
        return 2.0 * float(np.sqrt(sum(mad(d[:, k]) ** 2 for k in range(3))))
    return mad(chk.values[cid])


def compare(name, size, draws, seed):
    part = Part(name)
    rig = default_rig(size)
    pose = part.pose(rig)
    chars, datums = characteristics(part)
    t = time.perf_counter()
    pred = predict_pose(part.inv, part.scene, rig, pose, chars, datums=datums)
    t_pred = time.perf_counter() - t
    # The image-noise part alone: what the spread over noise draws of one scene can show.
    rand = predict_pose(part.inv, part.scene, rig, pose, chars, datums=datums, model=DetectorModel(systematic=False))
    t = time.perf_counter()
    radiance = render_radiance_pair(part.scene, rig, pose)
    chk = monte_carlo_check(part.scene, part.inv, rig, pose, chars, radiance, sensor, draws=draws, seed=seed,
                            datums=datums)
    t_mc = time.perf_counter() - t
    rows = []
    parts = rand.registration.features_in_part_frame() if rand.registration is not None else None
    for cp, cr in zip(pred.characteristics, rand.characteristics):
        cid = cp.id
        mc = chk.spread(cid)
        rms = chk.rms_error(cid, cp.characteristic.nominal)
        frac = chk.measured_fraction(cid)
        rep = chk.reported_u[cid]
        rep = float(np.nanmean(rep)) if np.isfinite(rep).any() else float("nan")
        n = int(np.isfinite(chk.values[cid]).sum())
        robust = robust_spread(chk, cid)
        ci = bootstrap_interval(chk, cid, cr.u) if math.isfinite(cr.u) else None
        # The range of spread / pred the prediction itself allows for n draws of one scene.
        own = None
        if math.isfinite(cr.u) and cr.u > 0 and n >= 3:
            lo, hi = spread_interval(chk, cr, rand.registration, n, seed=seed, parts=parts)
            own = [1.0 / hi, 1.0 / lo]
        true = 0.0 if cp.characteristic.type == "position" else cp.characteristic.nominal
        z = (chk.values[cid] - true) / chk.reported_u[cid]
        z = z[np.isfinite(z)]
        rows.append({
            "id": cid, "type": cp.characteristic.type, "source": cp.characteristic.source,
            "pred": cr.u if math.isfinite(cr.u) else None, "pred_total": cp.u if math.isfinite(cp.u) else None,
            "chain": rep if math.isfinite(rep) else None, "rms_error": rms if math.isfinite(rms) else None,
            "mc": mc if math.isfinite(mc) else None, "mc_robust": robust if math.isfinite(robust) else None,
            "ratio_ci": ci, "own_range": own,
            "measured_draws": n, "measured_fraction": frac,
            "z_rms": float(np.sqrt(np.mean(z * z))) if len(z) >= 3 else None,
            "covered": float(np.mean(np.abs(z) <= 2.0)) if len(z) >= 3 else None,
            "pred_status": "measured" if math.isfinite(cp.u) else cp.reason,
            "warning": cp.warning,
            "values": [None if not math.isfinite(v) else float(v) for v in chk.values[cid]],
        })
    return {"part": name, "size": list(size), "draws": chk.draws, "failed": chk.failed,
            "predict_seconds": t_pred, "monte_carlo_seconds": t_mc, "rows": rows}


def print_table(res):
    print(f"\n== {res['part']}: {res['size'][0]}x{res['size'][1]} px, {res['draws']} draws "
          f"(prediction {res['predict_seconds']:.1f} s, chain {res['monte_carlo_seconds']:.0f} s)")
    if res["failed"]:
        print("failed draws:", "; ".join(res["failed"]))
    lo, hi = chance_interval(res["draws"])
    print(f"a ratio of spreads from {res['draws']} draws lies in [{lo:.2f}, {hi:.2f}] by chance alone (95 %)")
    head = (f"{'characteristic':34s} {'type':12s} {'pred u':>9s} {'MC u':>9s} {'pred/MC':>8s} {'95 % CI':>11s} {'own 95 %':>11s} {'pred/MAD':>8s} "
            f"{'u total':>9s} {'chain u':>9s} {'RMS err':>9s} {'tot/RMS':>8s} {'z RMS':>6s} {'in +-U':>6s}  note")
    print(head)
    print("-" * len(head))
    ok = bad = reach = held = compared = 0
    for r in res["rows"]:
        def f(x):
            return f"{x:9.5f}" if x is not None else f"{'-':>9s}"

        note = ""
        rm = "-"
        if r["pred"] is None and r["mc"] is None:
            note = "not measured by either"
            rp = "-"
        elif r["pred"] is None or r["mc"] is None:
            note = "pred: not measurable" if r["pred"] is None else f"chain measured it in {r['measured_draws']} draws only"
            rp = "-"
        else:
            ratio = r["pred"] / r["mc"]
            rp = f"{ratio:8.2f}"
            rm = f"{r['pred'] / r['mc_robust']:8.2f}" if r["mc_robust"] else "-"
            within = abs(ratio - 1) <= 0.2
            own = r.get("own_range")
            if own:
                compared += 1
                held += own[0] <= ratio <= own[1]
            ok += within
            bad += not within
            if not within:
                note = "OUTSIDE 20 %"
                ci_ = r.get("ratio_ci")
                if ci_ and ci_[0] <= 1.2 and ci_[1] >= 0.8:
                    reach += 1
                    note += " (its 95 % CI reaches within)"
            if r["measured_fraction"] < 1:
                note += f" measured in {r['measured_draws']} of {res['draws']} draws"
        if r.get("warning"):
            note += " [plan warns: flat ellipse]"
        rt = f"{r['pred_total'] / r['rms_error']:8.2f}" if r["pred_total"] and r["rms_error"] else "-"
        zr = f"{r['z_rms']:6.2f}" if r.get("z_rms") is not None else "-"
        cv = f"{100 * r['covered']:5.0f}%" if r.get("covered") is not None else "-"
        ci = f"{r['ratio_ci'][0]:.2f}-{r['ratio_ci'][1]:.2f}" if r.get("ratio_ci") and r["mc"] else "-"
        ow = f"{r['own_range'][0]:.2f}-{r['own_range'][1]:.2f}" if r.get("own_range") and r["mc"] else "-"
        print(f"{r['id']:34s} {r['type']:12s} {f(r['pred'])} {f(r['mc'])} {rp:>8s} {ci:>11s} {ow:>11s} {rm:>8s} "
              f"{f(r['pred_total'])} {f(r['chain'])} {f(r['rms_error'])} {rt:>8s} {zr:>6s} {cv:>6s}  {note}")
    print(f"within 20 %: {ok} of {ok + bad} characteristics measured by both"
          + (f"; of the {bad} outside, {reach} with a 95 % bootstrap interval reaching within 20 %" if bad else ""))
    print(f"within the prediction's own 95 % range for a spread of that many draws: {held} of {compared}")
    res["own"] = [held, compared]
    return ok, bad


def bad_pose_demo(size, seed):
    """Bad poses rendered and measured; the plan's proposal rendered and measured."""
    from partinspect.planning.check import measure_pair
    from partinspect.planning.search import search_poses
    from partinspect.simulate.render import sensor
    from partinspect.tolerances.resolve import resolve_spec
    from partinspect.tolerances.spec import load_spec
    from tests.planning.conftest import view_pose

    part = Part("plate")
    rig = default_rig(size)
    path = REPO / "examples" / "plate" / "part.tol.yaml"
    chars = list(resolve_spec(load_spec(path), part.inv, path).characteristics)
    b = np.asarray(part.mesh.bounds, float)
    center = 0.5 * (b[0] + b[1])
    out = []
    for label, view, limits in (
        ("front edge along the epipolar lines (45, 270, 0)", (45.0, 270.0, 0.0), dict(rotation=90.0, step=30.0, max_tilt=0.0)),
        ("holes nearly edge-on (10, 250, 20)", (10.0, 250.0, 20.0), dict(rotation=0.0, max_tilt=30.0)),
    ):
        start = view_pose(part, rig, *view)

        def predict(P, fp):
            return predict_pose(part.inv, part.scene, rig, P, chars, label=fp.label,
                                angles=(fp.rotation, fp.tilt_x, fp.tilt_y))

        res = search_poses(predict, start, center, **limits)
        print(f"\n== bad pose: {label}; plan: {res.start.n_decidable} of {len(chars)} decidable")
        for c in res.start.characteristics:
            if not c.decidable:
                print(f"   plan names {c.id}: {c.reason}")
        print(f"   proposed: {res.best.label}: {res.best.n_decidable} of {len(chars)} decidable")
        entry = {"case": label, "start": {}, "best": {}, "proposal": res.best.label}
        for key, pose, pred in (("start", start, res.start), ("best", res.best.part_to_camera, res.best)):
            radiance = render_radiance_pair(part.scene, rig, pose)
            rng = np.random.default_rng([seed, 99])
            left, right = (sensor(img, 2.0, rng) for img in radiance)
            try:
                evs, _, _, _ = measure_pair(left, right, rig, part.inv, chars, pose_hint=pose)
            except Exception as exc:  # the chain may fail altogether on a bad pose: that is the point
                print(f"   chain on the {key} render: {type(exc).__name__}: {exc}")
                entry[key] = {"error": str(exc)}
                continue
            for ev, cp in zip(evs, pred.characteristics):
                got = "not measured" if ev.expanded_uncertainty is None else f"U = {ev.expanded_uncertainty:.4f}"
                want = "not measurable" if not math.isfinite(cp.U) else f"U = {cp.U:.4f}"
                print(f"   {key:5s} render, chain: {ev.id:30s} {got:14s} (plan: {want})")
                entry[key][ev.id] = {"chain_U": ev.expanded_uncertainty, "plan_U": cp.U if math.isfinite(cp.U) else None}
        out.append(entry)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=50)
    ap.add_argument("--size", type=int, nargs=2, default=(1224, 1024))
    ap.add_argument("--parts", nargs="+", default=["plate", "bracket"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bad-pose", action="store_true", help="also run the bad-pose demonstration")
    ap.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    args = ap.parse_args()
    results = {"parts": [], "bad_pose": None}
    total_ok = total_bad = 0
    for name in args.parts:
        res = compare(name, tuple(args.size), args.draws, args.seed)
        ok, bad = print_table(res)
        total_ok, total_bad = total_ok + ok, total_bad + bad
        results["parts"].append(res)
    held = sum(r["own"][0] for r in results["parts"])
    compared = sum(r["own"][1] for r in results["parts"])
    print(f"\nall parts: {total_ok} of {total_ok + total_bad} within 20 %; {held} of {compared} within the "
          "prediction's own 95 % range")
    if args.bad_pose:
        results["bad_pose"] = bad_pose_demo(tuple(args.size), args.seed)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
