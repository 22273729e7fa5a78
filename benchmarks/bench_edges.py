"""Speed and accuracy of the 2D chain on one 2448x2048 image of a plate with holes.

Prints the median wall time of each stage over several runs: noise
estimate, edge points, chaining, segmentation (line and ellipse fits), and
the total. Target: the whole 2D chain under 0.4 s on the project machine.
Beside it, in the same run and on the same image, OpenCV's obvious path
(Canny + findContours + fitEllipse / fitLine): its time, and for both the
RMS localisation error of edge points on the circular edges (distance to
the true circle; the drawn discs are known exactly) and the RMS errors of
the fitted circles' centres and radii.

Then the same stages on the rendered sample parts (plate and bracket, left
image of the default pair at noise 2), with the merging of pieces into
image features (``imagefeatures.image_features``) that ``inspect`` runs after
them: the whole 2D chain of one image as it is used.

    python3 benchmarks/bench_edges.py [--runs 5] [--no-parts]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from partinspect.vision.contours import chain_edges, segment_contours  # noqa: E402
from partinspect.vision.edges import edge_points  # noqa: E402
from partinspect.vision.noise import estimate_noise  # noqa: E402
from tests.vision.synthetic import Disc, Ellipse, rectangle, render  # noqa: E402


HOLES = [(600, 500, 120), (1850, 500, 120), (600, 1550, 120), (1850, 1550, 120), (1224, 1024, 260),
         (1224, 500, 60), (1224, 1550, 60)]


def discs():
    """(xc, yc, r) of the drawn holes, px."""
    return np.array([(x + 0.3 * k, y + 0.17 * k, r) for k, (x, y, r) in enumerate(HOLES)])


def plate_image(seed=0, noise=2.0):
    H, W = 2048, 2448
    shapes = [(rectangle(1224.3, 1024.6, 1900, 1500, 0.05), 190.0)]
    for xc, yc, r in discs():
        shapes.append((Disc(xc, yc, r), 45.0))
    shapes.append((Ellipse(900.4, 1024.2, 90, 50, 0.3), 45.0))
    return render(shapes, H, W, background=40.0, noise=noise, seed=seed, ss=16)


def circle_errors(xy, band=2.0):
    """Signed distances of points (N, 2) to the nearest drawn circle, those within ``band`` px of one."""
    D = discs()
    d = np.hypot(xy[:, None, 0] - D[None, :, 0], xy[:, None, 1] - D[None, :, 1]) - D[None, :, 2]
    e = d[np.arange(len(xy)), np.argmin(np.abs(d), axis=1)]
    return e[np.abs(e) < band]


def fit_errors(circles):
    """Centre and radius errors (px) of fitted circles (xc, yc, r) matched to the drawn ones."""
    ce, re = [], []
    for xc, yc, r in discs():
        if not len(circles):
            break
        c = np.asarray(circles)
        k = np.argmin(np.hypot(c[:, 0] - xc, c[:, 1] - yc) + np.abs(c[:, 2] - r))
        if np.hypot(c[k, 0] - xc, c[k, 1] - yc) < 5 and abs(c[k, 2] - r) < 5:
            ce.append(np.hypot(c[k, 0] - xc, c[k, 1] - yc))
            re.append(c[k, 2] - r)
    return np.array(ce), np.array(re)


def opencv_chain(img):
    """Canny (thresholds 40 / 100 on 8-bit grey) + findContours + fitEllipse or fitLine per contour."""
    e = cv2.Canny(img, 40, 100)
    cs, _ = cv2.findContours(e, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    ellipses, lines = [], []
    for c in cs:
        if len(c) < 20:
            continue
        pts = c.reshape(-1, 2).astype(np.float32)
        (x, y), (w, h), _ = cv2.fitEllipse(pts)
        if 0.8 < w / max(h, 1e-9) < 1.25 and max(w, h) < 1000:
            ellipses.append((x, y, (w + h) / 4))
        else:
            lines.append(cv2.fitLine(pts, cv2.DIST_L2, 0, 0.01, 0.01))
    return e, ellipses, lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--no-parts", action="store_true", help="skip the rendered sample parts")
    args = ap.parse_args(argv)
    from partinspect.vision._kernels import warm

    warm()  # the compiled fits loaded (or compiled) before any timing
    img = plate_image()
    stages, (s, ep, cs, segs) = timed_chain(img, args.runs)
    cv_times = []
    for _ in range(args.runs):
        t0 = time.perf_counter()
        canny, ellipses, lines = opencv_chain(img)
        cv_times.append(time.perf_counter() - t0)
    kinds = [sg.kind for sg in segs]
    print(f"image 2448x2048, noise estimate {s:.3f} grey levels, {len(ep)} edge points, "
          f"{len(cs)} contours, {kinds.count('line')} lines, {kinds.count('arc')} arcs")
    for k, v in stages.items():
        print(f"  {k:8s} median {np.median(v) * 1e3:8.1f} ms   (min {np.min(v) * 1e3:.1f} ms)")
    print(f"target: total < 400 ms -> {'met' if np.median(stages['total']) < 0.4 else 'NOT met'}")
    print(f"  OpenCV Canny + findContours + fitEllipse/fitLine: median {np.median(cv_times) * 1e3:.1f} ms")

    ours_pts = circle_errors(ep.xy)
    rows, cols = np.nonzero(canny)
    cv_pts = circle_errors(np.c_[cols, rows].astype(float))
    ours_c = [(sg.fit.params[0], sg.fit.params[1], 0.5 * (sg.fit.params[2] + sg.fit.params[3]))
              for sg in segs if sg.kind == "arc"]
    oc, orr = fit_errors(ours_c)
    cc, cr = fit_errors(ellipses)
    rms = lambda v: np.sqrt(np.mean(np.square(v))) if len(v) else float("nan")  # noqa: E731
    print("accuracy on the drawn circles (px)       partinspect   OpenCV")
    print(f"  edge points on circles: RMS error       {rms(ours_pts):10.4f}  {rms(cv_pts):8.4f}   "
          f"({len(ours_pts)} / {len(cv_pts)} points)")
    print(f"  circle centres: RMS error               {rms(oc):10.4f}  {rms(cc):8.4f}   ({len(oc)} / {len(cc)} of {len(HOLES)})")
    print(f"  circle radii: RMS error                 {rms(orr):10.4f}  {rms(cr):8.4f}")
    if not args.no_parts:
        sample_parts(args.runs)


def timed_chain(img, runs, camera=None):
    """Run the 2D chain ``runs`` times on ``img``; with ``camera`` (K, D) the
    image features too. Returns the wall times per stage (lists, s) and the
    last run's (noise, edge points, contours, segments[, features])."""
    from partinspect.vision.imagefeatures import image_features

    names = ["noise", "edges", "chain", "segment"] + (["features"] if camera else [])
    stages = {k: [] for k in names + ["total"]}
    for _ in range(runs):
        t = [time.perf_counter()]
        s = estimate_noise(img)
        t.append(time.perf_counter())
        ep = edge_points(img, 1.0, noise=s)
        t.append(time.perf_counter())
        cs = chain_edges(ep)
        t.append(time.perf_counter())
        out = (s, ep, cs, segment_contours(ep, cs))
        t.append(time.perf_counter())
        if camera:
            out = out + (image_features(ep, out[3], *camera),)
            t.append(time.perf_counter())
        for k, a, b in zip(names, t, t[1:]):
            stages[k].append(b - a)
        stages["total"].append(t[-1] - t[0])
    return stages, out


def sample_parts(runs):
    """The whole 2D chain, image features included, on the rendered sample parts."""
    import tests.vision.stereo_scenes as S

    for name in ("plate", "bracket"):
        rig, _, img, _ = S.render(name, 2.0, 0, False, (2448, 2048))
        stages, (_, _, _, segs, feats) = timed_chain(img, runs, (rig.K1, rig.D1))
        print(f"rendered {name}, left image 2448x2048: {len(segs)} segments, {len(feats)} image features; "
              f"medians of {runs}: " + ", ".join(f"{k} {np.median(v) * 1e3:.0f} ms" for k, v in stages.items()))


if __name__ == "__main__":
    main()
