"""The rims' stated covariance split by source, against their errors split the same way.

For each sample part and image-formation model of :mod:`bench_formation`,
the noiseless pair (8-bit, no noise) and noisy pairs of the same scene are
measured and registered as ``inspect`` does (``pipeline.measure``). Per
measured hole (its CAD id), in the rig frame against the rendered rim:

- the systematic error is the noiseless pair's error; the noise error is a
  noisy pair's error less the noiseless one's;
- each is compared with its stated component of the noisy run's covariance
  (``Feature3D.param_cov_image``: image noise; ``param_cov_systematic``:
  the rims' Type B after ``type_b_scale``), and the whole error with the
  whole covariance: normalised RMS of the centre in the hole's plane
  (``|P e|^2 / tr(P C P)``), along its axis, and of the radius;
- the pose's share of the part-frame covariance is printed;
- every pair of holes measured in one run gives a distance between their
  centres (rig frame): its error, whole and systematic, over its stated u
  with the two holes' covariances independent (as stated: the sample
  parts' calibration states no covariance, so nothing is shared), which
  shows whether the holes' errors are shared;
- the systematic errors, in the rig frame (x, y, depth) and turned into the
  part frame, are compared between holes: per axis their mean, RMS, and the
  pooled correlation between different holes
  ``sum_{i != j} e_i e_j / ((n - 1) sum_i e_i^2)``;
- the shading correction's factor as one unknown shared by all rims: each
  rim's response ``g`` to ``BACKGROUND_CORRECTION`` (the noiseless pair
  measured again with the factor 0.2 higher, ``measure_stereo`` alone) and
  the one factor error ``dk`` that best explains every rim's systematic
  centre and radius error as ``dk g`` (least squares), with the error RMS
  before and after removing it.

Usage::

    python3 benchmarks/bench_rim_budget.py --parts plate,bracket --models project,disc-prnu --noise 0.5,2 --seeds 2
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np

from bench_formation import ROOT, noisy_pair, radiance


def measured_holes(part, images):
    """``{cad id: (Feature3D, PartFeature)}`` of the circles ``inspect`` measures and registers in ``images``."""
    from partinspect.pipeline import check_calibration, load_inputs, measure

    ex = ROOT / "examples" / part
    inputs = load_inputs(ex / "part.step", images, images.parent / "out", None, None, lambda m: None)
    check, first = check_calibration(inputs, lambda m: None)
    m = measure(inputs, lambda m: None, check, first)
    reg = m.registration
    parts = {pf.index: pf for pf in reg.features_in_part_frame() if pf.kind == "circle"}
    circles = [f for f in m.stereo.features if f.kind != "line"]
    out = {}
    for i, f in enumerate(circles):
        cid = reg.assignment["circle"].get(i)
        if cid is not None:
            out[cid] = (f, parts[i], reg)
    return out


def correction_response(images, truth, step=0.2):
    """``{cad id: d(center, radius) / d BACKGROUND_CORRECTION}`` (4,) of the rims ``measure_stereo`` finds, mm.

    Rims are named by the nearest rendered rim (centre within 0.5 mm).
    """
    import partinspect.vision.stereo as stereo
    from partinspect.vision.calibration import read_calibration
    from partinspect.vision.images import read_pair

    calib = read_calibration(images)
    left, right, _ = read_pair(images, calib)
    k0 = stereo.BACKGROUND_CORRECTION
    out = []
    try:
        for k in (k0, k0 + step):
            stereo.BACKGROUND_CORRECTION = k
            out.append([f for f in stereo.measure_stereo(left, right, calib).features if f.kind != "line"])
    finally:
        stereo.BACKGROUND_CORRECTION = k0
    ids = [f["id"] for f in truth["features"] if f["kind"] != "line"]
    resp = {}
    for f in out[0]:
        d, cid = min((np.linalg.norm(f.center - rig_truth(truth, i)[0]), i) for i in ids)
        g = min(out[1], key=lambda x: np.linalg.norm(x.center - f.center))
        if d < 0.5 and np.linalg.norm(g.center - f.center) < 0.05:
            resp[cid] = (np.r_[g.center, g.radius] - np.r_[f.center, f.radius]) / step
    return resp


def correlation_row(E):
    """Per column of E (holes x axes): mean / RMS / pooled correlation between different holes, um."""
    cols = []
    for v in 1e3 * np.asarray(E).T:
        s2 = np.sum(v * v)
        rho = (np.sum(v) ** 2 - s2) / ((len(v) - 1) * s2)
        cols.append(f"{v.mean():+.2f} / {np.sqrt(np.mean(v * v)):.2f} / {rho:+.2f}")
    return " | ".join(cols)


def rig_truth(truth, cid):
    t = next(f for f in truth["features"] if f["id"] == cid)["rendered"]
    P = np.asarray(truth["part_to_camera"], float)
    return P[:3, :3] @ t["center"] + P[:3, 3], P[:3, :3] @ t["normal"], t["radius"], np.asarray(t["center"], float)


def errors(f, truth, cid):
    """Rig-frame centre error (3,) and radius error of a measured rim."""
    c, _, r, _ = rig_truth(truth, cid)
    return np.asarray(f.center, float) - c, float(f.radius) - r


def ratios(e, er, C, crr, n):
    """Squared normalised errors: in-plane centre, along the axis, radius."""
    P = np.eye(3) - np.outer(n, n)
    return (float(e @ P @ P @ e / np.trace(P @ C @ P)), float((n @ e) ** 2 / (n @ C @ n)), er * er / crr)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", default="plate,bracket")
    ap.add_argument("--models", default="project,disc-prnu")
    ap.add_argument("--noise", default="0.5,2")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--dir", default=None)
    args = ap.parse_args()
    work = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="rim-budget-"))
    work.mkdir(parents=True, exist_ok=True)
    cells = defaultdict(lambda: defaultdict(list))
    shared = defaultdict(list)
    for part in args.parts.split(","):
        ex = ROOT / "examples" / part
        truth = json.loads((ex / "truth.json").read_text())
        R = np.asarray(truth["part_to_camera"], float)[:3, :3]
        cal = ex / "images" / "calibration.yaml"
        for model in args.models.split(","):
            left, right = radiance(part, model, work)
            folder = work / f"{part}-{model}-0"
            noisy_pair(left, right, 0.0, 0, folder / "images", cal)
            clean = measured_holes(part, folder / "images")
            sys_err = {cid: errors(f, truth, cid) for cid, (f, _, _) in clean.items()}
            ids = sorted(sys_err)
            rig = np.array([np.r_[sys_err[c][0], sys_err[c][1]] for c in ids])
            # The part frame's axes, for their correlation between holes.
            prt = np.c_[rig[:, :3] @ R, rig[:, 3]]
            resp = correction_response(folder / "images", truth)
            both = [c for c in ids if c in resp]
            Eg = np.array([np.r_[sys_err[c][0], sys_err[c][1]] for c in both]).ravel()
            G = np.array([resp[c] for c in both]).ravel()
            dk = float(G @ Eg / (G @ G))
            shared[model].append((part, ids, rig, prt, dk, len(both), np.sqrt(np.mean(Eg ** 2)),
                                  np.sqrt(np.mean((Eg - dk * G) ** 2))))
            for noise in [float(x) for x in args.noise.split(",")]:
                for seed in range(args.seeds):
                    folder = work / f"{part}-{model}-{noise}-{seed}"
                    noisy_pair(left, right, noise, 7000 + seed, folder / "images", cal)
                    holes = measured_holes(part, folder / "images")
                    cell = cells[(model, noise)]
                    both = sorted(c for c in holes if c in sys_err)
                    for i, a in enumerate(both):
                        for b in both[i + 1:]:
                            fa, fb = holes[a][0], holes[b][0]
                            d = np.asarray(fa.center, float) - np.asarray(fb.center, float)
                            d = d / np.linalg.norm(d)
                            ea, eb = errors(fa, truth, a)[0], errors(fb, truth, b)[0]
                            u2 = d @ (fa.param_cov[:3, :3] + fb.param_cov[:3, :3]) @ d
                            s2 = d @ (fa.param_cov_systematic[:3, :3] + fb.param_cov_systematic[:3, :3]) @ d
                            es = sys_err[a][0] - sys_err[b][0]
                            cell["distance"].append(((d @ (ea - eb)) ** 2 / u2, (d @ es) ** 2 / s2))
                    for cid, (f, pf, reg) in holes.items():
                        if cid not in sys_err:
                            continue
                        _, n, _, _ = rig_truth(truth, cid)
                        e, er = errors(f, truth, cid)
                        es, ers = sys_err[cid]
                        img, sysb, calc = f.param_cov_image, f.param_cov_systematic, f.param_cov_calibration
                        whole = f.param_cov
                        cell["noise"].append(ratios(e - es, er - ers, img[:3, :3], img[6, 6], n))
                        cell["typeb"].append(ratios(es, ers, sysb[:3, :3], sysb[6, 6], n))
                        cell["whole"].append(ratios(e, er, whole[:3, :3], whole[6, 6], n))
                        cell["sys_vs_whole"].append(ratios(es, ers, whole[:3, :3], whole[6, 6], n))
                        A = R.T
                        own = A @ whole[:3, :3] @ A.T
                        cell["pose_share"].append(1.0 - np.trace(own) / np.trace(pf.param_cov[:3, :3]))
                        cell["typeb_share"].append((np.trace(sysb[:3, :3]) / np.trace(whole[:3, :3]),
                                                    sysb[6, 6] / whole[6, 6]))
                        cell["cal_share"].append(np.trace(calc[:3, :3]) / np.trace(whole[:3, :3]))
                        print(f"{part} {model} {noise} {seed} {cid}: sys centre (um) "
                              f"{np.array2string(1e3 * es, precision=2)} r {1e3 * ers:+.2f}; noise "
                              f"{np.array2string(1e3 * (e - es), precision=2)} r {1e3 * (er - ers):+.2f}; "
                              f"u_typeB r {1e3 * np.sqrt(sysb[6, 6]):.2f} u_img r {1e3 * np.sqrt(img[6, 6]):.2f}",
                              flush=True)
    print("\nNormalised error RMS (in-plane centre, along the axis, radius), n holes")
    print("| model | noise | n | noise part vs image-noise u | systematic part vs Type B u | systematic vs whole u "
          "| whole vs whole u | Type B share (centre, radius) | pose share | calibration share |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (model, noise), c in sorted(cells.items()):
        def rms(k):
            a = np.asarray(c[k])
            return ", ".join(f"{v:.2f}" for v in np.sqrt(a.mean(axis=0)))
        ts = np.median(np.asarray(c["typeb_share"]), axis=0)
        print(f"| {model} | {noise:g} | {len(c['noise'])} | {rms('noise')} | {rms('typeb')} | {rms('sys_vs_whole')} "
              f"| {rms('whole')} | {100 * ts[0]:.0f} %, {100 * ts[1]:.0f} % | {100 * np.median(c['pose_share']):.2f} % "
              f"| {100 * np.median(c['cal_share']):.1f} % |")
    print("\nDistances between every pair of holes of a run (rig frame), normalised error RMS: whole error over "
          "whole u, systematic part over Type B u; pairs")
    for (model, noise), c in sorted(cells.items()):
        a = np.asarray(c["distance"])
        w, sb = np.sqrt(a.mean(axis=0))
        print(f"| {model} | {noise:g} | {w:.2f} | {sb:.2f} | {len(a)} |")
    print("\nSystematic errors between holes (um): mean / RMS / correlation between holes, per axis and radius")
    print("| model | part (holes) | frame | x | y | z (rig: depth) | radius |")
    print("|---|---|---|---|---|---|---|")
    for model, rows in shared.items():
        for part, ids, rig, prt, *_ in rows:
            print(f"| {model} | {part} ({len(ids)}) | rig | {correlation_row(rig)} |")
            print(f"| {model} | {part} ({len(ids)}) | part | {correlation_row(prt)} |")
    print("\nOne shading-correction factor error for all rims: dk, rims, systematic error RMS before / after removing dk g")
    for model, rows in shared.items():
        for part, ids, rig, prt, dk, n, before, after in rows:
            print(f"| {model} | {part} | {dk:+.3f} | {n} | {1e3 * before:.2f} um | {1e3 * after:.2f} um |")


if __name__ == "__main__":
    main()
