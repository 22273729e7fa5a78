"""The results database: batches, parts and every characteristic, with a versioned schema.

One schema, written with SQLAlchemy Core, serves an embedded SQLite file
(the default, beside the reports) and a shared PostgreSQL line database
(``postgresql://...``). Each part is written in one transaction, so a batch
killed mid-way loses no finished part and leaves no half-written one; the
parts of a batch with status "done" are what ``inspect batch --resume``
skips.

The schema carries its version in ``schema_version``; :data:`MIGRATIONS`
is the ordered list of steps from an empty database to the current
schema, and opening an older database applies the missing steps in one
transaction.
"""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import sqlalchemy as sa

from partinspect.errors import InputError

DONE, FAILED = "done", "failed"


def _tables(version):
    """The tables as they stand at schema ``version`` (a new MetaData each call)."""
    md = sa.MetaData()
    sa.Table("schema_version", md, sa.Column("version", sa.Integer, nullable=False))
    sa.Table(
        "batches", md,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("name", sa.String(1000), nullable=False),   # the output folder, resolved
        sa.Column("manifest", sa.String(1000)),
        sa.Column("started", sa.DateTime, nullable=False),
        sa.Column("software_version", sa.String(50), nullable=False),
    )
    parts = [
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("batch_id", sa.Integer, sa.ForeignKey("batches.id"), nullable=False),
        sa.Column("serial", sa.String(200), nullable=False),
        sa.Column("step_file", sa.String(1000), nullable=False),
        sa.Column("step_sha256", sa.String(64)),
        sa.Column("images", sa.String(1000), nullable=False),
        sa.Column("left_sha256", sa.String(64)),
        sa.Column("right_sha256", sa.String(64)),
        sa.Column("calibration_sha256", sa.String(64)),
        sa.Column("spec_file", sa.String(1000)),
        sa.Column("spec_sha256", sa.String(64)),
        sa.Column("measured_at", sa.DateTime, nullable=False),  # the manifest's time stamp, else the run's
        sa.Column("software_version", sa.String(50), nullable=False),
        sa.Column("status", sa.String(10), nullable=False),     # done | failed (could not be run)
        sa.Column("exit_code", sa.Integer, nullable=False),
        sa.Column("verdict", sa.String(20)),
        sa.Column("error", sa.Text),
        sa.Column("report_dir", sa.String(1000)),
        sa.Column("seconds", sa.Float),
        sa.UniqueConstraint("batch_id", "serial"),
    ]
    if version >= 2:
        parts.append(sa.Column("worker", sa.String(200)))
    if version >= 3:
        parts.append(sa.Column("subgroup", sa.String(200)))
    if version >= 4:
        parts.append(sa.Column("rig_refined", sa.Boolean))
    sa.Table("parts", md, *parts)
    sa.Table(
        "characteristics", md,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("part_id", sa.Integer, sa.ForeignKey("parts.id"), nullable=False),
        sa.Column("characteristic", sa.String(200), nullable=False),
        sa.Column("type", sa.String(50)),
        sa.Column("feature", sa.String(200)),
        sa.Column("unit", sa.String(10)),
        sa.Column("nominal", sa.Float),
        sa.Column("measured", sa.Float),
        sa.Column("deviation", sa.Float),
        sa.Column("standard_uncertainty", sa.Float),
        sa.Column("expanded_uncertainty", sa.Float),
        sa.Column("coverage_factor", sa.Float),
        sa.Column("lower_limit", sa.Float),
        sa.Column("upper_limit", sa.Float),
        sa.Column("decision", sa.String(20), nullable=False),
        sa.Column("limit_source", sa.String(50)),
        sa.Column("rule", sa.String(200)),
        sa.UniqueConstraint("part_id", "characteristic"),
    )
    if version >= 2:
        sa.Index("ix_characteristics_name", md.tables["characteristics"].c.characteristic)
    return md


def _create_v1(conn):
    _tables(1).create_all(conn)
    conn.execute(sa.text("INSERT INTO schema_version (version) VALUES (0)"))


def _add_worker_and_index(conn):
    # Which host and process inspected a part (a cluster spreads them), and
    # the SPC page's query by characteristic name.
    conn.execute(sa.text("ALTER TABLE parts ADD COLUMN worker VARCHAR(200)"))
    conn.execute(sa.text("CREATE INDEX ix_characteristics_name ON characteristics (characteristic)"))


def _add_subgroup(conn):
    # The rational subgroup (lot, sample) a part was taken in: X-bar/R charts.
    conn.execute(sa.text("ALTER TABLE parts ADD COLUMN subgroup VARCHAR(200)"))


def _add_rig_refined(conn):
    # Whether the part was measured with the rig refined from its own circles
    # (``inspect batch --refine-rig``): NULL when not asked, false when asked
    # but the circles could not determine it (report.json says why).
    conn.execute(sa.text("ALTER TABLE parts ADD COLUMN rig_refined BOOLEAN"))


#: Ordered steps; step i (1-based) takes the schema from version i - 1 to i.
MIGRATIONS = (_create_v1, _add_worker_and_index, _add_subgroup, _add_rig_refined)
SCHEMA_VERSION = len(MIGRATIONS)
TABLES = _tables(SCHEMA_VERSION).tables


def database_url(db, out):
    """The SQLAlchemy URL for ``--db``: a URL as given, a path as SQLite, default OUT/results.sqlite."""
    if db is None:
        return f"sqlite:///{Path(out).resolve() / 'results.sqlite'}"
    if "://" in str(db):
        return str(db)
    return f"sqlite:///{Path(db).resolve()}"


def schema_version(conn):
    """The schema version of the database behind ``conn``; 0 when it has no schema yet."""
    if not sa.inspect(conn).has_table("schema_version"):
        return 0
    return conn.execute(sa.text("SELECT version FROM schema_version")).scalar_one()


def upgrade(engine, to=SCHEMA_VERSION):
    """Apply the missing migration steps up to version ``to``, all in one transaction.

    Returns
    -------
    (int, int)
        The version found and the version left.
    """
    with engine.begin() as conn:
        found = schema_version(conn)
        if found > SCHEMA_VERSION:
            raise InputError(str(engine.url), f"results database has schema version {found}, newer than this "
                             f"partinspect's {SCHEMA_VERSION}; upgrade partinspect")
        for version in range(found + 1, to + 1):
            MIGRATIONS[version - 1](conn)
            conn.execute(sa.text("UPDATE schema_version SET version = :v"), {"v": version})
    return found, max(found, to)


def open_database(url, *, create=True):
    """An engine on the results database at ``url``, its schema brought to the current version (``create``).

    Parameters
    ----------
    url : str
        SQLAlchemy URL (``sqlite:///path``, ``postgresql://user@host/db``).
    create : bool
        False: only read it (``inspect spc``): it must exist, and an older
        schema is read as it is, not upgraded (every version's tables answer
        the SPC query).

    Raises
    ------
    InputError
        The database cannot be opened, or (``create=False``) holds no results.
    """
    if url.startswith("sqlite:///"):
        path = Path(url[len("sqlite:///"):])
        if not create and not path.is_file():
            raise InputError(path, "results database not found")
        if create and not path.parent.is_dir():
            raise InputError(path, f"folder {path.parent} does not exist")
    try:
        engine = sa.create_engine(url)
        if url.startswith("sqlite"):
            # SQLite leaves foreign keys unchecked unless asked, per connection.
            sa.event.listen(engine, "connect", lambda dbapi, _: dbapi.execute("PRAGMA foreign_keys = ON"))
        if not create:
            with engine.connect() as conn:
                found = schema_version(conn)
            if found == 0:
                raise InputError(shown_url(url), "not a partinspect results database (no schema_version table)")
            if found > SCHEMA_VERSION:
                raise InputError(shown_url(url), f"results database has schema version {found}, newer than this "
                                 f"partinspect's {SCHEMA_VERSION}; upgrade partinspect")
        else:
            upgrade(engine)
    except (sa.exc.SQLAlchemyError, ImportError) as exc:
        raise InputError(shown_url(url), f"cannot open the results database: {' '.join(str(exc).split())[:200]}") from None
    return engine


def shown_url(url):
    """The URL as a message may show it: a SQLite file's path, a server's URL without its password."""
    if url.startswith("sqlite:///"):
        return url[len("sqlite:///"):]
    return sa.engine.make_url(url).render_as_string(hide_password=True)


def start_batch(engine, name, manifest, software_version, *, resume=False):
    """The batch's id: a new batch, or with ``resume`` the latest one of that name (new if none).

    Returns
    -------
    (int, dict of str to int)
        The batch id, and the serials it already holds as done with their exit codes.
    """
    b, p = TABLES["batches"], TABLES["parts"]
    with engine.begin() as conn:
        batch_id = None
        if resume:
            batch_id = conn.execute(sa.select(sa.func.max(b.c.id)).where(b.c.name == name)).scalar()
        if batch_id is None:
            batch_id = conn.execute(b.insert().values(
                name=name, manifest=manifest, started=_now(), software_version=software_version)).inserted_primary_key[0]
        done = conn.execute(sa.select(p.c.serial, p.c.exit_code).where(p.c.batch_id == batch_id, p.c.status == DONE))
        return batch_id, dict(done.all())


def record_part(engine, batch_id, part, characteristics):
    """Write one part and its characteristics in one transaction; replaces an earlier failed try.

    Parameters
    ----------
    part : dict
        Columns of ``parts`` (without id and batch_id).
    characteristics : list of dict
        report.json's characteristics (schema report/1).
    """
    p, c = TABLES["parts"], TABLES["characteristics"]
    with engine.begin() as conn:
        old = conn.execute(sa.select(p.c.id).where(p.c.batch_id == batch_id, p.c.serial == part["serial"])).scalar()
        if old is not None:
            conn.execute(c.delete().where(c.c.part_id == old))
            conn.execute(p.delete().where(p.c.id == old))
        part_id = conn.execute(p.insert().values(batch_id=batch_id, **part)).inserted_primary_key[0]
        rows = [characteristic_row(part_id, ch) for ch in characteristics]
        if rows:
            conn.execute(c.insert(), rows)
    return part_id


def characteristic_row(part_id, ch):
    """The ``characteristics`` row of one report.json characteristic."""
    return {
        "part_id": part_id, "characteristic": ch["id"], "type": ch.get("type"), "feature": ch.get("feature"),
        "unit": ch.get("unit"), "nominal": ch.get("nominal"), "measured": ch.get("measured"),
        "deviation": ch.get("deviation"), "standard_uncertainty": ch.get("standard_uncertainty"),
        "expanded_uncertainty": ch.get("expanded_uncertainty"), "coverage_factor": ch.get("coverage_factor"),
        "lower_limit": ch.get("lower_limit"), "upper_limit": ch.get("upper_limit"), "decision": ch["decision"],
        "limit_source": ch.get("source"), "rule": ch.get("rule"),
    }


def measurements(engine, batch_id=None):
    """Every characteristic of every part inspected (status done), one row each, in time order.

    A serial inspected in several batches counts once, with its latest
    inspection. ``batch_id`` limits the rows to one batch. A database of
    an older schema (read, not upgraded) gives None where it has no column.

    Returns
    -------
    list of dict
        Keys: serial, measured_at, batch_id, subgroup, verdict, step_file,
        step_sha256, and the columns of ``characteristics`` but its ids.
    """
    p, c = TABLES["parts"], TABLES["characteristics"]
    with engine.connect() as conn:
        have = {col["name"] for col in sa.inspect(conn).get_columns("parts")}
    where = [p.c.status == DONE]
    if batch_id is not None:
        where.append(p.c.batch_id == batch_id)
    latest = sa.select(sa.func.max(p.c.id)).where(*where).group_by(p.c.serial).scalar_subquery()
    subgroup = p.c.subgroup if "subgroup" in have else sa.null().label("subgroup")
    cols = [p.c.serial, p.c.measured_at, p.c.batch_id, subgroup, p.c.verdict, p.c.step_file, p.c.step_sha256,
            *[col for col in c.c if col.name not in ("id", "part_id")]]
    query = (sa.select(*cols).join(p, c.c.part_id == p.c.id).where(p.c.id.in_(latest))
             .order_by(p.c.measured_at, p.c.serial, c.c.characteristic))
    with engine.connect() as conn:
        return [dict(r._mapping) for r in conn.execute(query)]


def _now():
    return datetime.now(timezone.utc).replace(tzinfo=None, microsecond=0)
