"""The calibration reader on generated and mutated files (hypothesis).

Whatever the bytes, :func:`read_calibration` either returns a valid
StereoCalibration or raises InputError naming the file: never another
exception, which the command line would show as a traceback, and never a
crash of the process (OpenCV's parser is C++: a malformed matrix header can
corrupt its heap). The reads run in a worker process, so that a crash fails
the test, with the file, instead of killing the test run.
"""

import multiprocessing
import re
import tempfile
import traceback
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st

from partinspect.errors import InputError
from partinspect.simulate.rig import default_rig
from partinspect.vision.calibration import StereoCalibration, read_calibration, validate_calibration, write_calibration

# No shrinking: a crash restarts the worker (a second or two), and the
# failing file is shown whole anyway.
# Derandomized: the same examples on every run, so CI is reproducible; the
# regressions found by earlier random runs are kept as explicit examples.
SETTINGS = settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow],
                    phases=[Phase.explicit, Phase.reuse, Phase.generate], derandomize=True)


def _valid_text(with_std=True):
    from dataclasses import replace

    rig = default_rig((640, 480), distortion=True)
    if with_std:
        rig = replace(rig, std={"intrinsics1": np.full(9, 0.1), "intrinsics2": np.full(9, 0.1),
                                "extrinsics": np.full(6, 1e-3)})
    with tempfile.TemporaryDirectory() as d:
        write_calibration(Path(d) / "calibration.yaml", rig)
        return (Path(d) / "calibration.yaml").read_text()


VALID = _valid_text()
LINES = VALID.splitlines(keepends=True)
NUMBER = re.compile(r"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")
NUMBERS = list(NUMBER.finditer(VALID))
KEYS = ["image_width", "image_height", "K1", "D1", "K2", "D2", "R", "T",
        "std_intrinsics1", "std_intrinsics2", "std_extrinsics"]


def _read(target):
    """In the worker: the outcome of reading ``target``, as plain data."""
    try:
        calib = read_calibration(target)
    except InputError as e:
        return "InputError", e.path, e.problem
    except Exception:
        return "other", None, traceback.format_exc()
    try:
        validate_calibration(calib)
    except InputError as e:
        return "invalid", None, str(e)
    return "ok", None, calib


class Reader:
    """One worker process, restarted after a crash."""

    def __init__(self):
        self.pool = None

    def __call__(self, target):
        if self.pool is None:
            self.pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
        try:
            return self.pool.submit(_read, target).result(timeout=60)
        except BrokenProcessPool:
            self.close()
            return "crash", None, "the worker process died (a heap corrupted by an earlier read may abort later)"

    def close(self):
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)
            self.pool = None


_READER = Reader()


@pytest.fixture(scope="module", autouse=True)
def _worker():
    yield
    _READER.close()


def check(data, name="calibration.yaml"):
    """Write ``data`` (bytes) and read it; the outcome must be one of the two allowed."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / name
        path.write_bytes(data)
        for target in (str(path), d):  # the file itself, and the folder holding it
            outcome, where, what = _READER(target)
            assert outcome in ("ok", "InputError"), f"{outcome}: {what}\non the file:\n{data!r}"
            if outcome == "InputError":
                assert where == str(path), (where, what)
                assert what and "\n" not in what
            else:
                calib = what
                assert isinstance(calib, StereoCalibration)
                assert calib.image_size is not None
                assert np.all(np.isfinite(calib.K1)) and np.linalg.norm(calib.T) > 0


# ------------------------------------------------------------ mutations


replacement_numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**30, 10**30).map(str),
    st.sampled_from(["nan", ".nan", "-.inf", ".Inf", "1e999", "-0", "0x1F", "1_000", "", "~", "null", "[]", "{}",
                     "'3'", '"x"', "3,", "- 3"]),
    st.text(max_size=8),
)


@SETTINGS
@given(st.lists(st.tuples(st.integers(0, len(NUMBERS) - 1), replacement_numbers), min_size=1, max_size=4))
def test_numbers_replaced(changes):
    text = VALID
    # Replace from the end so the earlier spans stay valid.
    for k, new in sorted(dict(changes).items(), reverse=True):
        m = NUMBERS[k]
        text = text[: m.start()] + new + text[m.end():]
    check(text.encode("utf-8", "surrogatepass"))


@SETTINGS
@given(st.data())
def test_lines_deleted_duplicated_or_swapped(data):
    lines = list(LINES)
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["delete", "duplicate", "swap", "indent", "dedent"]))
        i = data.draw(st.integers(0, len(lines) - 1))
        if op == "delete":
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "swap":
            j = data.draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "indent":
            lines[i] = "   " + lines[i]
        else:
            lines[i] = lines[i].lstrip()
        if not lines:
            break
    check("".join(lines).encode())


@SETTINGS
@given(st.integers(0, len(VALID.encode())), st.binary(max_size=16), st.booleans())
@example(position=238, junk=b"\xc0", truncate=False)  # a non-UTF-8 byte inside a matrix's field name
def test_truncated_or_with_bytes_inserted(position, junk, truncate):
    raw = VALID.encode()
    check(raw[:position] if truncate else raw[:position] + junk + raw[position:])


@SETTINGS
@given(st.data())
def test_matrix_headers_changed(data):
    text = VALID
    field = data.draw(st.sampled_from(["rows", "cols", "dt"]))
    spans = [m for m in re.finditer(rf"{field}: (\S+)", text)]
    m = data.draw(st.sampled_from(spans))
    if field == "dt":
        new = data.draw(st.sampled_from(["u", "c", "w", "s", "i", "f", "d", "h", "x", "2d", "", "dd"]))
    else:
        new = str(data.draw(st.integers(-3, 20)))
    check((text[: m.start(1)] + new + text[m.end(1):]).encode())


@SETTINGS
@given(st.sampled_from(KEYS), st.sampled_from(KEYS + ["k1", "image-width", "", "R ", "T:", "K1K1"]))
def test_keys_renamed(key, new):
    check(re.sub(rf"^{re.escape(key)}:", f"{new}:", VALID, count=1, flags=re.M).encode())


# ------------------------------------------------------ generated files


def _matrix(rows, cols, dt, values):
    data = ", ".join(values)
    return f"!!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: {dt}\n   data: [ {data} ]\n"


scalars = st.one_of(st.integers(-5, 5000).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                    st.sampled_from(["abc", "'7'", "[1, 2]", "{a: 1}", "~", ".nan"]))
values = st.one_of(
    st.floats(-1e4, 1e4, allow_nan=False).map(lambda v: f"{v!r}"),
    st.sampled_from(["nan", ".nan", ".inf", "-.inf", "0", "1", "x"]),
)
matrices = st.builds(
    _matrix,
    st.integers(0, 4),
    st.integers(0, 4),
    st.sampled_from(["d", "f", "i", "u", "s"]),
    st.lists(values, max_size=16),
)


@SETTINGS
@given(st.dictionaries(st.sampled_from(KEYS), st.one_of(scalars, matrices), max_size=len(KEYS)),
       st.booleans())
def test_generated_documents(entries, with_header):
    body = "".join(f"{k}: {v}\n" if not v.startswith("!!") else f"{k}: {v}" for k, v in entries.items())
    text = ("%YAML 1.2\n---\n" if with_header else "") + body
    check(text.encode())


@SETTINGS
@given(st.binary(max_size=200))
@example(b"")
@example(b"%YAML 1.2\n---\n")
@example(b"<?xml version=\"1.0\"?>\n<opencv_storage>\n<K1>1</K1></opencv_storage>\n")
@example(b"{\"K1\": [1, 2, 3]}")
@example(b"\xef\xbb\xbf%YAML:1.0\n---\nimage_width: 640\n")
def test_arbitrary_bytes(raw):
    check(raw)


@SETTINGS
@given(st.data())
def test_stereo_calib_pair_mutated(data):
    """OpenCV stereo_calib's intrinsics.yml + extrinsics.yml, one of them damaged."""
    from partinspect.simulate.rig import default_rig

    rig = default_rig((640, 480))
    intr = (VALID.split("K1:")[0] + "M1:" + VALID.split("K1:")[1].split("R:")[0]).replace("K2:", "M2:")
    extr = "%YAML 1.2\n---\nR:" + VALID.split("R:")[1].split("std_")[0]
    victim = data.draw(st.sampled_from(["intrinsics.yml", "extrinsics.yml"]))
    text = intr if victim == "intrinsics.yml" else extr
    pos = data.draw(st.integers(0, len(text)))
    junk = data.draw(st.sampled_from(["", "x", "nan", "]", "\n   rows: 9\n", "-", "0."]))
    cut = data.draw(st.booleans())
    mutated = text[:pos] + ("" if cut else junk + text[pos:])
    files = {"intrinsics.yml": intr, "extrinsics.yml": extr, victim: mutated}
    with tempfile.TemporaryDirectory() as d:
        for name, content in files.items():
            (Path(d) / name).write_text(content)
        outcome, where, what = _READER(d)
        assert outcome in ("ok", "InputError"), f"{outcome}: {what}\non {victim}:\n{mutated!r}"
        if outcome == "InputError":
            assert where in {str(Path(d) / "intrinsics.yml"), str(Path(d) / "extrinsics.yml")}, what
        else:
            assert isinstance(what, StereoCalibration)
            assert rig.K1.shape == what.K1.shape


# ----------------------------------------------- found by the tests above


def test_top_level_sequence():
    """A file whose top level is a list, not named entries (cv2 raised from getNode)."""
    check(b"-")


def test_matrix_with_rows_twice_and_no_cols():
    """cv2.FileNode.mat() on such a header corrupts the heap (OpenCV 5.0.0): a later read aborts."""
    header = "K2: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
    assert header in VALID
    bad = VALID.replace(header, "K2: !!opencv-matrix\n   rows: 3\n   rows: 3\n").encode()
    for _ in range(3):
        check(bad)
    check(VALID.encode())
