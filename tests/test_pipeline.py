"""A whole `inspect` run on the bundled sample parts."""

import hashlib
import json
import shutil
from importlib import resources

import cv2
import jsonschema
import numpy as np
import pytest

from partinspect.cli import main

SCHEMA = json.loads(resources.files("partinspect.reports").joinpath("schemas/report-1.schema.json").read_text())


def digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def plate(repo):
    part = repo / "examples" / "plate" / "part.step"
    if not (part.parent / "images" / "left.png").exists():
        pytest.fail("examples/plate/images is missing: render it with inspect render (see README)")
    return part


@pytest.fixture
def workdir(tmp_path, plate):
    # A copy under a path with a space and non-ASCII letters, as users have.
    d = tmp_path / "Prüfung 1"
    shutil.copytree(plate.parent, d / "plate", ignore=shutil.ignore_patterns("truth.json", "make_part.py"))
    return d / "plate"


def test_run_reports_unmeasured_features_and_never_passes(workdir, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    before = digest(workdir)
    out = tmp_path / "out dir"
    code = main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(out), "-q"])
    assert code == 3, capsys.readouterr().err
    assert digest(workdir) == before  # inputs never written
    report = json.loads((out / "report.json").read_text())
    jsonschema.validate(report, SCHEMA)
    assert report["verdict"] == "inconclusive"
    assert report["features"] and all(f["measured"] is None for f in report["features"])
    assert {f["status"] for f in report["features"]} == {"not measured"}
    assert all(c["measured"] is None and c["decision"] == "inconclusive" for c in report["characteristics"])
    assert {i["role"] for i in report["inputs"]} >= {"part", "left image", "right image", "calibration"}
    html = (out / "report.html").read_text()
    assert "inconclusive" in html and "Prüfung 1" in html
    first = digest(out)
    # Same inputs, same outputs, byte for byte; a second run replaces the first cleanly.
    assert main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(out), "-q"]) == 3
    assert digest(out) == first
    assert sorted(p.name for p in out.iterdir()) == ["junit.xml", "report.html", "report.json"]


def test_image_of_wrong_size_is_refused_before_anything_is_written(workdir, tmp_path, capsys):
    right = workdir / "images" / "right.png"
    img = cv2.imread(str(right), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(right), img[:-8])
    out = tmp_path / "out"
    code = main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f"inspect: error: {right}: image is ") and err.count("\n") == 1
    assert not out.exists()


def test_black_image_is_refused(workdir, tmp_path, capsys):
    left = workdir / "images" / "left.png"
    img = cv2.imread(str(left), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(left), np.zeros_like(img))
    code = main([str(workdir / "part.step"), str(workdir / "images"), "-o", str(tmp_path / "o"), "-q"])
    assert code == 2
    assert "all black" in capsys.readouterr().err
