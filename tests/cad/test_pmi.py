"""Semantic PMI read from the NIST CTC/FTC AP242 files.

Where the expected numbers come from: the label counts per file are those
OCCT's XCAF gives for these files (recorded in issue 40 for OCCT 7.9.3);
every value is checked against the file's own text (the entity and its
line are named at each assert), which is what the NIST test-case drawings
put into the STEP file; the entity counts are counted in the text by the
test itself, so that the reader is cross-checked and not just replayed.
"""

import functools
import math
import re
from collections import Counter

import numpy as np
import pytest

from partinspect.cad.pmi import INCH, read_pmi, step_tolerance_values
from partinspect.errors import InputError

from .conftest import EXAMPLES, STEP_DIR

CTC_01 = STEP_DIR / "nist_ctc_01_asme1_ap242-e1.stp"
CTC_03 = STEP_DIR / "nist_ctc_03_asme1_ap242-e2.stp"
FTC_09 = STEP_DIR / "nist_ftc_09_asme1_ap242-e1.stp"


@functools.lru_cache(maxsize=None)
def _read(path):
    """Each file read once for the module (a NIST read takes 0.2-2 s)."""
    return read_pmi(path)


@pytest.fixture(scope="module")
def ctc01():
    return _read(CTC_01)


@pytest.fixture(scope="module")
def ctc03():
    return _read(CTC_03)


@pytest.fixture(scope="module")
def ftc09():
    return _read(FTC_09)


def _count(path, entity):
    """How many entities of a type the file's text holds (simple or in a compound)."""
    return len(re.findall(rf"\b{entity}\s*\(", path.read_text(encoding="latin-1")))


def _by_name(pmi, name):
    (item,) = [i for i in pmi.items if i.name == name]
    return item


def test_ctc01_counts(ctc01):
    # Labels as XCAF lists them (issue 40): 21 dimensions, 6 tolerances, 11 datum labels.
    assert ctc01.labels == {"dimensions": 21, "tolerances": 6, "datums": 11}
    dims = ctc01.of_kind("dimension")
    # 9 of the 21 are graphics only; the rest are the file's DIMENSIONAL_SIZE /
    # DIMENSIONAL_LOCATION / ANGULAR_LOCATION entities, one item each.
    assert ctc01.presentation_only == 9
    semantic = _count(CTC_01, "DIMENSIONAL_SIZE") + _count(CTC_01, "DIMENSIONAL_LOCATION") + _count(CTC_01, "ANGULAR_LOCATION")
    assert len(dims) == semantic == 12
    # Only dimensions with a DIMENSIONAL_CHARACTERISTIC_REPRESENTATION have a value.
    assert sum(d.value is not None for d in dims) == _count(CTC_01, "DIMENSIONAL_CHARACTERISTIC_REPRESENTATION") == 8
    assert Counter(t.type for t in ctc01.of_kind("tolerance")) == {
        "position": 2, "profile_of_surface": 2, "perpendicularity": 1, "flatness": 1}
    # The 11 datum labels repeat A, B and C for each tolerance using them.
    assert [d.id for d in ctc01.of_kind("datum")] == ["datum-A", "datum-B", "datum-C"]
    assert ctc01.unread == ()


def test_ctc01_values(ctc01):
    # Every ctc_01 tolerance magnitude is a compound measure entity OCCT
    # reads as 0: the values come from the text. FLATNESS_TOLERANCE #57 ->
    # #82 LENGTH_MEASURE(0.2) (line 121); Position.1 #21 -> #95 LENGTH_MEASURE(0.75) (line 247).
    flat = _by_name(ctc01, "Flatness.1")
    assert flat.value == pytest.approx(0.2)
    assert any("file's text" in n for n in flat.notes)
    pos = _by_name(ctc01, "Position.1")
    assert pos.value == pytest.approx(0.75)
    assert pos.datums == ("A", "B", "C")
    assert len(pos.faces) == 2  # a hole split into two half-cylinders
    # Datum A is the face the flatness applies to (the part's base plane).
    assert ctc01["datum-A"].faces == flat.faces
    perp = _by_name(ctc01, "Perpendicularity.1")
    assert perp.value == pytest.approx(1.5) and perp.datums == ("A",)
    assert "All_Around" in _by_name(ctc01, "Position surfacic profile.2").modifiers


def test_ctc01_dimensions(ctc01):
    dims = {d.id: d for d in ctc01.of_kind("dimension")}
    # A diameter 35 +0/-0.2: the lower deviation is negative (OCCT gives its size, 0.2).
    d4 = dims["dim-4"]
    assert (d4.type, d4.value, d4.upper, d4.lower) == ("diameter", 35.0, 0.0, -0.2)
    assert len(d4.faces) == 2
    # The 60 deg +-0.5 deg angle (ANGULAR_LOCATION #33) in radians.
    angle = [d for d in dims.values() if d.type == "angle"]
    assert len(angle) == 1 and angle[0].unit == "rad"
    assert angle[0].value == pytest.approx(math.radians(60))
    assert angle[0].upper == pytest.approx(math.radians(0.5)) and angle[0].lower == pytest.approx(-math.radians(0.5))
    # The two basic linear distances have no value in the file: said, not guessed.
    unknown = [d for d in dims.values() if d.value is None]
    assert len(unknown) == 4 and all(d.notes for d in unknown)


def test_ctc03_inch_pmi_on_mm_geometry(ctc03):
    assert ctc03.labels == {"dimensions": 18, "tolerances": 12, "datums": 26}
    # Position.3 #? -> LENGTH_MEASURE(0.05) in inch (line 53 onwards): 1.27 mm, at MMC, diameter zone.
    pos = _by_name(ctc03, "Position.3")
    assert pos.value == pytest.approx(0.05 * INCH)
    assert "MMC" in pos.modifiers and "diameter_zone" in pos.modifiers
    assert pos.datums == ("A", "B", "C")
    # The 0.438 in diameter (+-0.005 in): the nominal is scaled, the limits were already mm.
    d = [x for x in ctc03.of_kind("dimension") if x.type == "diameter" and x.value == pytest.approx(0.438 * INCH)]
    assert d and d[0].upper == pytest.approx(0.005 * INCH) and d[0].lower == pytest.approx(-0.005 * INCH)
    # The per-area flatness OCCT drops is kept as unread, with its value.
    assert ctc03.unread == (("Flatness.1", "FLATNESS_TOLERANCE", pytest.approx(0.005 * INCH)),)


def test_ctc03_datums_at_their_material_boundary_are_said(ctc03):
    """ctc_03's gtol-5 (the NIST drawing's position 1.27 mm at MMC | A | B(M) | C(M)): the datum
    modifiers are read, and the datum shift they allow is said, not dropped."""
    from partinspect.tolerances.pmi_text import describe_item

    item = next(i for i in ctc03.items if i.id == "gtol-5")
    assert {"datum_B_MMB", "datum_C_MMB"} <= set(item.modifiers) and "datum_A_MMB" not in item.modifiers
    assert any("datum B at MMB" in n and "shift as a pattern" in n for n in item.notes)
    text = describe_item(item)
    assert "| A | B(M) | C(M)" in text and "datum shift" in text
    others = [i for i in ctc03.items if i.kind == "tolerance" and i.id != "gtol-5"]
    assert not any(m.startswith("datum_") for i in others for m in i.modifiers)


def test_ftc09_counts_and_inch_nominals(ftc09):
    assert ftc09.labels == {"dimensions": 27, "tolerances": 31, "datums": 76}
    tols = ftc09.of_kind("tolerance")
    # 23 of them position: one POSITION_TOLERANCE entity each in the text.
    assert sum(t.type == "position" for t in tols) == _count(FTC_09, "POSITION_TOLERANCE") == 23
    # OCCT reads these values itself; they agree with the text's, name by name.
    text = {}
    for name, _, value in step_tolerance_values(FTC_09):
        text.setdefault(name, set()).add(round(value, 6))
    assert all(round(t.value, 6) in text[t.name] for t in tols)
    # The 0.234 in diameter with +-0.008 in limits (issue 40's example).
    d1 = ftc09["dim-1"]
    assert d1.value == pytest.approx(0.234 * INCH) and d1.upper == pytest.approx(0.008 * INCH)
    assert any("inch" in n for n in d1.notes)
    assert [d.name for d in ftc09.of_kind("datum")] == list("ABCDEFGH")


def test_text_and_xcaf_tolerances_add_up(ctc01, ctc03, ftc09):
    # Every geometric tolerance in the text is either read or listed as unread.
    for path, pmi in ((CTC_01, ctc01), (CTC_03, ctc03), (FTC_09, ftc09)):
        assert len(pmi.of_kind("tolerance")) + len(pmi.unread) == len(step_tolerance_values(path))


def test_file_without_pmi_gives_none():
    pmi = read_pmi(EXAMPLES / "plate" / "part.step")
    assert not pmi and pmi.items == () and pmi.labels == {"dimensions": 0, "tolerances": 0, "datums": 0}


def test_not_a_step_file(tmp_path):
    bad = tmp_path / "x.step"
    bad.write_text("hello")
    with pytest.raises(InputError, match="not a STEP file"):
        read_pmi(bad)


# Per file: dimension / tolerance / datum labels as OCCT 7.9.3 lists them
# (issue 40), and the geometric tolerances it does not read (the text's
# count minus the read ones: ctc_03 a per-area flatness, ctc_04 one
# position, ftc_10 a per-length straightness, an all-over profile and three
# pattern positions).
AP242 = {
    "nist_ctc_01_asme1_ap242-e1.stp": ((21, 6, 11), 0),
    "nist_ctc_02_asme1_ap242-e2.stp": ((15, 22, 87), 0),
    "nist_ctc_03_asme1_ap242-e2.stp": ((18, 12, 26), 1),
    "nist_ctc_04_asme1_ap242-e1.stp": ((13, 6, 15), 1),
    "nist_ftc_08_asme1_ap242-e1.stp": ((13, 33, 76), 0),
    "nist_ftc_09_asme1_ap242-e1.stp": ((27, 31, 76), 0),
    "nist_ftc_10_asme1_ap242-e2.stp": ((36, 35, 77), 5),
}


@pytest.mark.parametrize("name", sorted(AP242))
def test_every_ap242_file(name):
    path = STEP_DIR / name
    pmi = _read(path)
    labels, n_unread = AP242[name]
    assert (pmi.labels["dimensions"], pmi.labels["tolerances"], pmi.labels["datums"]) == labels
    text = step_tolerance_values(path)
    assert len(text) == len(pmi.of_kind("tolerance")) + len(pmi.unread)
    assert len(pmi.unread) == n_unread
    # Every tolerance has a value, and it is the text's for its name.
    by_name = {}
    for tname, _, value in text:
        by_name.setdefault(tname, set()).add(round(value, 6))
    assert all(t.value is not None and round(t.value, 6) in by_name[t.name] for t in pmi.of_kind("tolerance"))
    # Every semantic dimension and every graphics-only one is accounted for.
    assert len(pmi.of_kind("dimension")) + pmi.presentation_only == labels[0]
    # Every datum letter a tolerance names is a datum item.
    letters = {d.name for d in pmi.of_kind("datum")}
    assert {x for t in pmi.of_kind("tolerance") for x in t.datums} <= letters


def test_rd_files_have_no_pmi():
    for name in ("nist_ctc_01_asme1_rd.stp", "nist_ftc_06_asme1_rd.stp", "nist_ftc_11_asme1_rb.stp"):
        assert not read_pmi(STEP_DIR / name)


def test_missing_magnitude_is_said(tmp_path):
    bad = tmp_path / "bad.stp"
    text = CTC_01.read_text(encoding="latin-1")
    line = "#57=FLATNESS_TOLERANCE('Flatness.1','',#82,#297);"
    assert line in text
    bad.write_text(text.replace(line, line.replace("#82", "#999999")), encoding="latin-1")
    flat = _by_name(read_pmi(bad), "Flatness.1")
    assert flat.value is None and "missing" in flat.notes[-1]


@pytest.mark.parametrize("name", ["nist_ctc_01_asme1_ap242-e1.stp", "nist_ftc_10_asme1_ap242-e2.stp"])
def test_face_ids_agree_with_the_step_loader(name):
    # ftc_10's XCAF shape also holds 18 faces of loose shells (supplemental
    # geometry) beside the solid's 264: they must not shift the ids.
    from partinspect.cad.features import face_inventory
    from partinspect.cad.step import load_step

    path = STEP_DIR / name
    pmi = _read(path)
    loaded = face_inventory(load_step(path))
    assert len(pmi.faces) == len(loaded)
    for a, b in zip(pmi.faces, loaded):
        assert a.id == b.id and a.surface == b.surface
        np.testing.assert_allclose(a.centroid, b.centroid, atol=1e-6)
    if name.startswith("nist_ftc_10"):
        loose = [i for i in pmi.items if any("supplemental" in n for n in i.notes)]
        assert len(loose) == 8
