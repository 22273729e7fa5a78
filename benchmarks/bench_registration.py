"""Registration accuracy, honesty of the pose covariance, and speed.

For each sample part at the renderer's default pose, many noise draws of the
visible features (anisotropic: lateral 2 um, depth 8 um for centres and line
points; :mod:`partinspect.simulate.measured`) are registered with no pose
given. Printed per part:

- pose error (rotation, deg; translation at the part origin, um): RMS of the
  actual errors against the RMS of the predicted standard uncertainties;
- normalised errors ``e_i / u_i`` per pose component: their RMS (honest: 0.8
  to 1.25) and the fraction with ``|z| <= 1.96`` (93-97 %);
- the joint 95 % coverage: fraction with ``xi^T Sigma^-1 xi <= chi2_6(0.95)``;
- the fraction of draws with every feature assigned to the right CAD id;
- the time per registration (median and 90th percentile, hypothesis search
  included).

Then the hypothesis search's scoring on the NIST ftc_09 model (hundreds
of edges; its visible features at the default pose, one noise draw): every
hypothesis scored in batches (``pose_search._scores``, what ``register``
does) against one pose at a time (``pose_search.match`` in a loop, the
baseline), on the first 4000 hypotheses, median of 3 runs each, and
whether they agree.

With ``--characteristics N`` it also evaluates, on the plate with hole
circle-4 moved by 0.1 mm and edge line-5 by 0.05 mm (both left out of the
datums), one characteristic of each type over N draws and prints, per type,
the RMS of (measured - truth) / u and the fraction with |measured - truth|
<= U (k = 2).

Run: ``python3 benchmarks/bench_registration.py [--draws 200] [--datums lines] [--characteristics 100]``
(``--draws 0``: the scoring comparison alone)
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy import stats

from partinspect.cad.features import inventory
from partinspect.cad.pose_refine import pose_error
from partinspect.cad.registration import register
from partinspect.cad.step import load_step
from partinspect.simulate.measured import measure_features
from partinspect.poses import default_pose
from partinspect.simulate.rig import default_rig

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run(part, draws, seed, datums_kind):
    shape = load_step(EXAMPLES / part / "part.step")
    inv = inventory(shape)
    T = default_pose(shape, default_rig())
    truth = json.loads((EXAMPLES / part / "truth.json").read_text())
    ids = [f["id"] for f in truth["features"] if f["visible_both"]]
    datums = None if datums_kind == "all" else [i for i in ids if i.startswith(datums_kind.rstrip("s"))]
    rng = np.random.default_rng(seed)
    errs, stds, d2, times, right, wrms = [], [], [], [], 0, []
    for _ in range(draws):
        m = measure_features(inv, T, ids, rng, n_points=0)
        t0 = time.perf_counter()
        reg = register(m.circles, m.lines, inv, datums=datums)
        times.append(time.perf_counter() - t0)
        e = pose_error(reg.part_to_camera, T)
        errs.append(e)
        stds.append(reg.pose_std)
        d2.append(e @ np.linalg.solve(reg.pose_cov, e))
        wrms.append(reg.weighted_rms)
        right += all(reg.assignment["circle"].get(i) == c for i, c in enumerate(m.circle_ids)) and all(
            reg.assignment["line"].get(j) == c for j, c in enumerate(m.line_ids)
        )
    errs, stds, d2, times = map(np.array, (errs, stds, d2, times))
    z = errs / stds
    rot = np.rad2deg(np.linalg.norm(errs[:, :3], axis=1))
    tra = 1e3 * np.linalg.norm(errs[:, 3:], axis=1)
    rot_pred = np.rad2deg(np.sqrt((stds[:, :3] ** 2).sum(1)))
    tra_pred = 1e3 * np.sqrt((stds[:, 3:] ** 2).sum(1))
    print(f"\n{part}: {len(m.circles)} circles, {len(m.lines)} lines visible; datums: {datums_kind}; {draws} draws")
    print(f"  rotation error     RMS {np.sqrt(np.mean(rot**2)):.5f} deg (max {rot.max():.5f}), predicted {np.sqrt(np.mean(rot_pred**2)):.5f} deg")
    print(f"  translation error  RMS {np.sqrt(np.mean(tra**2)):.2f} um (max {tra.max():.2f}), predicted {np.sqrt(np.mean(tra_pred**2)):.2f} um")
    print("  z RMS   (wx wy wz vx vy vz): " + " ".join(f"{v:.3f}" for v in np.sqrt(np.mean(z**2, 0))))
    print("  |z|<=1.96 coverage, %:       " + " ".join(f"{100 * v:.1f}" for v in np.mean(np.abs(z) <= 1.96, 0)))
    print(f"  joint 95 % coverage (chi2_6): {100 * np.mean(d2 <= stats.chi2.ppf(0.95, 6)):.1f} %")
    print(f"  weighted RMS (sqrt(chi2/dof)) mean {np.mean(wrms):.3f}")
    print(f"  assignment right in {right}/{draws} draws")
    print(f"  time per registration: median {1e3 * np.median(times):.1f} ms, p90 {1e3 * np.percentile(times, 90):.1f} ms")


def characteristics(draws, seed):
    import math

    from partinspect.tolerances.evaluate import evaluate
    from partinspect.tolerances.geometry import feature_distance
    from partinspect.tolerances.resolve import Characteristic

    shape = load_step(EXAMPLES / "plate" / "part.step")
    inv = inventory(shape)
    T = default_pose(shape, default_rig())
    ids = [f["id"] for f in json.loads((EXAMPLES / "plate" / "truth.json").read_text())["features"] if f["visible_both"]]
    shifts = {"circle-4": np.array([0.1, 0.0, 0.0]), "line-5": np.array([0.0, 0.05, 0.0])}
    datums = [i for i in ids if i not in shifts]

    def C(cid, t, f, nominal=0.0):
        return Characteristic(cid, t, tuple(f), nominal, None, 1.0, "bench", unit="rad" if t == "angle" else "mm")

    chars = [
        (C("diameter", "diameter", ["circle-8"], 10.0), 10.0),
        (C("radius", "radius", ["circle-6"], 2.0), 2.0),
        (C("position (0.2 mm off)", "position", ["circle-4"]), 0.2),
        (C("position (on nominal)", "position", ["circle-8"]), 0.0),
        (C("profile line (0.1 mm off)", "profile", ["line-5"]), None),
        (C("straightness", "straightness", ["line-8"]), None),
        (C("circularity", "circularity", ["circle-2"]), None),
        (C("distance centre-centre", "distance", ["circle-2", "circle-10"]), feature_distance(inv["circle-2"], inv["circle-10"])),
        (C("distance lines", "distance", ["line-6", "line-8"]), None),
        (C("angle", "angle", ["line-5", "line-1"]), math.pi / 2),
    ]
    rng = np.random.default_rng(seed)
    z = {c.id: [] for c, _ in chars}
    t_eval = []
    for draw in range(draws):
        m = measure_features(inv, T, ids, rng, n_points=60, shifts=shifts)
        reg = register(m.circles, m.lines, inv, datums=datums)
        t0 = time.perf_counter()
        ev = evaluate([c for c, _ in chars], reg, inv, seed=draw)
        t_eval.append(time.perf_counter() - t0)
        for (c, truth), e in zip(chars, ev):
            if truth is None:
                truth = _truth(c, inv, T, ids, shifts)
            z[c.id].append((e.measured - truth) / e.standard_uncertainty)
    print(f"\ncharacteristics on the plate, {draws} draws (60 edge points per feature, 5 um / 20 um point noise)")
    print(f"  {'characteristic':28s} {'RMS z':>7s} {'|err|<=U':>9s}")
    for cid, zs in z.items():
        zs = np.array(zs)
        print(f"  {cid:28s} {np.sqrt(np.mean(zs**2)):7.3f} {100 * np.mean(np.abs(zs) <= 2):8.1f}%")
    print(f"  evaluation time for these {len(chars)}: median {1e3 * np.median(t_eval):.0f} ms")


def _truth(c, inv, T, ids, shifts):
    """Noise-free truth of the characteristics whose value is not a plain number above."""
    if c.type == "profile":
        return 2 * 0.05  # the edge moved 0.05 mm off nominal, form-free
    if c.type in ("straightness", "circularity"):
        return 0.0  # form-free edges
    if c.type == "distance":
        from partinspect.tolerances.geometry import feature_distance

        return feature_distance(inv[c.features[0]], inv[c.features[1]])
    raise ValueError(c.type)


def scoring_speed(step, runs=3, n_hyps=4000):
    """Batched hypothesis scoring against one pose at a time, on one STEP model (its first ``n_hyps`` hypotheses)."""
    from partinspect.cad import pose_search as reg
    from partinspect.simulate.measured import facing_feature_ids

    shape = load_step(step)
    inv = inventory(shape)
    T = default_pose(shape, default_rig())
    m = measure_features(inv, T, facing_feature_ids(inv, T), np.random.default_rng(0), n_points=0)
    meas, cad = reg.measured_arrays(m.circles, m.lines), reg.cad_arrays(inv)
    hyps = (reg._circle_hypotheses(meas, cad) or reg._line_hypotheses(meas, cad))[:n_hyps]

    def one_at_a_time():
        out = []
        for R, t in hyps:
            circ, lin, cost = reg.match(meas, cad, R, t)
            out.append((len(circ) + len(lin), cost))
        return out

    times = {}
    results = {}
    for name, fn in (("batched", lambda: reg._scores(meas, cad, hyps)), ("one at a time", one_at_a_time)):
        ts = []
        for _ in range(runs):
            t0 = time.perf_counter()
            results[name] = fn()
            ts.append(time.perf_counter() - t0)
        times[name] = float(np.median(ts))
    same = results["batched"] == results["one at a time"] or np.allclose(
        np.array(results["batched"]), np.array(results["one at a time"]), rtol=1e-12, atol=0)
    print(f"\n== hypothesis scoring, {Path(step).name}: {len(meas.radii)} circles and {len(meas.lengths)} lines "
          f"measured against {len(cad.radii)} and {len(cad.lengths)} CAD ones, {len(hyps)} hypotheses "
          f"(median of {runs})")
    print(f"   batched {times['batched']:.2f} s, one pose at a time {times['one at a time']:.2f} s "
          f"(x{times['one at a time'] / times['batched']:.1f}); same scores: {'yes' if same else 'NO'}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--datums", choices=["all", "lines", "circles"], default="all")
    ap.add_argument("--characteristics", type=int, default=0, metavar="N")
    args = ap.parse_args()
    if args.draws:
        for part in ("plate", "bracket"):
            run(part, args.draws, args.seed, args.datums)
    nist = Path(__file__).resolve().parents[1] / "tests" / "data" / "step" / "nist_ftc_09_asme1_ap242-e1.stp"
    if nist.exists():
        scoring_speed(nist)
    if args.characteristics:
        characteristics(args.characteristics, args.seed)


if __name__ == "__main__":
    main()
