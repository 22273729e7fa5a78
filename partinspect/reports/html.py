"""report.html: one self-contained page (inline CSS, no network), A4-printable.

Everything that comes from user files (names, paths, ids) goes through
jinja2's autoescaping.
"""

import math

_ORDER = {"fail": 0, "inconclusive": 1, "pass": 2}


def _num(x, digits=4):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.{digits}f}"


def _vec(v, digits=3):
    return "–" if v is None else "(" + ", ".join(f"{x:.{digits}f}" for x in v) + ")"


def _environment():
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("partinspect.reports", "templates"),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["num"] = _num
    env.filters["vec"] = _vec
    return env


def render_html(report):
    """The report.html text for a report.json dict."""
    chars = sorted(report["characteristics"], key=lambda c: (_ORDER.get(c["decision"], 1), c["id"]))
    return _environment().get_template("report.html.j2").render(r=report, characteristics=chars)
