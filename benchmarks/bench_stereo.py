"""Accuracy, honesty and speed of the stereo chain on a rendered sample part.

For each noise level the noiseless radiance of the part is ray-cast once
per light direction (12 by default: the rims' Type B component stands for
how the shading beside a hole falls, a fixed offset under one light), then
every draw, cycling through the lights, adds fresh sensor noise
(``partinspect.simulate.render.sensor``) and runs the whole 2D + 3D chain.
Reported per noise level: RMS errors of circle centres per axis, radii and
line positions (perpendicular to the line, at the measured line's point,
where its covariance is stated) beside their noise-only bounds, coverage
of the 95 % ellipsoid (centres) and of +-2u (radii), RMS of normalised errors, the median standard
uncertainties of centre depth and radius with the share of the systematic
rim component (``Feature3D.param_cov_systematic``) in the depth variance;
beside an OpenCV baseline
(Canny + findContours + fitEllipse, ellipse centres matched along epipolar
lines and triangulated with triangulatePoints, radius = semi-major axis x
depth / f, averaged over the views). Then the median wall time of
``measure_stereo`` on a 2448 x 2048 pair, beside the same runs with the two
images' 2D chains one after the other (``parallel=False``).

    python3 benchmarks/bench_stereo.py [--draws N] [--lights L] [--part plate] [--size 1224 1024]
"""

import argparse
import os
import sys
import time
from pathlib import Path

# As the inspect command sets it (cli.py), before NumPy and OpenCV load their BLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from partinspect.simulate.render import render_radiance, sensor
from partinspect.cad.raycast import DEFAULT_SHADING, camera_in_part
from partinspect.vision import forked as forked_module  # noqa: E402
from partinspect.vision.ideal import camera_matrices  # noqa: E402
from partinspect.vision.stereo import measure_stereo  # noqa: E402
from tests.vision import stereo_scenes as S  # noqa: E402

CHI2_3_95 = 7.814727903251178


def light_directions(n, seed=7, cone_deg=35.0):
    """The default light and n - 1 random directions within ``cone_deg`` of it (rig frame).

    The rim's Type B component stands for how the shading beside a hole
    happens to fall; over one light it is a fixed offset, over many lights
    the distribution its standard uncertainty describes.
    """
    rng = np.random.default_rng(seed)
    d0 = DEFAULT_SHADING.direction()
    out = [d0]
    while len(out) < n:
        v = d0 + rng.normal(0, 0.35, 3)
        v /= np.linalg.norm(v)
        if np.degrees(np.arccos(v @ d0)) < cone_deg:
            out.append(v)
    return out


def radiance(name, size, light_rig=None):
    p = S.part(name)
    rig = p.rig(False, size)
    pose = p.pose(rig)
    light = pose[:3, :3].T @ (DEFAULT_SHADING.direction() if light_rig is None else light_rig)
    out = []
    for i in range(2):
        K, D, R, t = camera_in_part(rig, i, pose)
        img, _ = render_radiance(p.scene, K, D, R, t, rig.image_size, light, psf=0.6)
        out.append(img)
    return rig, pose, out


def opencv_circles(L, R, rig):
    """The obvious OpenCV alternative: centres and radii of ellipses seen in both images."""
    ells = []
    for img in (L, R):
        e = cv2.Canny(img, 40, 100)
        cs, _ = cv2.findContours(e, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        el = []
        for c in cs:
            if len(c) < 40:
                continue
            (cx, cy), (w, h), ang = cv2.fitEllipse(c)
            pts = c.reshape(-1, 2).astype(float)
            if max(w, h) > 400 or min(w, h) < 8:
                continue
            # Keep closed-ish contours that the ellipse fits.
            if np.ptp(pts[:, 0]) < 0.6 * min(w, h):
                continue
            el.append((cx, cy, max(w, h) / 2))
        ells.append(np.array(el).reshape(-1, 3))
    P1, P2 = camera_matrices(rig)
    from partinspect.vision.triangulation import fundamental_matrix

    F = fundamental_matrix(rig.K1, rig.K2, rig.R, rig.T)
    out, used = [], set()
    for cx, cy, a in ells[0]:
        l = F @ [cx, cy, 1.0]
        d = np.abs(ells[1][:, 0] * l[0] + ells[1][:, 1] * l[1] + l[2]) / np.hypot(l[0], l[1])
        score = d + 5 * np.abs(np.log(ells[1][:, 2] / a)) * 10
        if len(score) == 0:
            continue
        j = int(np.argmin(score))
        if d[j] > 3 or j in used:
            continue
        used.add(j)
        X = cv2.triangulatePoints(P1, P2, np.array([[cx], [cy]]), ells[1][j, :2].reshape(2, 1))
        X = (X[:3] / X[3]).ravel()
        zr = (rig.R @ X + rig.T)[2]
        out.append((X, 0.5 * (a * X[2] / rig.K1[0, 0] + ells[1][j, 2] * zr / rig.K2[0, 0])))
    return out


def nearest_circle(X, truths):
    best = min((t for t in truths if t["kind"] == "circle"), key=lambda t: np.linalg.norm(t["center"] - X))
    return best


def run(name, size, noises, draws, n_lights=12):
    lights = light_directions(n_lights)
    rads = [radiance(name, size, l) for l in lights]
    rig = rads[0][0]
    truths = S.truth_in_rig(name, False, size)
    truth_ids = {t["id"]: t for t in truths}
    P1, _ = camera_matrices(rig)
    rows = []
    for noise in noises:
        rng = np.random.default_rng(int(noise * 1000))
        ce, cz, re, rz, le, lz, lb, base_c, base_r = [], [], [], [], [], [], [], [], []
        u_depth, u_rad, sys_share, bound_c, bound_r, whole, through = [], [], [], [], [], [], []
        for d in range(draws):
            rad = rads[d % len(rads)][2]
            L, R = sensor(rad[0], noise, rng), sensor(rad[1], noise, rng)
            res = measure_stereo(L, R, rig)
            for f in res.features:
                lab = S.label_image_feature(res.left.features[f.left].ideal.xy, truths, P1)
                if lab is None:
                    continue
                t = truth_ids[lab]
                if f.kind == "line":
                    if t["kind"] != "line":
                        continue  # a short stretch of a rim taken for a line
                    e = S.line_point_error(f.point, f.direction, t)
                    le.append(e)
                    lz.append(e @ np.linalg.pinv(f.covariance, rcond=1e-10) @ e)
                    lb.append(np.diag(f.param_cov_image[:3, :3]))
                elif t["kind"] == "circle" and not t["visible_both"]:
                    # A bottom rim glimpsed through its hole: registration never
                    # takes it as that edge (inspect reports it unmeasured).
                    through.append(np.linalg.norm(f.center - t["center"]))
                elif t["kind"] == "circle":
                    e = f.center - t["center"]
                    ce.append(e)
                    cz.append(e @ np.linalg.inv(f.covariance) @ e)
                    re.append(f.radius - t["radius"])
                    rz.append((f.radius - t["radius"]) / f.radius_std)
                    u_depth.append(np.sqrt(f.covariance[2, 2]))
                    u_rad.append(f.radius_std)
                    sys_share.append(f.param_cov_systematic[2, 2] / f.param_cov[2, 2])
                    # What image noise alone allows: the fits' covariance (at the
                    # KCR bound for the edge points' noise, tests/vision) propagated.
                    bound_c.append(np.diag(f.param_cov_image[:3, :3]))
                    bound_r.append(f.param_cov_image[6, 6])
                    whole.append(f.kind == "circle")
            for X, r in opencv_circles(L, R, rig):
                t = nearest_circle(X, truths)
                if np.linalg.norm(X - t["center"]) < 1.0:
                    base_c.append(X - t["center"])
                    base_r.append(r - t["radius"])
        ce, le, base_c = np.array(ce).reshape(-1, 3), np.array(le).reshape(-1, 3), np.array(base_c).reshape(-1, 3)
        cz, rz, whole = np.array(cz), np.array(rz), np.array(whole, bool)
        rows.append(dict(
            noise=noise, draws=draws, n_circles=len(ce), n_whole=int(whole.sum()), n_lines=len(le),
            n_through=len(through), through_median=np.median(through) * 1e3 if through else np.nan,
            centre_rms=np.sqrt((ce**2).mean(0)) * 1e3, radius_rms=np.sqrt(np.mean(np.square(re))) * 1e3,
            centre_bound=np.sqrt(np.mean(bound_c, axis=0)) * 1e3, radius_bound=np.sqrt(np.mean(bound_r)) * 1e3,
            centre_cov95=np.mean(cz <= CHI2_3_95), radius_cov95=np.mean(np.abs(rz) <= 2),
            centre_cov95_whole=np.mean(cz[whole] <= CHI2_3_95), radius_cov95_whole=np.mean(np.abs(rz[whole]) <= 2),
            centre_cov95_arc=np.mean(cz[~whole] <= CHI2_3_95), radius_cov95_arc=np.mean(np.abs(rz[~whole]) <= 2),
            centre_nrms=np.sqrt(np.mean(cz) / 3), radius_nrms=np.sqrt(np.mean(np.square(rz))),
            line_rms=np.sqrt((le**2).mean(0)) * 1e3, line_bound=np.sqrt(np.mean(lb, axis=0)) * 1e3,
            line_cov95=np.mean(np.array(lz) <= 5.991464547107979),
            line_nrms=np.sqrt(np.mean(lz) / 2),
            u_depth=np.median(u_depth) * 1e3, u_radius=np.median(u_rad) * 1e3, sys_share=np.median(sys_share),
            cv_n=len(base_c), cv_centre_rms=np.sqrt((base_c**2).mean(0)) * 1e3 if len(base_c) else np.full(3, np.nan),
            cv_radius_rms=np.sqrt(np.mean(np.square(base_r))) * 1e3 if base_r else np.nan))
    return rows


def fmt(v):
    return "/".join(f"{x:.1f}" for x in v)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=120)
    ap.add_argument("--part", default="plate")
    ap.add_argument("--size", type=int, nargs=2, default=(1224, 1024))
    ap.add_argument("--noises", type=float, nargs="+", default=(1.0, 2.0, 4.0))
    ap.add_argument("--lights", type=int, default=12,
                    help="light directions (the default and random ones within 35 deg); draws cycle through them")
    ap.add_argument("--timing-runs", type=int, default=3)
    a = ap.parse_args()
    if a.draws:
        rows = run(a.part, tuple(a.size), a.noises, a.draws, a.lights)
        print(f"part {a.part}, {a.size[0]}x{a.size[1]}, {a.draws} noise draws per level over {a.lights} light(s); "
              "errors in um (x/y/z rig frame); bound: the image-noise part of the first-order covariance (the 2D "
              "fits at their KCR bound, propagated)")
        print("noise | circles (whole) | centre RMS x/y/z | centre bound x/y/z | radius RMS / bound | "
              "centre in 95% ell. all/whole/arcs | radius in +-2u all/whole/arcs | RMS z centre/radius | "
              "median u depth/radius | systematic share of u^2 depth | lines | line RMS x/y/z | "
              "line bound x/y/z | line in 95% | RMS z line | OpenCV n | OpenCV centre RMS | OpenCV radius RMS")
        for r in rows:
            print(f"{r['noise']:.0f} | {r['n_circles']} ({r['n_whole']}) | {fmt(r['centre_rms'])} | "
                  f"{fmt(r['centre_bound'])} | {r['radius_rms']:.1f} / {r['radius_bound']:.1f} | "
                  f"{r['centre_cov95']:.3f}/{r['centre_cov95_whole']:.3f}/{r['centre_cov95_arc']:.3f} | "
                  f"{r['radius_cov95']:.3f}/{r['radius_cov95_whole']:.3f}/{r['radius_cov95_arc']:.3f} | "
                  f"{r['centre_nrms']:.2f}/{r['radius_nrms']:.2f} | "
                  f"{r['u_depth']:.1f}/{r['u_radius']:.1f} | {r['sys_share']:.2f} | "
                  f"{r['n_lines']} | {fmt(r['line_rms'])} | {fmt(r['line_bound'])} | {r['line_cov95']:.3f} | "
                  f"{r['line_nrms']:.2f} | "
                  f"{r['cv_n']} | {fmt(r['cv_centre_rms'])} | {r['cv_radius_rms']:.1f}")
        for r in rows:
            if r["n_through"]:
                print(f"noise {r['noise']:.0f}: {r['n_through']} bottom rims glimpsed through their holes, left out "
                      f"above (registration does not take them; median centre error {r['through_median']:.0f} um)")
    if a.timing_runs:
        rig, pose, L, R = S.render(a.part, 2.0, 0, False, (2448, 2048))
        # The baseline side by side in the same run, interleaved (the machine
        # is shared): the two images' 2D chains one after the other.
        times = {True: [], False: []}
        # The forked path itself is timed, whatever the load (in use it forks
        # only with a CPU idle: vision.forked.MIN_IDLE_CPUS); the load is printed.
        forked_module.MIN_IDLE_CPUS = float("-inf")
        load0 = os.getloadavg()[0]
        for _ in range(a.timing_runs):
            for parallel in (False, True):
                t = time.perf_counter()
                measure_stereo(L, R, rig, parallel=parallel)
                times[parallel].append(time.perf_counter() - t)
        print(f"measure_stereo on a 2448x2048 pair ({a.part}): median {np.median(times[True]):.2f} s over "
              f"{a.timing_runs} runs, the right image's 2D chain in a forked child process "
              f"(partinspect.vision.forked; {forked_module.available_cpus()} CPUs); baseline in the same runs, both chains here "
              f"one after the other (parallel=False): {np.median(times[False]):.2f} s; 1-minute load average "
              f"{load0:.1f} before, {os.getloadavg()[0]:.1f} after")


if __name__ == "__main__":
    main()
