"""report.html: one self-contained page (inline CSS, no network), A4-printable.

Everything that comes from user files (names, paths, ids, labels) goes
through jinja2's autoescaping; the few HTML fragments made in Python
(:func:`tolerance_bar`, the figures) contain numbers only or escape their
strings themselves. A Content-Security-Policy in the page forbids every
fetch and allows only the report's own script (by its hash), so even a
string that escaped escaping could neither run nor call home.

Order of the page: verdict and counts, inputs with their SHA-256,
registration, the characteristics (failing first, then inconclusive, then
passing; report order within each group), the figures
(:mod:`partinspect.reports.figures`), the features. Values are in the
report's units: mm, and degrees for angles (``unit`` of a characteristic,
converted from radians by ``Evaluation.to_dict``).
"""

import base64
import dataclasses
import datetime as _dt
import hashlib
import math
from importlib import resources

from markupsafe import Markup, escape

_ORDER = {"fail": 0, "inconclusive": 1, "pass": 2}
_INK = {"pass": "#1b7a3a", "fail": "#b3261e", "inconclusive": "#9a6700"}


def _num(x, digits=4):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.{digits}f}"


def _signed(x, digits=4):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:+.{digits}f}".replace("-", "−")


def _vec(v, digits=3):
    return "–" if v is None else "(" + ", ".join(f"{x:.{digits}f}" for x in v) + ")"


def environment():
    """The report templates' jinja2 environment, autoescaping HTML (report contents are never trusted)."""
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("partinspect.reports", "templates"),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["num"] = _num
    env.filters["signed"] = _signed
    env.filters["vec"] = _vec
    return env


def sort_characteristics(chars):
    """Failing first, then inconclusive, then passing; the report's order within each group."""
    return sorted(chars, key=lambda c: _ORDER.get(c.get("decision"), 1))


def _finite(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def tolerance_bar(c, width=150, height=22):
    """A small inline SVG: the tolerance zone, the nominal, and measured +- U, coloured by decision.

    Numbers only go into it (no user text), so it is returned as Markup.
    """
    lo, hi = c.get("lower_limit"), c.get("upper_limit")
    nom, m, U = c.get("nominal"), c.get("measured"), c.get("expanded_uncertainty")
    lo = lo if _finite(lo) else None
    hi = hi if _finite(hi) else None
    nom = nom if _finite(nom) else None
    m = m if _finite(m) else None
    U = U if _finite(U) and U >= 0 else (0.0 if m is not None else None)
    vals = [v for v in (lo, hi, nom) if v is not None]
    if m is not None:
        vals += [m - U, m + U]
    if not vals:
        return Markup("")
    a, b = min(vals), max(vals)
    span = b - a
    if span <= 0:
        span = max(abs(a) * 0.01, 1e-6)
        a, b = a - span / 2, b + span / 2
    a, b = a - 0.12 * span, b + 0.12 * span
    pad = 3.0

    def x(v):
        return pad + (v - a) / (b - a) * (width - 2 * pad)

    mid = height / 2
    dec = c.get("decision", "inconclusive")
    ink = _INK.get(dec, "#5b6474")
    parts = [f'<svg class="tolbar" width="{width}" height="{height}" viewBox="0 0 {width} {height}" '
             'xmlns="http://www.w3.org/2000/svg" role="img">']
    title = []
    if lo is not None or hi is not None:
        x0 = x(lo) if lo is not None else 0.0
        x1 = x(hi) if hi is not None else float(width)
        parts.append(f'<rect x="{x0:.1f}" y="3" width="{max(x1 - x0, 0.5):.1f}" height="{height - 6}" fill="#e1f0e5"/>')
        for v in (lo, hi):
            if v is not None:
                parts.append(f'<line x1="{x(v):.1f}" x2="{x(v):.1f}" y1="2" y2="{height - 2}" stroke="#1b7a3a" stroke-width="1.2"/>')
        title.append(f"tolerance zone [{_num(lo)}, {_num(hi)}]")
    if nom is not None:
        parts.append(f'<line x1="{x(nom):.1f}" x2="{x(nom):.1f}" y1="4" y2="{height - 4}" stroke="#5b6474" '
                     'stroke-width="0.8" stroke-dasharray="2 2"/>')
        title.append(f"nominal {_num(nom)}")
    if m is not None:
        x0, x1, xm = x(m - U), x(m + U), x(m)
        parts.append(f'<line x1="{x0:.1f}" x2="{x1:.1f}" y1="{mid}" y2="{mid}" stroke="{ink}" stroke-width="2"/>')
        for xe in (x0, x1):
            parts.append(f'<line x1="{xe:.1f}" x2="{xe:.1f}" y1="{mid - 4}" y2="{mid + 4}" stroke="{ink}" stroke-width="1.5"/>')
        parts.append(f'<circle cx="{xm:.1f}" cy="{mid}" r="3.2" fill="{ink}"/>')
        title.append(f"measured {_num(m)} ± {_num(U)} (U, k = 2)")
    else:
        parts.append(f'<text x="{width / 2:.0f}" y="{mid + 3.5:.1f}" text-anchor="middle" font-size="10" '
                     'fill="#5b6474">not measured</text>')
    parts.insert(1, f"<title>{escape('; '.join(title))}</title>")
    parts.append("</svg>")
    return Markup("".join(parts))


def _when(created):
    """'YYYY-MM-DD hh:mm:ss UTC+hh:mm' from an ISO timestamp; the text as given if it is not one."""
    if not created:
        return "–"
    try:
        t = _dt.datetime.fromisoformat(str(created))
    except ValueError:
        return str(created)
    tz = t.strftime("%z")
    tz = f" UTC{tz[:3]}:{tz[3:]}" if tz else ""
    return t.strftime("%Y-%m-%d %H:%M:%S") + tz


def _sigmas(cov):
    try:
        return [math.sqrt(max(float(cov[i][i]), 0.0)) for i in range(3)]
    except (TypeError, IndexError, ValueError):
        return None


def feature_rows(report):
    """The features table: one dict of display strings per feature, with its worst decision."""
    worst = {}
    for c in report.get("characteristics", []):
        for fid in c.get("features") or [c.get("feature")]:
            d = c.get("decision")
            if fid is not None and _ORDER.get(d, 1) < _ORDER.get(worst.get(fid), 3):
                worst[fid] = d
    rows = []
    for f in report.get("features", []):
        nom, mea = f.get("nominal") or {}, f.get("measured")
        if f.get("kind") == "line":
            nominal = f"{_vec(nom.get('start'))} → {_vec(nom.get('end'))}"
        else:
            nominal = f"centre {_vec(nom.get('center'))}, r {_num(nom.get('radius'))}"
        measured = sigma = ""
        if mea:
            s = _sigmas(mea.get("covariance"))
            if f.get("kind") == "line":
                measured = f"{_vec(mea.get('start'))} → {_vec(mea.get('end'))}"
                sigma = f"point σ {_vec(s, 4)}" if s else ""
            else:
                measured = f"centre {_vec(mea.get('center'))}, r {_num(mea.get('radius'))}"
                if _finite(mea.get("radius")) and _finite(nom.get("radius")):
                    measured += f" ({_signed(mea['radius'] - nom['radius'])})"
                sigma = ", ".join(
                    t for t in (f"centre σ {_vec(s, 4)}" if s else "",
                                f"σr {_num(mea.get('radius_std'))}" if _finite(mea.get("radius_std")) else "") if t
                )
        status = f.get("status") or ("measured" if mea else "not measured")
        rows.append({
            "id": f.get("id", ""), "kind": f.get("kind", ""), "nominal": nominal, "measured": measured,
            "sigma": sigma, "status": status, "reason": f.get("reason") or "", "decision": worst.get(f.get("id")),
            "edge_break": _edge_break_text(f.get("edge_break")) if mea else "",
        })
    return rows


def _edge_break_text(e):
    """One line saying where a feature's edge was taken on its broken edge (report.json's ``"edge_break"``)."""
    if not isinstance(e, dict):
        return ""
    px = "; ".join(f"{side} {_num(r[0], 2)} to {_num(r[1], 2)} px" for side, r in zip(("left", "right"), e.get("offset_px") or ())
                   if isinstance(r, (list, tuple)) and len(r) == 2 and all(_finite(x) for x in r))
    where = ""
    if _finite(e.get("offset")):
        towards = e.get("towards_face") or "the face"
        where = f"step predicted {_signed(e['offset'])} mm from the sharp edge towards {towards}" + (f" ({px})" if px else "")
        if _finite(e.get("band_place")):
            where += f", band place {_num(e['band_place'], 2)} ± {_num(e.get('band_place_standard_uncertainty'), 2)}"
    u = f"Type B {_num(e.get('standard_uncertainty'))} mm per point"
    if e.get("measured_at") == "predicted band place":
        band = e.get("band_standard_uncertainty")
        return (f"edge break: moved onto the sharp edge by its predicted band place; {where}; {u}"
                + (f" (the whole band's {_num(band)})" if _finite(band) else ""))
    return "; ".join(t for t in (f"edge break: measured at the apparent edge, the band carried as {u}", where,
                                 e.get("reason") or "") if t)


def _vec3(v):
    try:
        out = [float(v[i]) for i in range(3)]
    except (TypeError, IndexError, ValueError):
        return None
    return out if all(math.isfinite(x) for x in out) else None


def _datum_reference(ref):
    """Display values of registration["datum_reference"]: its source, each datum's fitted features."""
    if not isinstance(ref, dict):
        return None
    frame = [f"{d.get('datum')}: {', '.join(d.get('fitted') or []) or 'none measured'}"
             f" (of {len(d.get('features') or [])})" for d in ref.get("frame") or [] if isinstance(d, dict)]
    return {"source": ref.get("source"), "applied": bool(ref.get("applied")), "reason": ref.get("reason"),
            "frame": frame}


def registration_summary(reg):
    """Display values of report["registration"] (None stays None)."""
    if not reg:
        return None
    out = {"rms": reg.get("rms"), "weighted_rms": reg.get("weighted_rms"), "chi2": reg.get("chi2"),
           "dof": reg.get("dof"), "datums": list(reg.get("datums") or []),
           "outliers": [o for o in reg.get("outliers") or [] if isinstance(o, dict)], "translation": None,
           "rotation_deg": None, "axis": None, "translation_std": _vec3(reg.get("translation_std")),
           "rotation_std_deg": _vec3(reg.get("rotation_std_deg")),
           "datum_reference": _datum_reference(reg.get("datum_reference")),
           "pose_covariance_scale": reg.get("pose_covariance_scale")}
    T = reg.get("part_to_camera")
    try:
        R = [[float(T[i][j]) for j in range(3)] for i in range(3)]
        out["translation"] = [float(T[i][3]) for i in range(3)]
        c = max(-1.0, min(1.0, (R[0][0] + R[1][1] + R[2][2] - 1) / 2))
        out["rotation_deg"] = math.degrees(math.acos(c))
        ax = [R[2][1] - R[1][2], R[0][2] - R[2][0], R[1][0] - R[0][1]]
        n = math.sqrt(sum(v * v for v in ax))
        out["axis"] = [v / n for v in ax] if n > 1e-12 else None
    except (TypeError, IndexError, ValueError):
        pass
    for k in ("rms", "weighted_rms", "chi2", "dof", "pose_covariance_scale"):
        if not _finite(out[k]):
            out[k] = None
    return out


def _script():
    """The page's one script and its CSP hash."""
    text = resources.files("partinspect.reports").joinpath("templates/_report.js").read_text(encoding="utf-8")
    digest = base64.b64encode(hashlib.sha256(text.encode("utf-8")).digest()).decode("ascii")
    return text, Markup(f"'sha256-{digest}'")


def _summary(report):
    s = dict(report.get("summary") or {})
    chars = report.get("characteristics", [])
    for d in ("pass", "fail", "inconclusive"):
        s.setdefault(d, sum(c.get("decision") == d for c in chars))
    s.setdefault("characteristics", len(chars))
    s.setdefault("features", len(report.get("features", [])))
    s.setdefault("features_measured", sum(f.get("measured") is not None for f in report.get("features", [])))
    return s


def render_html(report, figures=None):
    """The report.html text for a report.json dict.

    ``figures`` is the optional dict of run data described in
    :func:`partinspect.reports.figures.build_figures`; without it the page has
    no figures section, and with it every figure whose data is missing is
    replaced by a one-line note.
    """
    from partinspect.reports.figures import build_figures, scene_json

    figs = build_figures(figures, report) if figures else []
    # The bodies are HTML made (and escaped where needed) by figures.py: trusted.
    figs = [dataclasses.replace(f, body=Markup(f.body)) if f.body else f for f in figs]
    scene = next((f.scene for f in figs if f.scene), None)
    script, script_hash = _script()
    return environment().get_template("report.html.j2").render(
        r=report,
        summary=_summary(report),
        when=_when(report.get("created")),
        characteristics=sort_characteristics(report.get("characteristics", [])),
        bar=tolerance_bar,
        features=feature_rows(report),
        registration=registration_summary(report.get("registration")),
        figures=figs,
        scene_json=Markup(scene_json(scene)) if scene else None,
        script=Markup(script),
        script_hash=script_hash,
    )
