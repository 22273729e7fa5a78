"""Manifests: CSV, YAML and folder layouts; every bad line named with its file and line."""

import re
import shutil
import subprocess
import sys
from datetime import datetime

import pytest

from partinspect.cli import main
from partinspect.errors import InputError
from partinspect.production.manifest import read_manifest


@pytest.fixture
def line(tmp_path, repo):
    """A production line's folder: two part numbers' STEP files and three image folders."""
    for name in ("plate", "bracket"):
        shutil.copy(repo / "examples" / name / "part.step", tmp_path / f"{name}.step")
    for serial in ("S1", "S2", "S3"):
        (tmp_path / serial / "images").mkdir(parents=True)
    (tmp_path / "spec.yaml").write_text("units: mm\n")
    return tmp_path


def test_csv_manifest_reads_good_lines_and_names_each_bad_one(line):
    m = line / "m.csv"
    m.write_text("serial,step,images,spec,time\n"
                 "S1,plate.step,S1/images,spec.yaml,2026-03-01T08:00:00+01:00\n"
                 "S2,missing.step,S2/images,,\n"
                 "\n"
                 "S3,bracket.step,S3/images,,yesterday\n"
                 "S1,plate.step,S3/images,,\n"
                 "../x,plate.step,S3/images,,\n"
                 "S4,plate.step,S4/images,,\n"
                 "S5,bracket.step,S2/images,,2026-03-01 09:00\n")
    jobs, problems = read_manifest(m)
    assert [(j.serial, j.step.name, j.line) for j in jobs] == [("S1", "plate.step", 2), ("S5", "bracket.step", 9)]
    assert jobs[0].images == (line / "S1" / "images").resolve() and jobs[0].spec == (line / "spec.yaml").resolve()
    assert jobs[0].time == datetime(2026, 3, 1, 7, 0)   # UTC
    assert jobs[1].time == datetime(2026, 3, 1, 9, 0) and jobs[1].spec is None
    assert problems == [
        f"{m}:3: STEP file missing.step not found",
        f"{m}:5: time 'yesterday' is not an ISO 8601 time stamp (YYYY-MM-DDThh:mm:ss)",
        f"{m}:6: serial S1 again (first on line 2)",
        f"{m}:7: serial '../x' is not a folder name (letters, digits, '.', '_', '-')",
        f"{m}:8: images folder S4/images not found",
    ]


def test_yaml_manifest_with_defaults_and_line_numbers(line):
    m = line / "m.yaml"
    m.write_text("step: plate.step\nparts:\n  - {serial: S1, images: S1/images, time: 2026-03-01T08:00:00+02:00}\n"
                 "  - serial: S2\n    images: S2/images\n    step: bracket.step\n"
                 "  - {serial: S3, images: S3/images, colour: red}\n  - just a string\n")
    jobs, problems = read_manifest(m)
    assert [(j.serial, j.step.name) for j in jobs] == [("S1", "plate.step"), ("S2", "bracket.step")]
    assert jobs[0].time == datetime(2026, 3, 1, 6, 0) and jobs[1].time is None  # YAML's own time stamp, in UTC
    assert problems == [f"{m}:7: unknown column(s) colour (expected serial, step, images, spec, time, subgroup)",
                        f"{m}:8: unknown column(s) (not a mapping) (expected serial, step, images, spec, time, subgroup)"]


def test_folder_layout_needs_the_step_file(line):
    batch = line / "parts"
    for s in ("A1", "A2"):
        (batch / s / "images").mkdir(parents=True)
    (batch / "A3").mkdir()
    jobs, problems = read_manifest(batch, step=line / "plate.step")
    assert [j.serial for j in jobs] == ["A1", "A2"] and all(j.step.name == "plate.step" for j in jobs)
    assert problems == [f"{batch / 'A3'}: images folder {batch / 'A3' / 'images'} not found"]
    with pytest.raises(InputError, match="needs the STEP file"):
        read_manifest(batch)


@pytest.mark.parametrize("text, message", [
    ("", "the manifest is empty"),
    ("serial,images\nS1,S1/images\n", "line 1: the header lacks column(s) step"),
    ("serial,step,images\n", "the manifest lists no part"),
])
def test_unreadable_manifests(line, text, message):
    m = line / "m.csv"
    m.write_text(text)
    with pytest.raises(InputError, match=re.escape(message)):
        read_manifest(m)


def test_batch_of_bad_lines_only_exits_2_naming_each_and_writes_nothing(line, capsys):
    m = line / "m.csv"
    m.write_text("serial,step,images\nS1,none.step,S1/images\nS2,plate.step,nowhere\n")
    out = line / "out"
    assert main(["batch", str(m), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f"inspect batch: {m}:2: STEP file none.step not found",
                   f"inspect batch: {m}:3: images folder nowhere not found",
                   f"inspect: error: {m}: no part to inspect: every line has a problem (2)"]
    assert not out.exists()


def test_batch_refuses_a_missing_manifest_and_bad_options(line, capsys):
    assert main(["batch", str(line / "none.csv"), "-o", str(line / "out")]) == 2
    assert capsys.readouterr().err.strip() == f"inspect: error: {line / 'none.csv'}: manifest not found"
    m = line / "m.csv"
    m.write_text("serial,step,images\nS1,plate.step,S1/images\n")
    assert main(["batch", str(m), "-o", str(line / "out"), "--workers", "0"]) == 2
    assert "--workers 0: at least one worker" in capsys.readouterr().err
    assert not (line / "out").exists()


def test_batch_and_spc_help_import_no_heavy_library():
    code = (
        "import sys\nfrom partinspect.cli import main\n"
        "for sub in ('batch', 'spc'):\n"
        "    try:\n        main([sub, '--help'])\n    except SystemExit as e:\n        assert e.code == 0\n"
        "heavy = [m for m in ('cadquery', 'numpy', 'sqlalchemy', 'distributed', 'dask', 'plotly', 'yaml') "
        "if m in sys.modules]\nprint('HEAVY', heavy, file=sys.stderr)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "HEAVY []" in out.stderr
    assert "--scheduler tcp://HOST:PORT" in out.stdout and "inspect spc" in out.stdout


def test_a_subgroup_column_names_each_part_s_rational_subgroup(line):
    m = line / "m.csv"
    m.write_text("serial,step,images,subgroup\nS1,plate.step,S1/images,lot-7\nS2,plate.step,S2/images, \n"
                 f"S3,plate.step,S3/images,{'x' * 201}\n")
    jobs, problems = read_manifest(m)
    assert [(j.serial, j.subgroup) for j in jobs] == [("S1", "lot-7"), ("S2", None)]
    assert problems == [f"{m}:4: subgroup longer than 200 characters"]
