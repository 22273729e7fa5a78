"""Accuracy of edge points and of line / ellipse fits over many noise draws.

Prints, for edge points on real synthetic images (area-integrated pixels,
Gaussian blur 0.6 px, noise 2 grey levels, contrast 80, 8-bit):
- the RMS fit-parameter errors against the KCR bound for the edge-point
  noise actually present (its measured spread), both the bound for
  independent point errors and the Cramer-Rao bound for the correlation
  along the edge that the Gaussian filter creates;
- predicted standard uncertainty (from the fit covariance) over the
  empirical spread of the estimates; residual means.

    python3 benchmarks/bench_fitting.py [--draws 200]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.vision.synthetic import ellipse_draws, line_draws  # noqa: E402


def report(name, labels, errs, preds, kcr_ind, kcr_cor, resid_mean, s_emp):
    rms = np.sqrt((errs ** 2).mean(axis=0))
    print(f"{name}: {len(errs)} draws, edge-point normal error spread {s_emp:.4f} px, "
          f"mean residual {resid_mean.mean():+.2e} px")
    print(f"  {'param':6s} {'RMS err':>10s} {'emp std':>10s} {'pred std':>10s} {'pred/emp':>9s} "
          f"{'RMS/KCRcorr':>12s} {'RMS/KCRind':>11s}")
    for k, lab in enumerate(labels):
        print(f"  {lab:6s} {rms[k]:10.3e} {errs[:, k].std():10.3e} {preds[:, k].mean():10.3e} "
              f"{preds[:, k].mean() / errs[:, k].std():9.3f} {rms[k] / kcr_cor[k]:12.3f} {rms[k] / kcr_ind[k]:11.3f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200)
    args = ap.parse_args(argv)
    e, p, ki, kc, rm, s = line_draws(args.draws)
    report("line (angle 0.3 rad, ~100 points)", ["alpha", "C"], e, p, ki, kc, rm, s)
    e, p, ki, kc, rm, s, conv = ellipse_draws(args.draws)
    report(f"ellipse (a 62, b 38 px, closed; all converged: {conv})", ["xc", "yc", "a", "b", "theta"],
           e, p, ki, kc, rm, s)


if __name__ == "__main__":
    main()
