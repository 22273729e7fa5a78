"""The renderer's supersampling lattice: how finely it reads an edge's coverage of a pixel, by the edge's angle.

The renderer integrates a pixel that an edge crosses with the same rotated
``n x n`` lattice of rays in every pixel (:func:`partinspect.simulate.render.sample_pattern`).
Along a pixel axis its ``n**2`` rays lie in ``n**2`` distinct places
across the edge; along the lattice's generators, ``(1, n) / n**2`` (3.58 deg
off the axes for n = 16) and the diagonals, in far fewer, and the pixel's
coverage is read in coarse steps. A straight edge at such an angle meets
every row at a phase that slips slowly through those steps, so the error
is coherent along the edge: a wave of ``1 / |n m - round(n m)|`` rows for a
slope ``m`` near ``1 / n`` (63 rows at gen-019's 3.6 deg edge), one offset
along a 45 deg edge. No camera has it.

Printed per angle from a pixel axis: the coverage error of one pixel row
(RMS and largest, px) for an edge crossing it at every phase, beside the
baseline of rays with exact positions (``n**2`` evenly spaced across the
edge, what the lattice gives along an axis), and the widest gap between
the rays' places across the edge (the step in which the coverage is read).

    python3 benchmarks/bench_render_lattice.py [--samples 16]
"""

from __future__ import annotations

import argparse

import numpy as np

from partinspect.simulate.render import SAMPLES, sample_pattern

ANGLES = (0.0, 1.0, 2.0, 3.0, 3.58, 4.0, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0, 40.0, 44.0, 45.0)


def coverage_error(offsets, degrees, phases=2001):
    """Error of the rays' coverage of a pixel by a half-plane, px, at ``phases`` edge positions.

    The edge passes at ``x0`` from the pixel centre, ``degrees`` off the
    pixel's columns; the exact area left of it is ``x0 + 1/2``.
    """
    m = np.tan(np.deg2rad(degrees))
    x0 = np.linspace(-0.45, 0.45, phases)
    across = offsets[:, 0] - m * offsets[:, 1]
    return (across[None, :] < x0[:, None]).mean(axis=1) - (x0 + 0.5)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=SAMPLES, help=f"lattice size n (default {SAMPLES})")
    args = ap.parse_args(argv)
    offsets = sample_pattern(args.samples)
    n2 = len(offsets)
    ideal = np.column_stack([(np.arange(n2) + 0.5) / n2 - 0.5, np.zeros(n2)])
    print(f"rotated {args.samples} x {args.samples} lattice, {n2} rays; coverage error of one pixel row, px")
    print(f"{'angle, deg':>10}  {'widest gap':>10}  {'RMS':>7}  {'largest':>7}  {'baseline RMS':>12}")
    base = np.sqrt(np.mean(coverage_error(ideal, 0.0) ** 2))
    for deg in ANGLES:
        err = coverage_error(offsets, deg)
        across = np.sort(offsets[:, 0] - np.tan(np.deg2rad(deg)) * offsets[:, 1])
        print(f"{deg:10.2f}  {np.diff(across).max():10.4f}  {np.sqrt(np.mean(err ** 2)):7.4f}  {np.abs(err).max():7.4f}  "
              f"{base:12.4f}")


if __name__ == "__main__":
    main()
