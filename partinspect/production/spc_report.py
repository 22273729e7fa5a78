"""The SPC page and its CSV exports, from the results database.

Reads every inspected part's characteristics (:func:`.database.measurements`),
computes each characteristic's figures (:mod:`.spc`) and writes, together
and atomically, ``spc.html`` (:mod:`partinspect.reports.spc_page`),
``spc.csv`` (one row per characteristic) and ``measurements.csv`` (one row
per part and characteristic, for users' own tools: :mod:`.export`, which
``inspect spc DB --export FILE.csv|FILE.parquet`` writes alone).
"""

from __future__ import annotations

import csv
import io
import re
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from partinspect import __version__
from partinspect.atomic import prepare_output_dir, write_files_atomic
from partinspect.production import export, spc

CONFIDENCE = 0.95
SUMMARY_COLUMNS = ("characteristic", "type", "unit", "n", "chart", "subgroup_size", "subgroups", "lower", "upper",
                   "mean", "s", "sigma_within", "cp", "cpk", "pp", "ppk", "U", "q_mp", "capable_measurement", "tests",
                   "range_out", "fails", "inconclusive")


def _natural(text):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text)]


def characteristic_series(rows):
    """Rows grouped by part number (the STEP file's content) and characteristic, in production order.

    Returns
    -------
    dict of str to list of dict
        The characteristic's id (prefixed by its STEP file, ``folder/part.step:``,
        when the rows hold more than one part number) -> its rows.
    """
    models = {r["step_sha256"]: r["step_file"] for r in rows}
    out = {}
    for r in rows:
        key = r["characteristic"]
        if len(models) > 1:
            f = Path(models[r["step_sha256"]] or "?")
            key = f"{f.parent.name}/{f.name}: {key}"
        out.setdefault(key, []).append(r)
    return {k: out[k] for k in sorted(out, key=_natural)}


def with_subgroups(rows, size=None):
    """The rows with each part's subgroup: the stored one, or (``size``) consecutive parts in groups of ``size``.

    Parameters
    ----------
    rows : list of dict
        :func:`.database.measurements` rows, in production order.
    size : int, optional
        1: no subgroups (individuals charts, whatever is stored); 2 to 10:
        the parts, in production order, in consecutive groups of ``size``
        (a last incomplete group is left out of the X-bar/R chart).
    """
    if size is None:
        return rows
    order = {}
    for r in rows:
        order.setdefault(r["serial"], len(order))
    return [{**r, "subgroup": None if size == 1 else str(order[r["serial"]] // size + 1)} for r in rows]


def summarise(cid, rows, confidence=CONFIDENCE):
    """One characteristic's SPC figures and chart series from its rows (production order).

    Its parts are charted in subgroups (X-bar/R) when every measured one has
    a subgroup, else one by one (individuals).
    """
    last = rows[-1]
    measured = [r for r in rows if r["measured"] is not None]
    x = np.array([r["measured"] for r in measured], float)
    u = np.array([np.nan if r["standard_uncertainty"] is None else r["standard_uncertainty"] for r in measured])
    lower, upper = last["lower_limit"], last["upper_limit"]
    labels = [r.get("subgroup") for r in measured]
    labels = labels if labels and all(k is not None for k in labels) else None
    s = spc.characteristic_summary(x, lower, upper, u=u[np.isfinite(u)], confidence=confidence, subgroups=labels)
    lim = s.pop("limits") or {}
    violations = {r: [int(i) for i in idx] for r, idx in s.pop("violations").items() if len(idx)}
    out = {
        "id": cid, "type": last["type"], "unit": last["unit"] or "", "lower": lower, "upper": upper,
        **{k: _plain(v) for k, v in s.items() if not k.startswith(("subgroup", "range_"))},
        "center": lim.get("center"), "lcl": lim.get("lcl"), "ucl": lim.get("ucl"),
        "violations": violations, "rules": sorted(violations),
        "fails": sum(r["decision"] == "fail" for r in rows),
        "inconclusive": sum(r["decision"] == "inconclusive" for r in rows),
        "not_measured": len(rows) - len(measured),
        "serials": [r["serial"] for r in measured], "measured": x.tolist(),
        "U_parts": [None if r["expanded_uncertainty"] is None else r["expanded_uncertainty"] for r in measured],
        "subgroup_size": s.get("subgroup_size"), "range_out": None,
    }
    if s["chart"] != "xbar-r" and len(x) > 1:
        out.update(moving_ranges=np.abs(np.diff(x)).tolist(), mr_mean=lim.get("mr_mean"), mr_ucl=lim.get("mr_ucl"))
    if s["chart"] == "xbar-r":
        out.update(
            subgroups=len(s["subgroup_index"]), subgroups_left_out=s["subgroups_left_out"],
            subgroup_labels=[str(labels[g[0]]) for g in s["subgroup_index"]],
            subgroup_serials=[[measured[i]["serial"] for i in g] for g in s["subgroup_index"]],
            subgroup_means=s["subgroup_means"].tolist(), subgroup_ranges=s["subgroup_ranges"].tolist(),
            range_violations=[int(i) for i in s["range_violations"]], range_out=len(s["range_violations"]),
            r_mean=lim["r_mean"], r_lcl=lim["r_lcl"], r_ucl=lim["r_ucl"])
    return out


def _plain(v):
    if isinstance(v, tuple):
        return tuple(float(a) for a in v)
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


def spc_data(rows, *, title, source, confidence=CONFIDENCE, subgroup_size=None):
    """Everything the SPC page shows, from :func:`.database.measurements` rows (see :func:`with_subgroups`)."""
    rows = with_subgroups(rows, subgroup_size)
    chars = [summarise(cid, rs, confidence) for cid, rs in characteristic_series(rows).items()]
    times = [r["measured_at"] for r in rows]
    return {
        "title": title, "source": source, "confidence": confidence, "software_version": __version__,
        "created": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "parts": len({r["serial"] for r in rows}),
        "first": str(min(times)) if times else None, "last": str(max(times)) if times else None,
        "characteristics": chars, "rules": spc.RULES, "q_limit": spc.Q_LIMIT,
        "not_capable": [c for c in chars if c["capable_measurement"] is False],
        "special_causes": [c for c in chars if c["rules"] or c.get("range_violations")],
        "subgrouped": any(c["chart"] == "xbar-r" for c in chars),
    }


def _csv(columns, rows, cell=None):
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([(cell or _cell)(r.get(c)) for c in columns])
    return buf.getvalue().encode("utf-8")


def _cell(v):
    """A computed figure: 12 significant digits, without the binary noise of the arithmetic."""
    if isinstance(v, float):
        return f"{v:.12g}"
    return "" if v is None else v


def summary_rows(data):
    """spc.csv's rows: the table of the page, one per characteristic."""
    out = []
    for c in data["characteristics"]:
        row = {"characteristic": c["id"], **{k: c.get(k) for k in SUMMARY_COLUMNS if k in c},
               "tests": " ".join(str(r) for r in c["rules"]), "subgroups": c.get("subgroups")}
        out.append(row)
    return out


def write_spc_files(out, rows, *, title, source, subgroup_size=None):
    """Write spc.html, spc.csv and measurements.csv into ``out``, together; returns spc.html's path."""
    from partinspect.reports.spc_page import render_spc_html

    out = prepare_output_dir(out)
    data = spc_data(rows, title=title, source=source, subgroup_size=subgroup_size)
    page = out / "spc.html"
    write_files_atomic({
        page: render_spc_html(data).encode("utf-8"),
        out / "spc.csv": _csv(SUMMARY_COLUMNS, summary_rows(data)),
        out / "measurements.csv": export.csv_bytes(with_subgroups(rows, subgroup_size)),
    })
    return page


def write_spc_page(engine, out, *, batch_id=None, title="Statistical process control", subgroup_size=None):
    """The SPC files of one batch (or of the whole database) into ``out``."""
    from partinspect.production.database import measurements, shown_url

    return write_spc_files(out, measurements(engine, batch_id), title=title, subgroup_size=subgroup_size,
                           source=shown_url(engine.url.render_as_string(hide_password=True)))


def check_subgroup_size(size):
    """``--subgroup-size``: None, 1 (individuals) or 2 to 10 (X-bar/R); else InputError."""
    if size is not None and not 1 <= size <= max(spc.XBAR_R_CONSTANTS):
        from partinspect.errors import InputError

        raise InputError(None, f"--subgroup-size {size}: X-bar/R charts take subgroups of 2 to "
                         f"{max(spc.XBAR_R_CONSTANTS)} parts (ISO 7870-2's constants); 1 charts parts one by one")
    return size


def run_spc(db, out, *, subgroup_size=None, export_to=None):
    """``inspect spc DB [-o OUT] [--export FILE]``: the SPC files and/or the export of an existing results database.

    Returns
    -------
    list of Path
        What was written: spc.html (when ``out``), the export file (when ``export_to``).
    """
    from partinspect.atomic import check_output_dir
    from partinspect.production.database import database_url, measurements, open_database, shown_url

    check_subgroup_size(subgroup_size)
    if export_to is not None:
        if Path(export_to).suffix.lower() not in export.FORMATS:
            export.export_bytes(export_to, [])  # the one-line error naming the file
        check_output_dir(Path(export_to).parent)
    if out is not None:
        check_output_dir(out)
    engine = open_database(database_url(db, Path(out or ".")), create=False)
    written = []
    try:
        if out is not None:
            written.append(write_spc_page(engine, out, title=f"SPC of {Path(str(db)).name}",
                                          subgroup_size=subgroup_size))
        if export_to is not None:
            rows = with_subgroups(measurements(engine), subgroup_size)
            written.append(export.write_export(export_to, rows, source=shown_url(
                engine.url.render_as_string(hide_password=True))))
    finally:
        engine.dispose()
    return written
