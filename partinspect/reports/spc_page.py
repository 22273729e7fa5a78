"""spc.html: the statistical process control page of a batch or a results database.

One self-contained, offline page: a table of every characteristic's
capability figures, then per characteristic an interactive run chart
(plotly.js, inlined once per page) of the measured values with each part's
+-U, the specification limits, the individuals chart's centre line and
control limits, and the points that complete a test for special causes,
above its moving-range chart (ranges of consecutive parts, their mean and
D4 limit). A characteristic measured in rational subgroups gets, under its run chart
(values and limits only), its X-bar chart (subgroup means, centre line,
control limits, tests for special causes) above its R chart (ranges,
R-bar, D3 and D4 limits).

Plotly rather than static SVG: a line engineer zooms into a drift, reads a
part's serial and U on hover and hides traces, which a page of hundreds of
points per chart needs; its 4.8 MB of script is paid once per page. The
page's scripts are allowed by their hashes only (Content-Security-Policy),
as report.html's, and every string from the database goes through jinja2's
autoescaping or, inside the charts' data, JSON with ``<`` escaped.
"""

import base64
import hashlib
import json
import math

from partinspect.reports.html import environment

_RULE_MARK = "#b3261e"


def _finite(v):
    return v is not None and isinstance(v, (int, float)) and math.isfinite(v)


def run_chart(c):
    """The plotly figure (as a dict: data, layout) of one characteristic's run chart.

    ``c``: one entry of :func:`partinspect.production.spc_report.spc_data`'s
    characteristics (serials, measured, U, limits, violations).
    """
    x = list(range(1, len(c["measured"]) + 1))
    hover = [f"{s}<br>{m:.4f} ± {u:.4f} {c['unit']}" if _finite(u) else f"{s}<br>{m:.4f} {c['unit']}"
             for s, m, u in zip(c["serials"], c["measured"], c["U_parts"])]
    data = [{
        "type": "scatter", "mode": "lines+markers", "name": "measured ± U", "x": x, "y": c["measured"],
        "text": hover, "hoverinfo": "text", "line": {"color": "#1d2330", "width": 1}, "marker": {"size": 5},
        "error_y": {"type": "data", "array": [u if _finite(u) else 0 for u in c["U_parts"]], "visible": True,
                    "color": "#8a94a6", "thickness": 1, "width": 2},
    }]
    subgrouped = c.get("chart") == "xbar-r"
    flagged = [] if subgrouped else sorted({i for idx in c["violations"].values() for i in idx})
    if flagged:
        rules = {i: ", ".join(str(r) for r, idx in sorted(c["violations"].items()) if i in idx) for i in flagged}
        data.append({"type": "scatter", "mode": "markers", "name": "test for special causes",
                     "x": [x[i] for i in flagged], "y": [c["measured"][i] for i in flagged],
                     "text": [f"{c['serials'][i]}: test(s) {rules[i]}" for i in flagged], "hoverinfo": "text",
                     "marker": {"symbol": "circle-open", "size": 13, "color": _RULE_MARK, "line": {"width": 2}}})
    rules = [(c["lower"], "LSL", "#b3261e", "solid"), (c["upper"], "USL", "#b3261e", "solid")]
    if not subgrouped:  # an X-bar chart's limits are for means, not for single values
        rules += [(c["center"], "centre", "#1b7a3a", "dot"), (c["lcl"], "LCL", "#9a6700", "dash"),
                  (c["ucl"], "UCL", "#9a6700", "dash")]
    lines = _rules(rules, len(x))
    layout = {"height": 300, "margin": {"l": 70, "r": 20, "t": 10, "b": 40}, "showlegend": True,
              "legend": {"orientation": "h", "y": -0.22, "font": {"size": 10}},
              "xaxis": {"title": {"text": "part (production order)"}, "zeroline": False,
                        # Serials under the points while they fit; beyond, numbers (the hover names the part).
                        **({"tickvals": x, "ticktext": c["serials"], "tickangle": -45} if len(x) <= 30 else {})},
              "yaxis": {"title": {"text": f"{c['type']} [{c['unit']}]"}, "zeroline": False, "exponentformat": "none"},
              "plot_bgcolor": "#fff", "paper_bgcolor": "#fff"}
    if c.get("moving_ranges"):
        data, layout = _with_moving_ranges(c, x, data, layout)
    return {"data": data + lines, "layout": layout}


def _with_moving_ranges(c, x, data, layout):
    """The individuals chart's moving-range (MR) chart under it (ISO 7870-2): |x_i - x_(i-1)|, its mean, D4 x mean.

    The moving range of part i is plotted at part i; ranges beyond the upper
    limit are marked, as the individuals' tests are.
    """
    u = c["unit"]
    mr, xs = c["moving_ranges"], x[1:]
    data = data + [{"type": "scatter", "mode": "lines+markers", "name": "moving range", "x": xs, "y": mr, "yaxis": "y2",
                    "text": [f"{a} to {b}<br>MR {r:.4f} {u}" for a, b, r in zip(c["serials"], c["serials"][1:], mr)],
                    "hoverinfo": "text", "line": {"color": "#44516b", "width": 1}, "marker": {"size": 4}}]
    out = [i for i, r in enumerate(mr) if _finite(c.get("mr_ucl")) and r > c["mr_ucl"]]
    if out:
        data.append({"type": "scatter", "mode": "markers", "name": "moving range beyond its limit", "yaxis": "y2",
                     "x": [xs[i] for i in out], "y": [mr[i] for i in out], "hoverinfo": "text",
                     "text": [f"{c['serials'][i + 1]}" for i in out],
                     "marker": {"symbol": "circle-open", "size": 13, "color": _RULE_MARK, "line": {"width": 2}}})
    data += _rules([(c.get("mr_mean"), "MR̄", "#1b7a3a", "dot"), (c.get("mr_ucl"), "MR UCL", "#9a6700", "dash")],
                   len(x), yaxis="y2")
    layout = {**layout, "height": 380, "legend": {**layout["legend"], "y": -0.18},
              "xaxis": {**layout["xaxis"], "anchor": "y2"},
              "yaxis": {**layout["yaxis"], "domain": [0.40, 1.0]},
              "yaxis2": {"title": {"text": f"moving range [{u}]"}, "domain": [0.0, 0.30], "zeroline": False,
                         "exponentformat": "none", "anchor": "x"}}
    return data, layout


def _rules(rules, count, yaxis=None):
    """Horizontal lines (value, name, colour, dash) across ``count`` points, as legend-named traces."""
    out = []
    for value, name, colour, dash in rules:
        if _finite(value):
            out.append({"type": "scatter", "mode": "lines", "name": f"{name} {value:.4f}", "x": [0.5, count + 0.5],
                        "y": [value, value], "hoverinfo": "name", "line": {"color": colour, "dash": dash, "width": 1},
                        **({"yaxis": yaxis} if yaxis else {})})
    return out


def xbar_r_chart(c):
    """The plotly figure of one characteristic's X-bar chart (top) and R chart (bottom), ISO 7870-2.

    ``c``: a characteristic of :func:`partinspect.production.spc_report.spc_data`
    charted in subgroups (``subgroup_means``, ``subgroup_ranges``, limits,
    ``violations`` by subgroup, ``range_violations``).
    """
    k = len(c["subgroup_means"])
    x = list(range(1, k + 1))
    u = c["unit"]
    names = [f"subgroup {lab} ({len(s)} parts: {', '.join(s[:3])}{', ...' if len(s) > 3 else ''})"
             for lab, s in zip(c["subgroup_labels"], c["subgroup_serials"])]
    data = [
        {"type": "scatter", "mode": "lines+markers", "name": "subgroup mean", "x": x, "y": c["subgroup_means"],
         "text": [f"{n}<br>mean {m:.4f} {u}" for n, m in zip(names, c["subgroup_means"])], "hoverinfo": "text",
         "line": {"color": "#1d2330", "width": 1}, "marker": {"size": 5}},
        {"type": "scatter", "mode": "lines+markers", "name": "subgroup range", "x": x, "y": c["subgroup_ranges"],
         "yaxis": "y2", "text": [f"{n}<br>range {r:.4f} {u}" for n, r in zip(names, c["subgroup_ranges"])],
         "hoverinfo": "text", "line": {"color": "#44516b", "width": 1}, "marker": {"size": 5}},
    ]
    flagged = sorted({i for idx in c["violations"].values() for i in idx})
    if flagged:
        rules = {i: ", ".join(str(r) for r, idx in sorted(c["violations"].items()) if i in idx) for i in flagged}
        data.append({"type": "scatter", "mode": "markers", "name": "test for special causes", "x": [x[i] for i in flagged],
                     "y": [c["subgroup_means"][i] for i in flagged], "hoverinfo": "text",
                     "text": [f"subgroup {c['subgroup_labels'][i]}: test(s) {rules[i]}" for i in flagged],
                     "marker": {"symbol": "circle-open", "size": 13, "color": _RULE_MARK, "line": {"width": 2}}})
    if c["range_violations"]:
        data.append({"type": "scatter", "mode": "markers", "name": "range beyond its limits", "yaxis": "y2",
                     "x": [x[i] for i in c["range_violations"]], "hoverinfo": "text",
                     "y": [c["subgroup_ranges"][i] for i in c["range_violations"]],
                     "text": [f"subgroup {c['subgroup_labels'][i]}" for i in c["range_violations"]],
                     "marker": {"symbol": "circle-open", "size": 13, "color": _RULE_MARK, "line": {"width": 2}}})
    data += _rules([(c["center"], "X̄ centre", "#1b7a3a", "dot"), (c["lcl"], "X̄ LCL", "#9a6700", "dash"),
                    (c["ucl"], "X̄ UCL", "#9a6700", "dash")], k)
    data += _rules([(c["r_mean"], "R̄", "#1b7a3a", "dot"), (c["r_lcl"] or None, "R LCL", "#9a6700", "dash"),
                    (c["r_ucl"], "R UCL", "#9a6700", "dash")], k, yaxis="y2")
    layout = {"height": 380, "margin": {"l": 70, "r": 20, "t": 10, "b": 40}, "showlegend": True,
              "legend": {"orientation": "h", "y": -0.18, "font": {"size": 10}},
              # The subgroups' axis under the R chart; the X-bar chart above shares it.
              "xaxis": {"title": {"text": f"subgroup of {c['subgroup_size']} (production order)"}, "zeroline": False,
                        "anchor": "y2",
                        **({"tickvals": x, "ticktext": c["subgroup_labels"], "tickangle": -45} if k <= 30 else {})},
              "yaxis": {"title": {"text": f"mean [{u}]"}, "domain": [0.40, 1.0], "zeroline": False,
                        "exponentformat": "none"},
              "yaxis2": {"title": {"text": f"range [{u}]"}, "domain": [0.0, 0.30], "zeroline": False,
                         "exponentformat": "none", "anchor": "x"},
              "plot_bgcolor": "#fff", "paper_bgcolor": "#fff"}
    return {"data": data, "layout": layout}


def _script_json(obj):
    # Inside <script>, "</" would end it early: JSON's \u003c keeps the value.
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")


def _hash(script):
    return "'sha256-" + base64.b64encode(hashlib.sha256(script.encode("utf-8")).digest()).decode() + "'"


def render_spc_html(data):
    """spc.html's text.

    Parameters
    ----------
    data : dict
        :func:`partinspect.production.spc_report.spc_data`'s result:
        ``title``, ``source``, ``created``, ``parts``, ``first``, ``last``,
        ``characteristics`` (each with its figures and series),
        ``not_capable`` and ``special_causes``.
    """
    import plotly.offline

    charts = [{"id": f"chart-{i}", **run_chart(c)} for i, c in enumerate(data["characteristics"]) if c["measured"]]
    charts += [{"id": f"xbar-{i}", **xbar_r_chart(c)} for i, c in enumerate(data["characteristics"])
               if c.get("chart") == "xbar-r"]
    plotly_js = plotly.offline.get_plotlyjs()
    draw = ("const CHARTS = " + _script_json(charts) + ";\n"
            "for (const c of CHARTS) {\n"
            "  Plotly.newPlot(c.id, c.data, c.layout, {responsive: true, displaylogo: false});\n"
            "}\n")
    return environment().get_template("spc.html.j2").render(
        d=data, plotly_js=plotly_js, draw=draw, script_hashes=f"{_hash(plotly_js)} {_hash(draw)}",
        charted={c["id"] for c in data["characteristics"] if c["measured"]},
    )
