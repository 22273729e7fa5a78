"""inspect spc: the page and the CSV from a results database, checked against an independent computation."""

import csv
from datetime import datetime, timedelta

import numpy as np
import pytest

from partinspect.cli import main
from partinspect.production import database as db

N = 30
EVIL = "edge-<script>alert(1)</script>.straightness"


@pytest.fixture(scope="module")
def line_db(tmp_path_factory):
    """30 parts: a hole's diameter drifting upwards, a steady one, and a form characteristic with a large U."""
    path = tmp_path_factory.mktemp("spc") / "line.sqlite"
    engine = db.open_database(f"sqlite:///{path}")
    batch, _ = db.start_batch(engine, "line", None, "0.1.0")
    rng = np.random.default_rng(7)
    drift = 12.0 + 0.004 * rng.standard_normal(N) + np.linspace(0.0, 0.03, N)
    steady = 8.0 + 0.003 * rng.standard_normal(N)
    for i in range(N):
        chars = [
            {"id": "circle-4.diameter", "type": "diameter", "unit": "mm", "nominal": 12.0, "measured": drift[i],
             "standard_uncertainty": 0.002, "expanded_uncertainty": 0.004, "lower_limit": 11.95,
             "upper_limit": 12.05, "decision": "fail" if drift[i] > 12.05 else "pass", "source": "spec"},
            {"id": "circle-2.diameter", "type": "diameter", "unit": "mm", "nominal": 8.0, "measured": steady[i],
             "standard_uncertainty": 0.002, "expanded_uncertainty": 0.004, "lower_limit": 7.95, "upper_limit": 8.05,
             "decision": "pass"},
            {"id": EVIL, "type": "straightness", "unit": "mm", "nominal": 0.0, "measured": 0.01 + 0.001 * (i % 3),
             "standard_uncertainty": 0.005, "expanded_uncertainty": 0.010, "lower_limit": None,
             "upper_limit": 0.05, "decision": "pass"},
        ]
        part = {"serial": f"S{i:03d}", "step_file": "/line/plate.step", "step_sha256": "b" * 64, "images": "x",
                "measured_at": datetime(2026, 3, 1, 6) + timedelta(minutes=5 * i), "software_version": "0.1.0",
                "status": db.DONE, "exit_code": 0, "verdict": "pass"}
        db.record_part(engine, batch, part, chars)
    engine.dispose()
    return path, drift


@pytest.fixture(scope="module")
def spc_out(line_db, tmp_path_factory):
    out = tmp_path_factory.mktemp("spc-out")
    assert main(["spc", str(line_db[0]), "-o", str(out), "-q"]) == 0
    with open(out / "spc.csv", newline="") as f:
        table = {r["characteristic"]: r for r in csv.DictReader(f)}
    return out, table


def test_cpk_in_the_export_matches_an_independent_computation(line_db, spc_out):
    _, drift = line_db
    _, table = spc_out
    row = table["circle-4.diameter"]
    assert int(row["n"]) == N
    sigma_w = np.mean(np.abs(np.diff(drift))) * np.sqrt(np.pi) / 2
    s = np.std(drift, ddof=1)
    mean = drift.mean()
    assert float(row["cpk"]) == pytest.approx(min(12.05 - mean, mean - 11.95) / (3 * sigma_w), rel=1e-9)
    assert float(row["ppk"]) == pytest.approx(min(12.05 - mean, mean - 11.95) / (3 * s), rel=1e-9)
    assert float(row["cp"]) == pytest.approx(0.1 / (6 * sigma_w), rel=1e-9)
    assert int(row["fails"]) == int(np.sum(drift > 12.05))


def test_the_drift_fires_a_test_and_the_steady_hole_none(spc_out):
    _, table = spc_out
    assert table["circle-4.diameter"]["tests"] != ""
    assert set(table["circle-4.diameter"]["tests"].split()) & {"1", "2", "3", "5", "6"}
    assert table["circle-2.diameter"]["tests"] == ""


def test_the_measuring_system_is_judged_against_the_tolerance(spc_out):
    out, table = spc_out
    # straightness: U = 0.010 over the zone 0 .. 0.05: Q_MP = 2 U / T = 40 %, above 30 %.
    assert float(table[EVIL]["q_mp"]) == pytest.approx(0.4)
    assert table[EVIL]["capable_measurement"] == "False"
    assert float(table["circle-2.diameter"]["q_mp"]) == pytest.approx(0.08)
    html = (out / "spc.html").read_text()
    notice = html[html.index('id="not-capable"'):]
    notice = notice[:notice.index("</p>")]
    assert "edge-&lt;script&gt;alert(1)&lt;/script&gt;.straightness" in notice and "40 %" in notice
    assert "<script>alert(1)" not in html          # escaped in the table and, as \u003c, in the charts' data
    assert html.count("Plotly.newPlot") == 1 and 'id="chart-2"' in html


def test_measurements_export_has_one_row_per_part_and_characteristic(spc_out):
    out, _ = spc_out
    with open(out / "measurements.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3 * N
    assert {r["serial"] for r in rows} == {f"S{i:03d}" for i in range(N)}


def test_spc_of_a_missing_or_foreign_database(tmp_path, capsys):
    assert main(["spc", str(tmp_path / "none.sqlite"), "-o", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.strip() == f"inspect: error: {tmp_path / 'none.sqlite'}: results database not found"
    (tmp_path / "x.sqlite").write_text("not a database at all, just text " * 50)
    assert main(["spc", str(tmp_path / "x.sqlite"), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot open the results database" in err


@pytest.fixture(scope="module")
def lots_db(tmp_path_factory):
    """20 parts in 4 lots of 5 (the manifest's subgroup column), the lots' means apart; then no lot for 3 parts."""
    path = tmp_path_factory.mktemp("lots") / "lots.sqlite"
    engine = db.open_database(f"sqlite:///{path}")
    batch, _ = db.start_batch(engine, "lots", None, "0.1.0")
    rng = np.random.default_rng(3)
    x = 12.0 + 0.002 * rng.standard_normal(20) + np.repeat([0.0, 0.004, -0.002, 0.001], 5)
    for i, value in enumerate(x):
        part = {"serial": f"L{i:02d}", "step_file": "/line/plate.step", "step_sha256": "c" * 64, "images": "x",
                "measured_at": datetime(2026, 3, 2, 6) + timedelta(minutes=i), "software_version": "0.1.0",
                "status": db.DONE, "exit_code": 0, "verdict": "pass", "subgroup": f"lot-{i // 5 + 1}"}
        db.record_part(engine, batch, part, [
            {"id": "circle-4.diameter", "type": "diameter", "unit": "mm", "nominal": 12.0, "measured": value,
             "standard_uncertainty": 0.001, "expanded_uncertainty": 0.002, "lower_limit": 11.95,
             "upper_limit": 12.05, "decision": "pass"}])
    engine.dispose()
    return path, x


def _spc_table(out):
    with open(out / "spc.csv", newline="") as f:
        return {r["characteristic"]: r for r in csv.DictReader(f)}


def test_stored_subgroups_give_xbar_r_charts_and_the_within_sigma_from_ranges(lots_db, tmp_path):
    path, x = lots_db
    assert main(["spc", str(path), "-o", str(tmp_path), "-q"]) == 0
    row = _spc_table(tmp_path)["circle-4.diameter"]
    table = x.reshape(4, 5)
    sigma_w = np.mean(table.max(axis=1) - table.min(axis=1)) / 2.326      # R_bar / d2(5)
    assert (row["chart"], row["subgroup_size"], row["subgroups"]) == ("xbar-r", "5", "4")
    assert float(row["sigma_within"]) == pytest.approx(sigma_w, rel=1e-9)
    assert float(row["cpk"]) == pytest.approx(min(12.05 - x.mean(), x.mean() - 11.95) / (3 * sigma_w), rel=1e-9)
    html = (tmp_path / "spc.html").read_text()
    assert 'id="xbar-0"' in html and "X̄/R, 4 × 5" in html and "subgroup lot-2 (5 parts: L05, L06, L07, ...)" in html
    with open(tmp_path / "measurements.csv", newline="") as f:
        assert [r["subgroup"] for r in csv.DictReader(f)][:6] == ["lot-1"] * 5 + ["lot-2"]


def test_subgroup_size_groups_consecutive_parts_or_charts_them_one_by_one(line_db, lots_db, tmp_path):
    path, drift = line_db
    assert main(["spc", str(path), "-o", str(tmp_path / "g"), "--subgroup-size", "4", "-q"]) == 0
    row = _spc_table(tmp_path / "g")["circle-4.diameter"]
    # 30 parts: 7 subgroups of 4 charted, the last 2 parts a subgroup left out of the chart.
    assert (row["chart"], row["subgroup_size"], row["subgroups"]) == ("xbar-r", "4", "7")
    r = drift[:28].reshape(7, 4)
    assert float(row["sigma_within"]) == pytest.approx(np.mean(r.max(axis=1) - r.min(axis=1)) / 2.059, rel=1e-9)
    assert "(1 left out)" in (tmp_path / "g" / "spc.html").read_text()
    assert main(["spc", str(lots_db[0]), "-o", str(tmp_path / "i"), "--subgroup-size", "1", "-q"]) == 0
    assert _spc_table(tmp_path / "i")["circle-4.diameter"]["chart"] == "individuals"


def test_a_subgroup_size_without_chart_constants_is_refused(line_db, tmp_path, capsys):
    assert main(["spc", str(line_db[0]), "-o", str(tmp_path), "--subgroup-size", "12"]) == 2
    err = capsys.readouterr().err
    assert err == ("inspect: error: --subgroup-size 12: X-bar/R charts take subgroups of 2 to 10 parts "
                   "(ISO 7870-2's constants); 1 charts parts one by one\n")


def test_the_xbar_r_chart_draws_in_a_real_browser(lots_db, tmp_path):
    """Headless Chromium (tests/reports/cdp.py): no error or CSP violation, nothing fetched, both panels drawn."""
    from tests.reports.cdp import Browser, find_chromium

    chromium = find_chromium()
    if chromium is None:
        pytest.skip("Chromium is not installed (scripts/install.sh installs it)")
    assert main(["spc", str(lots_db[0]), "-o", str(tmp_path / "out"), "-q"]) == 0
    (tmp_path / "profile").mkdir()
    with Browser(chromium, tmp_path / "profile", width=1300, height=900) as browser:
        browser.open((tmp_path / "out" / "spc.html").resolve().as_uri())
        assert browser.errors() == []
        assert [u for u in browser.requests() if not u.startswith(("file:", "data:"))] == []
        traces, panels, points = browser.evaluate(
            "[document.getElementById('xbar-0').data.length, "
            "[...document.querySelectorAll('#xbar-0 g.subplot')].map(g => g.getAttribute('class')).sort(), "
            "document.querySelectorAll('#xbar-0 g.trace.scatter path.point').length]")
    assert traces >= 6                              # means, ranges, their centre lines and limits
    assert panels == ["subplot xy", "subplot xy2"]  # the X-bar panel above the R panel
    assert points >= 8                              # 4 subgroup means and 4 ranges drawn


def test_a_subgroup_s_wide_range_is_named_on_the_page():
    from partinspect.production.spc_report import spc_data
    from partinspect.reports.spc_page import render_spc_html

    x = 12.0 + 0.001 * np.random.default_rng(1).standard_normal(40)
    x[17] += 0.02                                            # one part far off: its subgroup's range is wide
    rows = [{"serial": f"S{i:02d}", "measured_at": datetime(2026, 1, 1, 0, i), "subgroup": str(i // 4),
             "characteristic": "circle-1.diameter", "type": "diameter", "unit": "mm", "measured": v,
             "standard_uncertainty": 0.001, "expanded_uncertainty": 0.002, "lower_limit": 11.9, "upper_limit": 12.1,
             "decision": "pass", "step_sha256": "a", "step_file": "p.step"} for i, v in enumerate(x)]
    data = spc_data(rows, title="t", source="s")
    c = data["characteristics"][0]
    assert c["chart"] == "xbar-r" and c["range_violations"] == [4] and c["range_out"] == 1
    html = render_spc_html(data)
    notice = html[html.index('id="special-causes"'):]
    assert "1 subgroup range(s) beyond the R chart's limits" in notice[:notice.index("</p>")]


def test_individuals_get_their_moving_range_chart_and_a_jump_is_marked():
    from partinspect.production.spc_report import spc_data
    from partinspect.reports.spc_page import run_chart

    x = 12.0 + 0.001 * np.random.default_rng(2).standard_normal(30)
    x[20:] += 0.01                                            # a step: one moving range far beyond D4 x its mean
    rows = [{"serial": f"S{i:02d}", "measured_at": datetime(2026, 1, 1, 0, i), "characteristic": "circle-1.diameter",
             "type": "diameter", "unit": "mm", "measured": v, "standard_uncertainty": 0.001,
             "expanded_uncertainty": 0.002, "lower_limit": 11.9, "upper_limit": 12.1, "decision": "pass",
             "step_sha256": "a", "step_file": "p.step"} for i, v in enumerate(x)]
    c = spc_data(rows, title="t", source="s")["characteristics"][0]
    mr = np.abs(np.diff(x))
    assert c["chart"] != "xbar-r" and np.allclose(c["moving_ranges"], mr)
    assert c["mr_mean"] == pytest.approx(mr.mean()) and c["mr_ucl"] == pytest.approx(3.267 * mr.mean())
    traces = {t["name"]: t for t in run_chart(c)["data"]}
    assert traces["moving range"]["yaxis"] == "y2" and traces["moving range"]["x"][0] == 2
    jump = traces["moving range beyond its limit"]
    assert jump["x"] == [21] and jump["text"] == ["S20"]  # the range from part 20 to 21, plotted at the later part
    assert any(n.startswith("MR UCL") for n in traces)
