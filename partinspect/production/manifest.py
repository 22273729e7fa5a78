"""A batch's manifest: which parts to inspect, read from CSV, YAML or a folder layout.

CSV: a header row naming the columns ``serial, step, images`` and
optionally ``spec`` (the tolerance file), ``time`` (ISO 8601 time stamp
of the measurement) and ``subgroup`` (the rational subgroup the part was
taken in: a lot, an hourly sample; the SPC page then draws X-bar/R
charts), one part per row. YAML: a list of mappings with the
same keys under ``parts:``; ``step:`` and ``spec:`` at the top are every
part's default. A folder: one sub-folder per serial number holding
``images/``, with the STEP file given on the command line. Paths are
relative to the manifest (the folder itself for a layout).

A line naming a missing file, a repeated serial or an unreadable time is
one problem naming the manifest and its line; the other lines still run.
A manifest that cannot be read at all is an :class:`InputError`.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from partinspect.errors import InputError

COLUMNS = ("serial", "step", "images", "spec", "time", "subgroup")
REQUIRED = ("serial", "step", "images")
# A serial names its report folder: no separators, no leading dot.
SERIAL = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,199}")


@dataclass(frozen=True)
class Job:
    """One part of a batch; paths absolute, ``time`` naive UTC or None."""

    serial: str
    step: Path
    images: Path
    spec: Path | None = None
    time: datetime | None = None
    line: int | None = None
    subgroup: str | None = None


def read_manifest(path, step=None):
    """The parts a manifest lists, and one line per problem.

    Parameters
    ----------
    path : str or Path
        A ``.csv``, ``.yaml``/``.yml`` file, or a folder of ``SERIAL/images/``.
    step : str or Path, optional
        The STEP file of every part of a folder layout (required there); a
        default for manifests whose rows leave ``step`` empty.

    Returns
    -------
    jobs : list of Job
        The valid lines, in manifest order.
    problems : list of str
        ``"MANIFEST:LINE: problem"`` for every line left out
        (``"FOLDER/SERIAL: problem"`` in a folder layout).

    Raises
    ------
    InputError
        The manifest cannot be read, or lists no part.
    """
    path = Path(path)
    if path.is_dir():
        rows = _folder_rows(path, step)
    elif not path.is_file():
        raise InputError(path, "manifest not found")
    elif path.suffix.lower() == ".csv":
        rows = _csv_rows(path)
    elif path.suffix.lower() in (".yaml", ".yml"):
        rows = _yaml_rows(path)
    else:
        raise InputError(path, "manifest must be a .csv, .yaml or .yml file, or a folder of SERIAL/images/")
    base = path if path.is_dir() else path.parent
    jobs, problems, seen = [], [], {}
    for line, row in rows:
        if step is not None and not row.get("step"):
            row["step"] = str(Path(step).resolve())
        try:
            job = _job(base, line, row)
            if job.serial in seen:
                raise ValueError(f"serial {job.serial} again (first on line {seen[job.serial]})")
        except ValueError as exc:
            where = f"{path}:{line}" if line else str(path / str(row.get("serial")))
            problems.append(f"{where}: {exc}")
            continue
        seen[job.serial] = line
        jobs.append(job)
    if not jobs and not problems:
        raise InputError(path, "the manifest lists no part")
    return jobs, problems


def _job(base, line, row):
    unknown = sorted(set(row) - set(COLUMNS))
    if unknown:
        raise ValueError(f"unknown column(s) {', '.join(unknown)} (expected {', '.join(COLUMNS)})")
    for key in REQUIRED:
        if not str(row.get(key) or "").strip():
            raise ValueError(f"no {key}")
    serial = str(row["serial"]).strip()
    if not SERIAL.fullmatch(serial):
        raise ValueError(f"serial {serial!r} is not a folder name (letters, digits, '.', '_', '-')")
    step = _existing(base, row["step"], "STEP file", Path.is_file)
    images = _existing(base, row["images"], "images folder", Path.is_dir)
    spec = _existing(base, row["spec"], "tolerance spec", Path.is_file) if row.get("spec") else None
    subgroup = str(row.get("subgroup") or "").strip() or None
    if subgroup is not None and len(subgroup) > 200:
        raise ValueError("subgroup longer than 200 characters")
    return Job(serial, step, images, spec, _time(row.get("time")), line, subgroup)


def _existing(base, value, what, check):
    p = (base / str(value).strip()).resolve()
    if not check(p):
        raise ValueError(f"{what} {value} not found" if not p.exists() else f"{what} {value} is not a "
                         f"{'folder' if check is Path.is_dir else 'file'}")
    return p


def _time(value):
    if value is None or str(value).strip() == "":
        return None
    if isinstance(value, datetime):
        t = value
    else:
        try:
            t = datetime.fromisoformat(str(value).strip())
        except ValueError:
            raise ValueError(f"time {value!r} is not an ISO 8601 time stamp (YYYY-MM-DDThh:mm:ss)") from None
    if t.tzinfo is not None:
        t = t.astimezone(timezone.utc).replace(tzinfo=None)
    return t


def _csv_rows(path):
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            if reader.fieldnames is None:
                raise InputError(path, "the manifest is empty (expected a header row: serial,step,images[,spec][,time][,subgroup])")
            header = [(h or "").strip().lower() for h in reader.fieldnames]
            missing = [c for c in REQUIRED if c not in header]
            if missing:
                raise InputError(path, f"line 1: the header lacks column(s) {', '.join(missing)} "
                                 "(expected serial,step,images[,spec][,time][,subgroup])")
            rows = []
            for raw in reader:
                row = {h: (v or "").strip() for h, v in zip(header, raw.values()) if h}
                if None in raw:
                    row["(extra cells)"] = "x"
                if any(row.values()):
                    rows.append((reader.line_num, row))
            return rows
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(path, f"cannot read the manifest as CSV: {exc}") from None


def _yaml_rows(path):
    import yaml

    try:
        node = yaml.compose(path.read_text(encoding="utf-8"))
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the manifest as YAML: {' '.join(str(exc).split())}") from None
    items = data.get("parts") if isinstance(data, dict) else None
    if not isinstance(items, list):
        raise InputError(path, "expected a mapping with a list of parts under 'parts:'")
    defaults = {k: data[k] for k in ("step", "spec") if data.get(k) is not None}
    item_nodes = next(v for k, v in node.value if k.value == "parts").value
    rows = []
    for item, item_node in zip(items, item_nodes):
        line = item_node.start_mark.line + 1
        if not isinstance(item, dict):
            rows.append((line, {"(not a mapping)": item}))
            continue
        rows.append((line, {**defaults, **{str(k): v for k, v in item.items()}}))
    return rows


def _folder_rows(path, step):
    if step is None:
        raise InputError(path, "a folder of SERIAL/images/ needs the STEP file: --step PART.step")
    rows = [(None, {"serial": d.name, "step": str(Path(step).resolve()), "images": str(d / "images")})
            for d in sorted(path.iterdir()) if d.is_dir() and not d.name.startswith(".")]
    if not rows:
        raise InputError(path, "no SERIAL/images/ sub-folders")
    return rows
