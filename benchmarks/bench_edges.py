"""Speed of the 2D chain on one 2448x2048 image of a plate with holes.

Prints the median wall time of each stage over several runs: noise
estimate, edge points, chaining, segmentation (line and ellipse fits), and
the total. Target: the whole 2D chain under 0.4 s on the project machine.

    python3 benchmarks/bench_edges.py [--runs 5]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from partinspect.vision.contours import chain_edges, segment_contours  # noqa: E402
from partinspect.vision.edges import edge_points  # noqa: E402
from partinspect.vision.noise import estimate_noise  # noqa: E402
from tests.vision.synthetic import Disc, Ellipse, rectangle, render  # noqa: E402


def plate_image(seed=0, noise=2.0):
    H, W = 2048, 2448
    shapes = [(rectangle(1224.3, 1024.6, 1900, 1500, 0.05), 190.0)]
    for k, (x, y, r) in enumerate([(600, 500, 120), (1850, 500, 120), (600, 1550, 120),
                                   (1850, 1550, 120), (1224, 1024, 260), (1224, 500, 60),
                                   (1224, 1550, 60)]):
        shapes.append((Disc(x + 0.3 * k, y + 0.17 * k, r), 45.0))
    shapes.append((Ellipse(900.4, 1024.2, 90, 50, 0.3), 45.0))
    return render(shapes, H, W, background=40.0, noise=noise, seed=seed, ss=16)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args(argv)
    img = plate_image()
    stages = {"noise": [], "edges": [], "chain": [], "segment": [], "total": []}
    for _ in range(args.runs):
        t0 = time.perf_counter()
        s = estimate_noise(img)
        t1 = time.perf_counter()
        ep = edge_points(img, 1.0, noise=s)
        t2 = time.perf_counter()
        cs = chain_edges(ep)
        t3 = time.perf_counter()
        segs = segment_contours(ep, cs)
        t4 = time.perf_counter()
        for k, v in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0)):
            stages[k].append(v)
    kinds = [sg.kind for sg in segs]
    print(f"image 2448x2048, noise estimate {s:.3f} grey levels, {len(ep)} edge points, "
          f"{len(cs)} contours, {kinds.count('line')} lines, {kinds.count('arc')} arcs")
    for k, v in stages.items():
        print(f"  {k:8s} median {np.median(v) * 1e3:8.1f} ms   (min {np.min(v) * 1e3:.1f} ms)")
    print(f"target: total < 400 ms -> {'met' if np.median(stages['total']) < 0.4 else 'NOT met'}")


if __name__ == "__main__":
    main()
