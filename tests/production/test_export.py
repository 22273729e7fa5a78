"""inspect spc DB --export FILE.csv|FILE.parquet: the table read back equals the database, value for value."""

import csv
import sqlite3
from datetime import datetime, timedelta

import pytest

from partinspect.cli import main
from partinspect.production import database as db

# The database's own rows, by a query of its own (not the code under test's).
QUERY = """
SELECT p.serial, p.measured_at, p.batch_id, p.subgroup, p.verdict, p.step_file, p.step_sha256, c.characteristic,
       c.type, c.feature, c.unit, c.nominal, c.measured, c.deviation, c.standard_uncertainty,
       c.expanded_uncertainty, c.coverage_factor, c.lower_limit, c.upper_limit, c.decision, c.limit_source, c.rule
FROM characteristics c JOIN parts p ON p.id = c.part_id
WHERE p.id IN (SELECT max(id) FROM parts WHERE status = 'done' GROUP BY serial)
ORDER BY p.measured_at, p.serial, c.characteristic
"""


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """6 parts in 2 lots, a value not measured, a one-sided limit; S1 inspected again later; S9 could not be run."""
    path = tmp_path_factory.mktemp("export") / "line.sqlite"
    engine = db.open_database(f"sqlite:///{path}")
    b1, _ = db.start_batch(engine, "line", "m.csv", "0.1.0")
    for i in range(6):
        part = {"serial": f"S{i}", "step_file": "/line/plate.step", "step_sha256": "d" * 64, "images": f"S{i}",
                "measured_at": datetime(2026, 3, 1, 6, 0, 0, 250000) + timedelta(minutes=7 * i),
                "software_version": "0.1.0", "status": db.DONE, "exit_code": 3, "verdict": "inconclusive",
                "subgroup": f"lot-{i // 3}"}
        d = 12.0 + 0.1 / 3 * i
        db.record_part(engine, b1, part, [
            {"id": "circle-4.diameter", "type": "diameter", "feature": "circle-4", "unit": "mm", "nominal": 12.0,
             "measured": d, "deviation": d - 12.0, "standard_uncertainty": 0.0011 + 1e-7 * i,
             "expanded_uncertainty": 2 * (0.0011 + 1e-7 * i), "coverage_factor": 2.0, "lower_limit": 12.0,
             "upper_limit": 12.05, "decision": "pass", "source": "spec", "rule": "part.tol.yaml line 7"},
            {"id": "line-2.straightness", "type": "straightness", "feature": "line-2", "unit": "mm", "nominal": 0.0,
             "measured": None if i == 4 else 0.003 * i, "standard_uncertainty": None if i == 4 else 0.004,
             "expanded_uncertainty": None if i == 4 else 0.008, "lower_limit": None, "upper_limit": 0.02,
             "decision": "inconclusive", "source": "ISO 2768-K"}])
    db.record_part(engine, b1, {"serial": "S9", "step_file": "/line/plate.step", "images": "S9",
                                "measured_at": datetime(2026, 3, 1, 7), "software_version": "0.1.0",
                                "status": db.FAILED, "exit_code": 2, "error": "no right.png"}, [])
    b2, _ = db.start_batch(engine, "line-2", "m2.csv", "0.1.0")
    db.record_part(engine, b2, {"serial": "S1", "step_file": "/line/plate.step", "step_sha256": "d" * 64,
                                "images": "S1b", "measured_at": datetime(2026, 3, 2, 6), "software_version": "0.1.0",
                                "status": db.DONE, "exit_code": 1, "verdict": "fail", "subgroup": "lot-9"},
                   [{"id": "circle-4.diameter", "type": "diameter", "unit": "mm", "nominal": 12.0, "measured": 12.06,
                     "standard_uncertainty": 0.001, "expanded_uncertainty": 0.002, "lower_limit": 12.0,
                     "upper_limit": 12.05, "decision": "fail"}])
    engine.dispose()
    con = sqlite3.connect(path)
    expected = [list(r) for r in con.execute(QUERY)]
    con.close()
    for r in expected:
        r[1] = datetime.fromisoformat(r[1])
    return path, expected


def test_parquet_export_reads_back_equal_to_the_database(results, tmp_path, monkeypatch):
    import pyarrow as pa
    import pyarrow.parquet as pq

    path, expected = results
    monkeypatch.chdir(tmp_path)
    assert main(["spc", str(path), "--export", "line.parquet", "-q"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["line.parquet"]  # the table alone, no page
    table = pq.read_table(tmp_path / "line.parquet")
    got = [list(r.values()) for r in table.to_pylist()]
    assert len(got) == len(expected) == 2 * 6 - 1   # S1's latest inspection only; S9 not run
    assert got == expected                          # every value, float for float, nulls as None
    assert table.schema.field("measured").type == pa.float64()
    assert table.schema.field("measured_at").type == pa.timestamp("us")
    assert table.schema.field("batch_id").type == pa.int64()
    assert table.column("subgroup").to_pylist()[:2] == ["lot-0", "lot-0"]
    assert table.schema.metadata[b"partinspect"]
    assert table.column("measured").null_count == 1 and table.column("lower_limit").null_count == 5


def test_csv_export_and_the_page_together(results, tmp_path):
    path, expected = results
    out, f = tmp_path / "spc", tmp_path / "sub" / "line.csv"
    assert main(["spc", str(path), "-o", str(out), "--export", str(f), "-q"]) == 0
    assert (out / "spc.html").is_file() and f.read_bytes() == (out / "measurements.csv").read_bytes()
    with open(f, newline="") as fh:
        rows = list(csv.reader(fh))
    header, rows = rows[0], rows[1:]
    assert header[:4] == ["serial", "measured_at", "batch_id", "subgroup"] and len(rows) == len(expected)
    for got, want in zip(rows, expected):
        for cell, value in zip(got, want):
            if value is None:
                assert cell == ""
            elif isinstance(value, float):
                assert float(cell) == value      # the shortest exact form: the same double
            else:
                assert cell == str(value)


def test_subgroup_size_regroups_the_exported_parts(results, tmp_path):
    import pyarrow.parquet as pq

    path, _ = results
    assert main(["spc", str(path), "--export", str(tmp_path / "g.parquet"), "--subgroup-size", "2", "-q"]) == 0
    table = pq.read_table(tmp_path / "g.parquet", columns=["serial", "subgroup"]).to_pylist()
    assert {(r["serial"], r["subgroup"]) for r in table} == {
        ("S0", "1"), ("S2", "1"), ("S3", "2"), ("S4", "2"), ("S5", "3"), ("S1", "3")}


def test_an_export_format_we_do_not_write_is_one_line(results, tmp_path, capsys):
    path, _ = results
    assert main(["spc", str(path), "--export", str(tmp_path / "line.xlsx")]) == 2
    err = capsys.readouterr().err
    assert err == f"inspect: error: {tmp_path / 'line.xlsx'}: --export: the file's name must end in .csv or .parquet\n"
    assert list(tmp_path.iterdir()) == []
