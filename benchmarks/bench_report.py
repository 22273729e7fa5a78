"""The HTML report's figures: drawn as SVG text against matplotlib, on a real run's data.

The bundled part is inspected once (``--part plate`` by default) and the
data handed to the report are kept. Then, beside the baseline measured in
the same run (the matplotlib versions of the two plots, read from git
history by ``benchmarks/mpl_baseline.py``), it times:

- ``residual_figure`` and ``sigma_figure`` alone, warm (median of runs);
- ``build_figures`` and ``render_html`` whole, warm;
- ``build_figures`` cold, in a fresh process as ``inspect`` pays it once a
  run: imports (matplotlib's for the baseline) and first draw included;

and prints the size of each plot's SVG. Usage::

    python3 benchmarks/bench_report.py [--part plate|bracket] [--runs 5]

About 20 s for the inspection, then a few seconds plus ``--runs`` fresh
processes of a second or two each.
"""

from __future__ import annotations

import argparse
import base64
import pickle
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def run_data(part):
    """(report, figures) of one inspection of ``examples/PART``, caught where the HTML report is rendered."""
    import partinspect.reports.html as html
    from partinspect.pipeline import run_inspection

    got = {}
    render = html.render_html

    def catch(report, figures=None):
        got["report"], got["figures"] = report, figures
        return render(report, figures)

    html.render_html = catch
    try:
        with tempfile.TemporaryDirectory() as out:
            run_inspection(ROOT / "examples" / part / "part.step", ROOT / "examples" / part / "images", out=out)
    finally:
        html.render_html = render
    if not got.get("figures"):
        raise SystemExit("the run handed no figure data to the report")
    return got["report"], got["figures"]


def use_baseline(on):
    """Swap matplotlib's residual and sigma figures into partinspect.reports.figures (or back)."""
    import mpl_baseline

    from partinspect.reports import figures as F

    if not hasattr(use_baseline, "svg"):
        use_baseline.svg = (F.residual_figure, F.sigma_figure)
    mpl = (mpl_baseline.residual_figure, mpl_baseline.sigma_figure)
    F.residual_figure, F.sigma_figure = mpl if on else use_baseline.svg


def median_time(fn, runs):
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def svg_bytes(fig):
    m = re.search(r'src="data:image/svg\+xml;base64,([A-Za-z0-9+/=]+)"', fig.body or "")
    return len(base64.b64decode(m.group(1))) if m else 0


def child(path, variant):
    """In a fresh process: one cold build_figures, printed in seconds."""
    t0 = time.perf_counter()
    with open(path, "rb") as fh:
        report, figures = pickle.load(fh)
    t_load = time.perf_counter() - t0
    if variant == "matplotlib":
        use_baseline(True)
    from partinspect.reports.figures import build_figures

    t0 = time.perf_counter()
    figs = build_figures(figures, report)
    assert all(f.body for f in figs), [f.note for f in figs if not f.body]
    print(f"{time.perf_counter() - t0:.6f} {t_load:.6f}")


def cold_times(path, variant, runs):
    out = []
    for _ in range(runs):
        r = subprocess.run([sys.executable, __file__, "--child", str(path), variant], capture_output=True, text=True,
                           check=True)
        out.append(float(r.stdout.split()[0]))
    return statistics.median(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="plate")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(*args.child)
    import mpl_baseline

    from partinspect.reports import figures as F
    from partinspect.reports.html import render_html

    t0 = time.perf_counter()
    report, figures = run_data(args.part)
    print(f"inspected examples/{args.part} in {time.perf_counter() - t0:.1f} s; {len(figures['residuals'])} fits, "
          f"{sum(len(p['points']) for p in figures['points3d'])} 3D points; median of {args.runs} runs below")
    pose = report["registration"]["part_to_camera"]
    rows = [
        ("residual_figure", lambda: F.residual_figure(figures), lambda: mpl_baseline.residual_figure(figures)),
        ("sigma_figure", lambda: F.sigma_figure(figures, pose), lambda: mpl_baseline.sigma_figure(figures, pose)),
    ]
    print(f"{'':34s} {'SVG text':>10s} {'matplotlib':>11s} {'ratio':>7s}")
    for name, new, old in rows:
        old()  # matplotlib's first draw (font cache, imports) is in the cold row below, not here
        a, b = median_time(new, args.runs), median_time(old, args.runs)
        print(f"{name + ' (warm)':34s} {a:9.4f}s {b:10.4f}s {b / a:6.0f}x")
        print(f"{name + ' SVG size':34s} {svg_bytes(new()) / 1e3:8.1f}kB {svg_bytes(old()) / 1e3:9.1f}kB")
    for name, fn in (("build_figures (warm)", lambda: F.build_figures(figures, report)),
                     ("render_html (warm)", lambda: render_html(report, figures))):
        a = median_time(fn, args.runs)
        use_baseline(True)
        try:
            b = median_time(fn, args.runs)
        finally:
            use_baseline(False)
        print(f"{name:34s} {a:9.4f}s {b:10.4f}s {b / a:6.1f}x")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "data.pkl"
        with open(path, "wb") as fh:
            pickle.dump((report, figures), fh)
        a, b = cold_times(path, "svg", args.runs), cold_times(path, "matplotlib", args.runs)
    print(f"{'build_figures (cold, fresh process)':34s} {a:9.4f}s {b:10.4f}s {b / a:6.1f}x")


if __name__ == "__main__":
    main()
