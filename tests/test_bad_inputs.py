"""Every bad input a user may bring: exit 2, one line naming the file and the problem, nothing written.

Each case starts from a fresh copy of examples/plate in tmp_path with a
previous report already in the output folder, breaks one thing, runs
``inspect`` in-process and checks that:

- the exit code is 2 and stderr is exactly one line, ``inspect: error: <file>: <problem>``;
- no traceback is printed and stdout is empty;
- nothing under tmp_path changed: inputs, the previous reports, and no
  temporary or new files.

Inputs that look unusual but are fine (16-bit, colour, alpha, paths with
spaces and non-ASCII letters) must run.
"""

import hashlib
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest

from partinspect.cli import main

REPO = Path(__file__).resolve().parents[1]
PLATE = REPO / "examples" / "plate"
PREVIOUS = {"report.json": b'{"schema": "report/1", "verdict": "pass"}\n', "junit.xml": b"<testsuites/>\n", "report.html": b"<html>old</html>\n"}


@dataclass
class Work:
    """A copy of the sample plate and the command line to run on it."""

    root: Path
    part: Path
    images: Path
    out: Path
    extra: list = field(default_factory=list)

    @property
    def calib(self):
        return self.images / "calibration.yaml"

    @property
    def tol(self):
        return self.part.with_name("part.tol.yaml")

    def argv(self):
        return [str(self.part), str(self.images), "-o", str(self.out), *self.extra]


def make_work(tmp_path, name="plate"):
    d = tmp_path / name
    shutil.copytree(PLATE, d, ignore=shutil.ignore_patterns("truth.json", "make_part.py"))
    out = tmp_path / "out"
    out.mkdir()
    for n, data in PREVIOUS.items():
        (out / n).write_bytes(data)
    return Work(tmp_path, d / "part.step", d / "images", out)


def snapshot(root):
    """Every file and folder under root with its content hash and mode."""
    snap = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        if p.is_dir():
            snap[rel] = ("dir", p.stat().st_mode)
        else:
            st = p.stat()
            if st.st_size > 100 * 2**20:  # the sparse huge STEP: size and mtime say enough
                snap[rel] = ("big", st.st_size, st.st_mtime_ns)
            else:
                snap[rel] = (hashlib.sha256(p.read_bytes()).hexdigest(), st.st_mode)
    return snap


def run(argv, capsys):
    """main() in-process; argparse usage errors end in SystemExit, which is still an exit code."""
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


# ------------------------------------------------------------ file helpers


def write_png(path, img):
    ok, buf = cv2.imencode(".png", img)
    assert ok
    path.write_bytes(buf.tobytes())


def read_png(path):
    return cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)


def random_bytes(n, seed=0):
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


def plate_calibration():
    fs = cv2.FileStorage(str(PLATE / "images" / "calibration.yaml"), cv2.FILE_STORAGE_READ)
    c = {"image_width": int(fs.getNode("image_width").real()), "image_height": int(fs.getNode("image_height").real())}
    for k in ("K1", "D1", "K2", "D2", "R", "T"):
        c[k] = fs.getNode(k).mat()
    fs.release()
    return c


def write_fs(path, entries):
    """An OpenCV FileStorage file with exactly these entries: no validation on the way."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in entries.items():
        fs.write(k, v)
    fs.release()


def calib_with(w, **changes):
    c = plate_calibration()
    for k, v in changes.items():
        if v is None:
            del c[k]
        else:
            c[k] = v
    write_fs(w.calib, c)
    return w.calib


def image_pair(w, fn):
    """Replace both images by fn(image)."""
    for n in ("left.png", "right.png"):
        p = w.images / n
        write_png(p, fn(read_png(p)))


def edit_tol(w, old, new):
    text = w.tol.read_text()
    assert old in text
    w.tol.write_text(text.replace(old, new, 1))
    return w.tol


@pytest.fixture(scope="session")
def sphere_step(tmp_path_factory):
    # A solid with no line or circle edge at all: one spherical face, a seam
    # and two degenerated pole edges.
    import cadquery as cq

    from partinspect.cad.step import save_step

    path = tmp_path_factory.mktemp("sphere") / "sphere.step"
    save_step(cq.Workplane().sphere(10).val(), path)
    return path


# --------------------------------------------------------------- the table
#
# Each case breaks the copy and returns (the path or option the message must
# name first, a regex the problem must match).


def step_missing(w):
    w.part.unlink()
    return w.part, "STEP file not found"


def step_is_folder(w):
    w.part.unlink()
    w.part.mkdir()
    return w.part, "not a regular file"


def step_empty(w):
    w.part.write_bytes(b"")
    return w.part, "empty"


def step_random_bytes(w):
    w.part.write_bytes(random_bytes(40_000))
    return w.part, "not a STEP file"


def step_truncated(w):
    data = (PLATE / "part.step").read_bytes()
    w.part.write_bytes(data[: len(data) // 2])
    return w.part, "truncated"


def step_is_png(w):
    shutil.copyfile(PLATE / "images" / "left.png", w.part)
    return w.part, "not a STEP file"


def step_huge(w):
    # Sparse: 600 MB by its size, no disk used. Refused by its size before a byte is read.
    with open(w.part, "r+b") as f:
        f.truncate(600 * 2**20)
    return w.part, r"too large \(600 MB; the limit is 500 MB\)"


def step_gzipped(w):
    import gzip

    w.part.write_bytes(gzip.compress((PLATE / "part.step").read_bytes()))
    return w.part, "compressed"


def images_folder_missing(w):
    shutil.rmtree(w.images)
    return w.images, "not found"


def left_missing(w):
    (w.images / "left.png").unlink()
    return w.images / "left.png", "image not found"


def right_missing(w):
    (w.images / "right.png").unlink()
    return w.images / "right.png", "image not found"


def left_empty(w):
    (w.images / "left.png").write_bytes(b"")
    return w.images / "left.png", "empty"


def left_random_bytes(w):
    (w.images / "left.png").write_bytes(random_bytes(10_000))
    return w.images / "left.png", "not a readable image"


def right_truncated_png(w):
    p = w.images / "right.png"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    return p, "not a readable image"


def sizes_differ(w):
    p = w.images / "right.png"
    write_png(p, read_png(p)[:-8])
    return p, r"image is 2448x2040 pixels but left.png is 2448x2048"


def size_not_calibrated(w):
    image_pair(w, lambda im: cv2.resize(im, (1224, 1024), interpolation=cv2.INTER_AREA))
    return w.images / "left.png", r"image is 1224x1024 pixels but the calibration is for 2448x2048"


def left_all_black(w):
    p = w.images / "left.png"
    write_png(p, np.zeros_like(read_png(p)))
    return p, "all black"


def right_saturated(w):
    p = w.images / "right.png"
    write_png(p, np.full_like(read_png(p), 255))
    return p, "saturated"


def right_saturated_16bit(w):
    image_pair(w, lambda im: im.astype(np.uint16) * 257)
    p = w.images / "right.png"
    write_png(p, np.full(read_png(p).shape, 65535, np.uint16))
    return p, "saturated"


def depths_differ(w):
    p = w.images / "right.png"
    write_png(p, read_png(p).astype(np.uint16) * 257)
    return p, "16-bit but left.png is 8-bit"


def calib_missing(w):
    w.calib.unlink()
    return w.images, "no calibration.yaml"


def calib_empty(w):
    w.calib.write_bytes(b"")
    return w.calib, "empty"


def calib_random_bytes(w):
    w.calib.write_bytes(random_bytes(3000))
    return w.calib, "not a readable OpenCV FileStorage"


def calib_nan(w):
    K = plate_calibration()["K1"].copy()
    K[0, 2] = np.nan
    return calib_with(w, K1=K), "K1 contains NaN"


def calib_inf_T(w):
    return calib_with(w, T=np.array([[-118.0], [np.inf], [17.8]])), "T contains NaN or infinite"


def calib_K_wrong_shape(w):
    return calib_with(w, K2=np.eye(2)), "K2 must be 3x3, got 2x2"


def calib_D_wrong_length(w):
    return calib_with(w, D1=np.zeros((1, 3))), "D1 must have 4, 5, 8, 12 or 14 coefficients, got 3"


def calib_R_wrong_shape(w):
    return calib_with(w, R=np.eye(4)), "R must be 3x3, got 4x4"


def calib_R_not_rotation(w):
    return calib_with(w, R=np.diag([1.0, 1.0, 1.1])), "R is not a rotation"


def calib_R_reflection(w):
    return calib_with(w, R=np.diag([1.0, 1.0, -1.0])), "reflection"


def calib_negative_focal(w):
    K = plate_calibration()["K1"].copy()
    K[1, 1] = -K[1, 1]
    return calib_with(w, K1=K), "K1 has a non-positive focal length"


def calib_missing_T(w):
    return calib_with(w, T=None), "missing entry 'T'"


def calib_missing_width(w):
    return calib_with(w, image_width=None), "missing entry 'image_width'"


def calib_zero_baseline(w):
    return calib_with(w, T=np.zeros((3, 1))), "T is zero"


def calib_text_in_matrix(w):
    text = w.calib.read_text().replace("data: [ 0., 0., 0., 0., 0. ]", "data: [ 0., zero, 0., 0., 0. ]", 1)
    w.calib.write_text(text)
    return w.calib, "entry .D1. is not a number or an OpenCV matrix"


def calib_only_intrinsics(w):
    w.calib.unlink()
    write_fs(w.images / "intrinsics.yml", {"M1": np.eye(3), "D1": np.zeros((1, 5)), "M2": np.eye(3), "D2": np.zeros((1, 5))})
    return w.images / "extrinsics.yml", "file not found"


def tol_typo_key(w):
    return edit_tol(w, "distances:", "distanses:"), r"line \d+: distanses: unknown key 'distanses'.*did you mean 'distances'"


def tol_typo_characteristic(w):
    return edit_tol(w, "position: {tolerance", "positon: {tolerance"), r"line 10: features\.circle-4\.positon: unknown characteristic 'positon'.*did you mean 'position'"


def tol_unknown_feature(w):
    return edit_tol(w, "circle-8:", "circle-99:"), r"line 11: features\.circle-99: no feature circle-99 in the CAD model"


def tol_wrong_type(w):
    return edit_tol(w, "{upper: 0.04, lower: -0.04}", "{upper: abc, lower: -0.04}"), r"line 12: features\.circle-8\.diameter\.upper: expected a number, got 'abc'"


def tol_not_mapping(w):
    return edit_tol(w, "{upper: 0.04, lower: -0.04}", "0.04"), r"line 12: features\.circle-8\.diameter: expected a mapping, got 0\.04"


def tol_negative(w):
    return edit_tol(w, "{tolerance: 0.10}", "{tolerance: -0.10}"), r"line 10: features\.circle-4\.position\.tolerance: expected a positive number, got -0\.1"


def tol_lower_above_upper(w):
    return edit_tol(w, "{upper: 0.04, lower: -0.04}", "{upper: -0.04, lower: 0.04}"), r"line 12: features\.circle-8\.diameter: lower 0\.04 is above upper -0\.04"


def tol_not_yaml(w):
    w.tol.write_text("features: [unclosed\n")
    return w.tol, "not valid YAML"


def tol_binary(w):
    w.tol.write_bytes(random_bytes(500, seed=3))
    return w.tol, "not UTF-8|not a text file|not valid YAML"


def tol_option_missing(w):
    w.extra += ["--tolerances", str(w.root / "nope.yaml")]
    return w.root / "nope.yaml", "tolerance file not found"


def tol_option_folder(w):
    w.extra += ["--tolerances", str(w.images)]
    return w.images, "not a regular file"


def out_is_file(w):
    shutil.rmtree(w.out)
    w.out.write_bytes(b"not a folder")
    return w.out, "exists and is not a folder"


def out_under_file(w):
    # A path below a regular file cannot be created, even by root.
    blocker = w.root / "blocker"
    blocker.write_bytes(b"x")
    w.out = blocker / "out"
    return w.out, "is not a folder"


def unknown_option(w):
    w.extra += ["--tolerance-file", "x"]
    return None, r"unrecognized arguments: --tolerance-file"


CASES = [
    step_missing,
    step_is_folder,
    step_empty,
    step_random_bytes,
    step_truncated,
    step_is_png,
    step_huge,
    step_gzipped,
    images_folder_missing,
    left_missing,
    right_missing,
    left_empty,
    left_random_bytes,
    right_truncated_png,
    sizes_differ,
    size_not_calibrated,
    left_all_black,
    right_saturated,
    right_saturated_16bit,
    depths_differ,
    calib_missing,
    calib_empty,
    calib_random_bytes,
    calib_nan,
    calib_inf_T,
    calib_K_wrong_shape,
    calib_D_wrong_length,
    calib_R_wrong_shape,
    calib_R_not_rotation,
    calib_R_reflection,
    calib_negative_focal,
    calib_missing_T,
    calib_missing_width,
    calib_zero_baseline,
    calib_text_in_matrix,
    calib_only_intrinsics,
    tol_typo_key,
    tol_typo_characteristic,
    tol_unknown_feature,
    tol_wrong_type,
    tol_not_mapping,
    tol_negative,
    tol_lower_above_upper,
    tol_not_yaml,
    tol_binary,
    tol_option_missing,
    tol_option_folder,
    out_is_file,
    out_under_file,
    unknown_option,
]


def assert_refused(code, out, err, named, problem):
    assert code == 2, err
    assert "Traceback" not in err and "Traceback" not in out
    assert out == ""
    assert err.endswith("\n") and err.count("\n") == 1, f"not one line: {err!r}"
    assert not err.startswith("inspect: internal error"), err
    if named is None:
        m = re.fullmatch(r"inspect: error: (.*)\n", err)
    else:
        prefix = f"inspect: error: {named}: "
        assert err.startswith(prefix), f"expected the message to start with {prefix!r}: {err!r}"
        m = re.fullmatch(re.escape(prefix) + r"(.*)\n", err)
    assert m and re.search(problem, m.group(1)), f"{problem!r} not in {err!r}"


@pytest.mark.parametrize("case", CASES, ids=lambda f: f.__name__)
def test_bad_input_is_refused_and_nothing_changes(case, tmp_path, capsys):
    w = make_work(tmp_path)
    named, problem = case(w)
    before = snapshot(tmp_path)
    code, out, err = run(w.argv(), capsys)
    assert_refused(code, out, err, named, problem)
    assert snapshot(tmp_path) == before


def test_step_without_line_or_circle_edges(tmp_path, sphere_step, capsys):
    w = make_work(tmp_path)
    shutil.copyfile(sphere_step, w.part)
    w.tol.unlink()  # its ids are the plate's, not the sphere's
    before = snapshot(tmp_path)
    code, out, err = run(w.argv(), capsys)
    assert_refused(code, out, err, w.part, r"^no line or circle edges to measure \(its edges: .*seam")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("case", [step_truncated, calib_nan, left_all_black, tol_typo_key], ids=lambda f: f.__name__)
def test_no_output_folder_is_created(case, tmp_path, capsys):
    w = make_work(tmp_path)
    shutil.rmtree(w.out)
    w.out = tmp_path / "new" / "out"
    named, problem = case(w)
    code, out, err = run(w.argv(), capsys)
    assert_refused(code, out, err, named, problem)
    assert not (tmp_path / "new").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders; out_under_file covers root")
def test_output_folder_not_writable(tmp_path, capsys):
    w = make_work(tmp_path)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        w.out = locked / "out"
        before = snapshot(tmp_path)
        code, out, err = run(w.argv(), capsys)
        assert_refused(code, out, err, w.out, "not writable")
        assert snapshot(tmp_path) == before
    finally:
        locked.chmod(0o700)


# ------------------------------------------------------ unusual but fine


def to_16bit(w):
    # The full 16-bit range, not a shifted copy, so a reader that wraps or clips shows.
    image_pair(w, lambda im: im.astype(np.uint16) * 257)


def to_colour(w):
    image_pair(w, lambda im: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR))


def to_colour_alpha(w):
    image_pair(w, lambda im: cv2.cvtColor(im, cv2.COLOR_GRAY2BGRA))


def to_16bit_colour(w):
    image_pair(w, lambda im: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR).astype(np.uint16) * 257)


@pytest.mark.parametrize("variant", [to_16bit, to_colour, to_colour_alpha, to_16bit_colour], ids=lambda f: f.__name__)
def test_image_variants_are_accepted(variant, tmp_path):
    # Checked at the reader, where the pipeline takes its images: the same
    # grey levels (in the file's scale) whatever the encoding.
    from partinspect.vision.calibration import read_calibration
    from partinspect.vision.images import read_pair

    w = make_work(tmp_path)
    calib = read_calibration(w.images)
    ref_left, ref_right, depth = read_pair(w.images, calib)
    assert depth == 8
    variant(w)
    left, right, depth = read_pair(w.images, calib)
    scale = 257.0 if "16" in variant.__name__ else 1.0
    assert depth == (16 if scale > 1 else 8)
    # BT.601 luma of a grey pixel is the grey level (OpenCV rounds to the integer).
    np.testing.assert_allclose(left, ref_left * scale, atol=scale * 0.5 + 1e-6)
    np.testing.assert_allclose(right, ref_right * scale, atol=scale * 0.5 + 1e-6)


def test_a_noise_free_image_keeps_its_rounding_noise(tmp_path):
    # The reader keeps the file's integers: the noise estimate then knows
    # the pixels were rounded (as float32 a noise-free 8-bit render read as
    # noise 0, every edge point had a zero uncertainty and the chain stopped
    # with an internal error) and which value is saturation.
    from partinspect.vision.images import read_image
    from partinspect.vision.noise import QUANTISATION_STD, estimate_noise

    yy, xx = np.mgrid[0:120, 0:160]
    clean = np.where((xx - 80.3) ** 2 + (yy - 60.7) ** 2 < 35.0**2, 180, 60).astype(np.uint8)
    clean[:, :20] = 255  # a saturated stripe
    cv2.imwrite(str(tmp_path / "clean.png"), clean)
    img, depth = read_image(tmp_path / "clean.png")
    assert depth == 8 and img.dtype == np.uint8
    assert estimate_noise(img) == pytest.approx(QUANTISATION_STD)


def test_16bit_colour_pair_runs_end_to_end(tmp_path, capsys):
    w = make_work(tmp_path)
    to_16bit_colour(w)
    code, out, err = run(w.argv() + ["-q"], capsys)
    assert code == 3, err
    assert err == ""
    import json

    report = json.loads((w.out / "report.json").read_text())
    assert report["images"] == {"width": 2448, "height": 2048, "bit_depth": 16}


def test_paths_with_spaces_and_non_ascii_work(tmp_path, capsys):
    w = make_work(tmp_path, name="Prüfteil Ø12 №1")
    # Every input named with spaces and non-ASCII letters: the STEP file, the
    # images folder, the tolerance file and the output folder.
    part = w.part.with_name("Gehäuse Ø12 – Teil.step")
    w.part.rename(part)
    tol = w.root / "Toleranzen für Ø12.yaml"
    w.tol.rename(tol)
    images = w.images.with_name("Bilder über 1")
    w.images.rename(images)
    out = tmp_path / "Ausgabe δ 1"
    argv = [str(part), str(images), "-o", str(out), "--tolerances", str(tol), "-q"]
    inputs = w.part.parent
    before = snapshot(inputs)
    code, stdout, err = run(argv, capsys)
    assert code in (0, 1, 3), err
    assert err == ""
    assert snapshot(inputs) == before
    import json

    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert report["part"] == part.name
    assert report["tolerances"]["file"] == str(tol)
    # The spec was read: its own characteristics are there, with their line.
    assert any(c["rule"] == f"{tol.name} line 9" for c in report["characteristics"])
    assert sorted(p.name for p in out.iterdir()) == ["junit.xml", "report.html", "report.json"]
