"""The results database on a real PostgreSQL server: the same contents as SQLite's, migrations, SPC and export.

A throwaway cluster (initdb in a temporary folder, the server on 127.0.0.1
on a free port, fsync off) lives for this module. Skipped, with the reason,
where the PostgreSQL server binaries or the psycopg driver are missing.
"""

import glob
import os
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest
import sqlalchemy as sa

from partinspect.cli import main
from partinspect.production import database as db

pytestmark = pytest.mark.timeout(600)

PLATE = Path(__file__).resolve().parents[2] / "examples" / "plate"


def _bin_dir():
    found = shutil.which("initdb")
    if found:
        return Path(found).parent
    dirs = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))  # Debian keeps them off the PATH
    return Path(dirs[-1]).parent if dirs else None


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server():
    """A PostgreSQL server of this module's own; yields a URL prefix ``postgresql://qa@127.0.0.1:PORT/``."""
    pytest.importorskip("psycopg", reason="the PostgreSQL driver psycopg is not installed (pip install 'psycopg[binary]')")
    bin_dir = _bin_dir()
    if bin_dir is None:
        pytest.skip("no PostgreSQL server binaries (initdb, pg_ctl): apt-get install postgresql")
    as_user = []
    if os.geteuid() == 0:  # the server refuses to run as root
        if shutil.which("runuser") is None or subprocess.run(["id", "postgres"], capture_output=True).returncode:
            pytest.skip("running as root without a 'postgres' user (and runuser) to run the server as")
        as_user = ["runuser", "-u", "postgres", "--"]
    root = Path(tempfile.mkdtemp(prefix="partinspect-pg-"))
    if as_user:
        shutil.chown(root, "postgres")
    data, port = root / "data", _free_port()
    run = lambda *cmd: subprocess.run([*as_user, *cmd], capture_output=True, text=True, check=True)  # noqa: E731
    try:
        run(str(bin_dir / "initdb"), "-D", str(data), "-A", "trust", "-U", "qa", "-E", "UTF8", "--no-sync")
        run(str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(root / "log"), "-w", "-t", "60", "start", "-o",
            f"-p {port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off")
        base = f"postgresql://qa@127.0.0.1:{port}/"
        engine = sa.create_engine(base + "postgres", isolation_level="AUTOCOMMIT")
        with engine.connect() as conn:
            for name in ("line", "old"):
                conn.execute(sa.text(f"CREATE DATABASE {name}"))
        engine.dispose()
        yield base
    finally:
        subprocess.run([*as_user, str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop"],
                       capture_output=True)
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="module")
def both(server, tmp_path_factory):
    """The same two-part batch into SQLite and into PostgreSQL (one warm worker: this process)."""
    root = tmp_path_factory.mktemp("pg")
    manifest = root / "line.csv"
    manifest.write_text("serial,step,images,time,subgroup\n" + "".join(
        f"Q-{i},{PLATE / 'part.step'},{PLATE / 'images'},2026-03-01T08:0{i}:00,lot-1\n" for i in (1, 2)))
    codes = {}
    for name, url in (("sqlite", None), ("pg", server + "line")):
        args = ["batch", str(manifest), "-o", str(root / name), "--workers", "1", "-q"]
        codes[name] = main(args + (["--db", url] if url else []))
    return {"root": root, "codes": codes, "sqlite": f"sqlite:///{root / 'sqlite' / 'results.sqlite'}",
            "pg": server + "line"}


# Typed queries (SQLite hands back a time stamp as text to a raw one): every column but ids, paths, timing, worker.
_P, _C = db.TABLES["parts"], db.TABLES["characteristics"]
PARTS = sa.select(*[c for c in _P.c if c.name not in ("id", "batch_id", "report_dir", "seconds", "worker")]
                  ).order_by(_P.c.serial)
CHARS = (sa.select(_P.c.serial, *[c for c in _C.c if c.name not in ("id", "part_id")])
         .join(_P, _P.c.id == _C.c.part_id).order_by(_P.c.serial, _C.c.characteristic))


def _rows(url, query):
    engine = sa.create_engine(url)
    try:
        with engine.connect() as conn:
            return [tuple(r) for r in conn.execute(query if not isinstance(query, str) else sa.text(query))]
    finally:
        engine.dispose()


def test_a_batch_writes_the_same_database_contents_to_postgresql_as_to_sqlite(both):
    assert both["codes"] == {"sqlite": 3, "pg": 3}
    parts = _rows(both["pg"], PARTS)
    assert parts == _rows(both["sqlite"], PARTS) and [p[0] for p in parts] == ["Q-1", "Q-2"]
    chars = _rows(both["pg"], CHARS)
    assert len(chars) > 40 and chars == _rows(both["sqlite"], CHARS)  # every float the same double
    assert _rows(both["pg"], "SELECT version FROM schema_version") == [(db.SCHEMA_VERSION,)]
    # The batch's SPC page read back from the server: the same table as from SQLite.
    assert (both["root"] / "pg" / "spc.csv").read_bytes() == (both["root"] / "sqlite" / "spc.csv").read_bytes()


def test_spc_and_export_from_the_server(both, tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    assert main(["spc", both["pg"], "-o", str(tmp_path / "spc"), "--export", str(tmp_path / "pg.parquet"), "-q"]) == 0
    assert main(["spc", both["sqlite"][len("sqlite:///"):], "--export", str(tmp_path / "lite.parquet"), "-q"]) == 0
    assert pq.read_table(tmp_path / "pg.parquet").equals(pq.read_table(tmp_path / "lite.parquet"))
    html = (tmp_path / "spc" / "spc.html").read_text()
    assert "postgresql://qa@127.0.0.1:" in html  # the source named, without a password to hide


def test_an_older_schema_on_the_server_is_migrated(server):
    url = server + "old"
    engine = sa.create_engine(url)
    assert db.upgrade(engine, to=1) == (0, 1)
    engine.dispose()
    engine = db.open_database(url)
    with engine.connect() as conn:
        assert db.schema_version(conn) == db.SCHEMA_VERSION
        assert {"worker", "subgroup"} <= {c["name"] for c in sa.inspect(conn).get_columns("parts")}
    engine.dispose()
