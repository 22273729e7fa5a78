"""The results database: schema, migrations, one transaction per part, the SPC query."""

from datetime import datetime

import pytest
import sqlalchemy as sa

from partinspect.errors import InputError
from partinspect.production import database as db


def _part(serial, when, status=db.DONE, verdict="pass", exit_code=0):
    return {"serial": serial, "step_file": "part.step", "step_sha256": "a" * 64, "images": f"{serial}/images",
            "measured_at": when, "software_version": "0.1.0", "status": status, "exit_code": exit_code,
            "verdict": verdict}


def _char(cid, measured, decision="pass"):
    return {"id": cid, "type": "diameter", "feature": cid.split(".")[0], "unit": "mm", "nominal": 12.0,
            "measured": measured, "deviation": None if measured is None else measured - 12.0,
            "standard_uncertainty": 0.002, "expanded_uncertainty": 0.004, "coverage_factor": 2.0,
            "lower_limit": 11.95, "upper_limit": 12.05, "decision": decision, "source": "spec"}


def test_a_new_database_has_the_current_schema(tmp_path):
    engine = db.open_database(f"sqlite:///{tmp_path / 'r.sqlite'}")
    with engine.connect() as conn:
        assert db.schema_version(conn) == db.SCHEMA_VERSION == 4
        assert {"worker", "subgroup", "rig_refined"} <= {c["name"] for c in sa.inspect(conn).get_columns("parts")}


def test_an_older_database_is_upgraded_and_keeps_its_rows(tmp_path):
    url = f"sqlite:///{tmp_path / 'old.sqlite'}"
    engine = sa.create_engine(url)
    assert db.upgrade(engine, to=1) == (0, 1)
    with engine.begin() as conn:
        conn.execute(sa.text("INSERT INTO batches (name, started, software_version) VALUES ('b', '2026-01-01 00:00:00', '0.0.9')"))
    with engine.connect() as conn:
        assert "worker" not in {c["name"] for c in sa.inspect(conn).get_columns("parts")}
    engine.dispose()
    old = db.open_database(url, create=False)
    with old.connect() as conn:  # read only: not upgraded
        assert db.schema_version(conn) == 1
    assert db.measurements(old) == []  # the SPC query answers on the old schema (no subgroup column)
    engine = db.open_database(url)
    with engine.connect() as conn:
        assert db.schema_version(conn) == 4
        assert {"worker", "subgroup", "rig_refined"} <= {c["name"] for c in sa.inspect(conn).get_columns("parts")}
        assert conn.execute(sa.text("SELECT software_version FROM batches")).scalar_one() == "0.0.9"
    assert db.upgrade(engine) == (4, 4)  # nothing left to do


def test_a_newer_database_is_refused(tmp_path):
    url = f"sqlite:///{tmp_path / 'new.sqlite'}"
    engine = db.open_database(url)
    with engine.begin() as conn:
        conn.execute(sa.text("UPDATE schema_version SET version = 99"))
    for create in (True, False):
        with pytest.raises(InputError, match="schema version 99, newer"):
            db.open_database(url, create=create)


def test_spc_needs_an_existing_results_database(tmp_path):
    with pytest.raises(InputError, match="results database not found"):
        db.open_database(f"sqlite:///{tmp_path / 'none.sqlite'}", create=False)
    (tmp_path / "other.sqlite").write_bytes(b"")
    with pytest.raises(InputError, match="not a partinspect results database"):
        db.open_database(f"sqlite:///{tmp_path / 'other.sqlite'}", create=False)


def test_parts_resume_and_the_latest_inspection_counts(tmp_path):
    engine = db.open_database(db.database_url(None, tmp_path))
    assert str(engine.url).endswith("results.sqlite")
    b1, done = db.start_batch(engine, "line-1", "m.csv", "0.1.0")
    assert done == {}
    db.record_part(engine, b1, _part("S1", datetime(2026, 1, 1, 8)), [_char("circle-1.diameter", 12.01),
                                                                     _char("circle-2.diameter", None, "inconclusive")])
    db.record_part(engine, b1, _part("S2", datetime(2026, 1, 1, 9), db.FAILED, None, 2), [])
    same, done = db.start_batch(engine, "line-1", "m.csv", "0.1.0", resume=True)
    assert same == b1 and done == {"S1": 0}  # a failed part is tried again
    # The retry replaces the failed row: one row per serial and batch.
    db.record_part(engine, b1, _part("S2", datetime(2026, 1, 1, 7), verdict="fail", exit_code=1),
                   [_char("circle-1.diameter", 12.06, "fail")])
    # S1 measured again in a new batch: its latest inspection counts.
    b2, _ = db.start_batch(engine, "line-1", "m.csv", "0.1.0")
    assert b2 != b1
    db.record_part(engine, b2, _part("S1", datetime(2026, 1, 2, 8)), [_char("circle-1.diameter", 12.02)])
    rows = db.measurements(engine)
    assert [(r["serial"], r["characteristic"], r["measured"]) for r in rows] == [
        ("S2", "circle-1.diameter", 12.06), ("S1", "circle-1.diameter", 12.02)]
    assert rows[0]["limit_source"] == "spec" and rows[0]["expanded_uncertainty"] == 0.004
    assert [r["serial"] for r in db.measurements(engine, b1)] == ["S2", "S1", "S1"]


def test_a_part_is_written_whole_or_not_at_all(tmp_path):
    engine = db.open_database(db.database_url(tmp_path / "x.sqlite", tmp_path))
    b, _ = db.start_batch(engine, "b", None, "0.1.0")
    bad = _char("circle-1.diameter", 12.0)
    del bad["decision"]  # fails inside the transaction, after the part row
    with pytest.raises(KeyError):
        db.record_part(engine, b, _part("S1", datetime(2026, 1, 1)), [_char("circle-2.diameter", 12.0), bad])
    with engine.connect() as conn:
        assert conn.execute(sa.text("SELECT count(*) FROM parts")).scalar_one() == 0
        assert conn.execute(sa.text("SELECT count(*) FROM characteristics")).scalar_one() == 0


def test_the_schema_compiles_for_postgresql():
    """No PostgreSQL server here: the DDL and the SPC query at least compile for its dialect."""
    from sqlalchemy.dialects import postgresql

    ddl = [str(sa.schema.CreateTable(t).compile(dialect=postgresql.dialect())) for t in db.TABLES.values()]
    assert any("SERIAL NOT NULL" in d and "CREATE TABLE parts" in d for d in ddl)
    assert any("DOUBLE PRECISION" in d or "FLOAT" in d for d in ddl)
    assert db.shown_url("postgresql://qa:secret@line-db/line") == "postgresql://qa:***@line-db/line"
