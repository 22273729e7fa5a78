"""The results database as one table for users' own tools: CSV or Parquet.

One row per characteristic per inspected part (a serial inspected more
than once with its latest inspection, as on the SPC page): the part's
serial, time stamp, batch and subgroup, its part number (STEP file and
its sha256), and the characteristic's value, standard and expanded
uncertainty with the coverage factor, limits and their source, and
decision. Values are the database's own, not rounded: CSV writes Python's
shortest exact form of each float, Parquet the IEEE doubles, with
``measured_at`` as a timestamp (UTC, microseconds) and empty cells as
nulls.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

from partinspect import __version__
from partinspect.errors import InputError

#: The table's columns and their Parquet types (pyarrow type names).
COLUMNS = (
    ("serial", "string"), ("measured_at", "timestamp"), ("batch_id", "int64"), ("subgroup", "string"),
    ("verdict", "string"), ("step_file", "string"), ("step_sha256", "string"), ("characteristic", "string"),
    ("type", "string"), ("feature", "string"), ("unit", "string"), ("nominal", "float64"),
    ("measured", "float64"), ("deviation", "float64"), ("standard_uncertainty", "float64"),
    ("expanded_uncertainty", "float64"), ("coverage_factor", "float64"), ("lower_limit", "float64"),
    ("upper_limit", "float64"), ("decision", "string"), ("limit_source", "string"), ("rule", "string"),
)
NAMES = tuple(name for name, _ in COLUMNS)
FORMATS = (".csv", ".parquet")


def csv_bytes(rows):
    """The rows as CSV (header, then one line each; floats in their shortest exact form, None empty)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(NAMES)
    for r in rows:
        w.writerow(["" if r.get(c) is None else r.get(c) for c in NAMES])
    return buf.getvalue().encode("utf-8")


def parquet_bytes(rows, metadata=None):
    """The rows as a Parquet file's bytes (one row group, typed columns, nulls for missing values).

    ``metadata``: str -> str pairs kept in the file's schema metadata.
    """
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise InputError(None, "--export FILE.parquet needs pyarrow (pip install pyarrow)") from None
    types = {"string": pa.string(), "int64": pa.int64(), "float64": pa.float64(), "timestamp": pa.timestamp("us")}
    schema = pa.schema([pa.field(name, types[kind]) for name, kind in COLUMNS], metadata=metadata)
    table = pa.Table.from_pydict({c: [r.get(c) for r in rows] for c in NAMES}, schema=schema)
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


def export_bytes(path, rows, *, source=""):
    """The export of ``rows`` in the format ``path``'s suffix names (.csv or .parquet)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".csv":
        return csv_bytes(rows)
    if suffix == ".parquet":
        return parquet_bytes(rows, {"partinspect": __version__, "source": source,
                                    "rows": "one per characteristic per part (latest inspection of a serial)"})
    raise InputError(path, f"--export: the file's name must end in {' or '.join(FORMATS)}")


def write_export(path, rows, *, source=""):
    """Write the export file atomically; returns its Path."""
    from partinspect.atomic import prepare_output_dir, write_bytes_atomic

    path = Path(path)
    data = export_bytes(path, rows, source=source)
    prepare_output_dir(path.parent)
    return write_bytes_atomic(path, data)
