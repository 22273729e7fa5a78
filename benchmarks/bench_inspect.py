"""Whole-run time of `inspect` on the sample parts, stage by stage, beside the OpenCV path.

For each sample part (examples/plate, examples/bracket) the bundled pair is
inspected as a user runs it, ``python -m partinspect PART IMAGES -o OUT
--quiet``, process start to exit, report included:

- once with an empty CAD model cache (the first run on a part number), then
- ``--runs`` times with the cache filled (every later run): the median
  whole-run time and each stage's median from report.json's ``timings``.

Beside it, in the same run, the OpenCV path on the same pair (read both
images, Canny + findContours + fitEllipse, epipolar matching,
triangulatePoints: ``bench_stereo.opencv_circles``), its median printed as
the ratio of the two, and ``measure_stereo`` alone on the pair (issue
target: under 0.5 s per 2448 x 2048 pair). The load average is printed
too: the chain runs its second process only when a CPU is idle.

    python3 benchmarks/bench_inspect.py [--runs 5] [--parts plate bracket]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# As the inspect command sets it (cli.py), before NumPy and OpenCV load their BLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))


def inspect_once(part_dir, out, cache):
    """Wall seconds of one whole run, and its report.json."""
    env = {**os.environ, "PARTINSPECT_CACHE": str(cache)}
    env.pop("SOURCE_DATE_EPOCH", None)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "partinspect", str(part_dir / "part.step"), str(part_dir / "images"),
                           "-o", str(out), "--quiet"], env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if done.returncode == 2:
        raise SystemExit(f"bench_inspect: {part_dir.name}: {done.stderr.strip()}")
    return seconds, json.loads((out / "report.json").read_text())


def opencv_path(part_dir, rig):
    from bench_stereo import opencv_circles

    left = cv2.imread(str(part_dir / "images" / "left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(part_dir / "images" / "right.png"), cv2.IMREAD_GRAYSCALE)
    return opencv_circles(left, right, rig)


def median_call(func, runs):
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        func()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_part(name, runs):
    from partinspect.vision.calibration import read_calibration
    from partinspect.vision.images import read_pair
    from partinspect.vision.stereo import measure_stereo

    part_dir = REPO / "examples" / name
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cold, _ = inspect_once(part_dir, tmp / "cold", tmp / "cache")
        warm, stages = [], {}
        for k in range(runs):
            seconds, report = inspect_once(part_dir, tmp / f"warm{k}", tmp / "cache")
            warm.append(seconds)
            for s in report["timings"]["stages"]:
                stages.setdefault(s["stage"], []).append(s["seconds"])
    rig = read_calibration(part_dir / "images")
    left, right, _ = read_pair(part_dir / "images", rig)
    measure_stereo(left, right, rig)  # loads the compiled kernels once, as a run does before its first pair
    return {
        "cold": cold,
        "warm": statistics.median(warm),
        "warm_range": (min(warm), max(warm)),
        "stages": {k: statistics.median(v) for k, v in stages.items()},
        "opencv": median_call(lambda: opencv_path(part_dir, rig), runs),
        "measure_stereo": median_call(lambda: measure_stereo(left, right, rig), runs),
        "size": f"{left.shape[1]}x{left.shape[0]}",
        "verdict": report["verdict"],
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--parts", nargs="+", default=["plate", "bracket"])
    args = ap.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    results = {name: bench_part(name, args.runs) for name in args.parts}
    print(f"\nwhole run, process start to exit (median of {args.runs}; target under 4 s)")
    print(f"{'part':8s} {'image':10s} {'first run':>10s} {'later runs':>11s} {'range':>13s} "
          f"{'OpenCV path':>12s} {'ratio':>6s} {'measure_stereo':>15s}")
    for name, r in results.items():
        lo, hi = r["warm_range"]
        print(f"{name:8s} {r['size']:10s} {r['cold']:9.2f}s {r['warm']:10.2f}s {lo:6.2f}-{hi:5.2f}s "
              f"{r['opencv']:11.3f}s {r['warm'] / r['opencv']:5.0f}x {r['measure_stereo']:14.3f}s")
    print("\nstages of the later runs (median seconds, report.json timings)")
    names = list(dict.fromkeys(k for r in results.values() for k in r["stages"]))
    print(f"{'stage':34s}" + "".join(f"{p:>10s}" for p in results))
    for k in names:
        print(f"{k:34s}" + "".join(f"{r['stages'].get(k, float('nan')):10.3f}" for r in results.values()))
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
