"""Honesty on images formed differently from the project's renderer, at noise 0.5 to 4.

The error model was built and checked on renders from
:mod:`partinspect.simulate.render`: a Gaussian PSF applied to the radiance
before each pixel integrates it, an exact rotated-lattice supersampling, a
uniform sensor. A camera is none of these exactly. This benchmark renders
the sample parts at their bundled poses, with the exact rig of their
``calibration.yaml``, under further image-formation models:

- ``project``: the renderer as it is (Gaussian PSF 0.6 px on the radiance,
  then pixel integration);
- ``blur-after``: each pixel's mean radiance first, then a digital
  Gaussian blur of 0.7 px on the pixel grid (as a filter or a demosaicing
  step would; the edge profile is then not a Gaussian-blurred step);
- ``disc-prnu``: each pixel's mean radiance, blurred by a uniform disc of
  radius 1.2 px (a defocused aperture) and multiplied by a fixed
  pixel-response non-uniformity (1 % gain, one pattern per camera,
  EMVA 1288's PRNU) before the noise.

For every model the noiseless image is formed once; each noise level and
seed adds Gaussian noise and quantises to 8 bits, and the pair is
inspected with the exact calibration. Printed per model and noise level:
per characteristic type, true value within +-U (claimed 95.45 %), RMS and
largest |error / u|; the position every measured hole would read
(``position, every hole``: the sample parts tolerance one hole's position
each, two holes' figures); hole centres' normalised error (the squared
Mahalanobis distance over 3, RMS) and the registered pose's (over 6).

Usage::

    python3 benchmarks/bench_formation.py                        # both parts, 3 models, noise 0.5,1,2,4, 2 seeds
    python3 benchmarks/bench_formation.py --parts plate --models blur-after --noise 1 --seeds 4
    python3 benchmarks/bench_formation.py --dir /tmp/formation    # keep the radiance and the reports
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

from bench_drift import CHI2_3
from bench_stress import coverage_cell, honesty_by_type, pose_mahalanobis, table, true_value

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("project", "blur-after", "disc-prnu")
PRNU = 0.01
DISC_RADIUS = 1.2
BLUR_AFTER = 0.7
CHI2_6 = 12.5916  # chi-square 95 % point, 6 degrees of freedom (the pose)


def _disc_kernel(radius, n=16):
    """A uniform disc of ``radius`` px integrated over each pixel (n x n sub-samples)."""
    r = int(np.ceil(radius))
    s = (np.arange(n) + 0.5) / n - 0.5
    k = np.zeros((2 * r + 1, 2 * r + 1))
    for i in range(-r, r + 1):
        for j in range(-r, r + 1):
            y, x = np.meshgrid(i + s, j + s, indexing="ij")
            k[i + r, j + r] = np.mean(x * x + y * y <= radius * radius)
    return k / k.sum()


def radiance(part, model, cache):
    """The noiseless left and right images (float) of a sample part under one formation model."""
    path = cache / f"{part}-{model}.npz"
    if path.is_file():
        z = np.load(path)
        return z["left"], z["right"]
    import cv2

    from partinspect.cad.mesh import tessellate
    from partinspect.cad.raycast import RENDER_ANGULAR_TOLERANCE, RENDER_TOLERANCE, build_scene
    from partinspect.cad.step import load_step
    from partinspect.simulate.folder import BLUR_SIGMA
    from partinspect.simulate.render import render_radiance_pair
    from partinspect.vision.calibration import read_calibration

    ex = ROOT / "examples" / part
    truth = json.loads((ex / "truth.json").read_text())
    calib = read_calibration(ex / "images" / "calibration.yaml")
    scene = build_scene(tessellate(load_step(ex / "part.step"), RENDER_TOLERANCE, RENDER_ANGULAR_TOLERANCE))
    P = np.asarray(truth["part_to_camera"], float)
    if model == "project":
        images = render_radiance_pair(scene, calib, P, blur_sigma=BLUR_SIGMA)
    else:
        means = render_radiance_pair(scene, calib, P, blur_sigma=0.0)
        images = []
        for index, m in enumerate(means):
            m = np.asarray(m, np.float64)
            if model == "blur-after":
                images.append(cv2.GaussianBlur(m, (0, 0), BLUR_AFTER, borderType=cv2.BORDER_REPLICATE))
            else:
                img = cv2.filter2D(m, -1, _disc_kernel(DISC_RADIUS), borderType=cv2.BORDER_REPLICATE)
                gain = 1.0 + PRNU * np.random.default_rng(1000 + index).standard_normal(img.shape)
                images.append(img * gain)
    left, right = (np.asarray(i, np.float32) for i in images)
    np.savez_compressed(path, left=left, right=right)
    return left, right


def noisy_pair(left, right, noise, seed, folder, calibration):
    """Write the pair with noise and 8-bit quantisation, and the calibration, into ``folder``."""
    import cv2

    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    for name, img in (("left.png", left), ("right.png", right)):
        x = np.clip(np.rint(img + noise * rng.standard_normal(img.shape)), 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / name), x)
    shutil.copy(calibration, folder / "calibration.yaml")


def score(report, truth, every_hole=False):
    """Characteristic rows for honesty_by_type, and the hole centres' normalised errors.

    ``every_hole``: add a row for the position of every measured hole
    (:func:`every_hole_position`), toleranced or not.
    """
    rows = []
    for c in report["characteristics"]:
        tv = true_value(c, truth)
        if c["measured"] is None or tv is None:
            continue
        rows.append({"type": c["type"], "id": c["id"], "measured": c["measured"], "true": tv,
                     "u": c["standard_uncertainty"], "U": c["expanded_uncertainty"]})
    truth_features = {f["id"]: f for f in truth["features"]}
    centres = []
    for f in report["features"]:
        m, t = f["measured"], truth_features.get(f["id"])
        if m is None or f["kind"] == "line" or t is None or "center" not in m:
            continue
        e = np.asarray(m["center"], float) - np.asarray(t["rendered"]["center"], float)
        centres.append(float(e @ np.linalg.solve(np.asarray(m["covariance"], float), e)))
        if every_hole and not t.get("deviated"):
            rows.append(every_hole_position(f["id"], m, t["nominal"]))
    return rows, centres


def every_hole_position(fid, measured, nominal):
    """The position a hole would read if toleranced, as a row for honesty_by_type (true value 0).

    The sample parts tolerance the position of one hole each, and its error
    repeats from seed to seed (the rim's fixed displacement), so the
    toleranced positions alone are two holes' figures; every measured hole's
    position, as :func:`partinspect.tolerances.evaluate.true_position` states
    it from the reported centre and covariance, is a sample of all of them.
    """
    from partinspect.tolerances.evaluate import COVERAGE_FACTOR, true_position

    value, u = true_position(np.asarray(measured["center"], float), np.asarray(measured["covariance"], float),
                             np.asarray(nominal["center"], float), np.asarray(nominal["normal"], float),
                             np.random.default_rng(0))
    return {"type": "position, every hole", "id": f"{fid}.position (every hole)", "measured": value, "true": 0.0,
            "u": u, "U": COVERAGE_FACTOR * u}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", default="plate,bracket")
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--noise", default="0.5,1,2,4")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--dir", default=None)
    args = ap.parse_args()
    from partinspect.errors import InputError
    from partinspect.pipeline import run_inspection

    work = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="formation-"))
    work.mkdir(parents=True, exist_ok=True)
    noises = [float(x) for x in args.noise.split(",")]
    results = defaultdict(lambda: {"rows": [], "centres": [], "poses": [], "failed": 0, "s": []})
    for part in args.parts.split(","):
        ex = ROOT / "examples" / part
        truth = json.loads((ex / "truth.json").read_text())
        for model in args.models.split(","):
            left, right = radiance(part, model, work)
            for noise in noises:
                for seed in range(args.seeds):
                    folder = work / f"{part}-{model}-{noise}-{seed}"
                    noisy_pair(left, right, noise, 7000 + seed, folder / "images", ex / "images" / "calibration.yaml")
                    t0 = time.perf_counter()
                    key = (model, noise)
                    try:
                        report = run_inspection(ex / "part.step", folder / "images", folder / "out").report
                    except InputError as e:
                        print(f"{part} {model} noise {noise} seed {seed}: {e}")
                        results[key]["failed"] += 1
                        continue
                    rows, centres = score(report, truth, every_hole=True)
                    results[key]["rows"] += rows
                    results[key]["centres"] += centres
                    results[key]["poses"].append(pose_mahalanobis(report["registration"], truth))
                    results[key]["s"].append(time.perf_counter() - t0)
                    worst = max(rows, key=lambda r: abs(r["measured"] - r["true"]) / r["u"])
                    print(f"{part} {model} noise {noise} seed {seed}: {len(rows)} judged, worst {worst['id']} "
                          f"{(worst['measured'] - worst['true']) / worst['u']:+.1f} u", flush=True)
    for (model, noise), r in sorted(results.items()):
        print(f"== {model}, noise {noise} ({args.parts}; {args.seeds} seeds; {r['failed']} runs failed)")
        header, rows = honesty_by_type(r["rows"])
        c = np.asarray(r["centres"])
        if len(c):
            rows.append(["centre (3D)", len(c), len(c), coverage_cell(np.sum(c <= CHI2_3), len(c)),
                         f"{np.sqrt(np.mean(c / 3)):.2f}", "-", f"{np.sqrt(c.max() / 3):.1f}"])
        p = np.asarray(r["poses"])
        if len(p):
            rows.append(["pose (6D)", len(p), len(p), coverage_cell(np.sum(p <= CHI2_6), len(p)),
                         f"{np.sqrt(np.mean(p / 6)):.2f}", "-", f"{np.sqrt(p.max() / 6):.1f}"])
        table(header, rows)
    if not args.dir:
        shutil.rmtree(work)


if __name__ == "__main__":
    main()
