"""Baseline for bench_report.py: the report's two plots as matplotlib drew them.

``residual_figure`` and ``sigma_figure`` are taken from
``partinspect/reports/figures.py`` as it was at commit 634b1d5, before they
were written directly as SVG (``partinspect/reports/svgplot.py``): the module
is read from git history and loaded under another name, so the benchmark
measures exactly the code that was replaced without a copy of it in the tree.
Needs git (a clone with that commit) and matplotlib; production code does
not import it.
"""

import importlib.util
import subprocess
import sys
from pathlib import Path

BASELINE_COMMIT = "634b1d5"
_REPO = Path(__file__).resolve().parents[1]


def _load():
    try:
        source = subprocess.run(["git", "show", f"{BASELINE_COMMIT}:partinspect/reports/figures.py"], cwd=_REPO,
                                check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        raise SystemExit(f"mpl_baseline: cannot read the baseline from git commit {BASELINE_COMMIT} ({e}); "
                         "run the benchmark in a full clone") from None
    spec = importlib.util.spec_from_loader("figures_matplotlib_baseline", loader=None)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    exec(compile(source, f"{BASELINE_COMMIT}:partinspect/reports/figures.py", "exec"), module.__dict__)
    return module


_baseline = _load()
residual_figure = _baseline.residual_figure
sigma_figure = _baseline.sigma_figure
