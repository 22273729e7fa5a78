"""PMI carried over to edge characteristics (NIST CTC 01 and 03).

Expected values come from the files' own PMI (see tests/cad/test_pmi.py for
where each is in the file) and from their geometry, read independently here
through the feature inventory.
"""

import math
from pathlib import Path

import numpy as np
import pytest

from partinspect.cad.features import inventory
from partinspect.cad.pmi import INCH, read_pmi
from partinspect.cad.step import load_step
from partinspect.tolerances.from_pmi import spec_from_pmi
from partinspect.tolerances.resolve import characteristics_for, resolve_spec
from partinspect.tolerances.spec import dump_spec, parse_spec, spec_to_dict

STEP_DIR = Path(__file__).resolve().parents[1] / "data" / "step"


def _load(name):
    path = STEP_DIR / name
    inv = inventory(load_step(path))
    pmi = read_pmi(path)
    return pmi, inv, spec_from_pmi(pmi, inv)


@pytest.fixture(scope="module")
def ctc01():
    return _load("nist_ctc_01_asme1_ap242-e1.stp")


@pytest.fixture(scope="module")
def ctc03():
    return _load("nist_ctc_03_asme1_ap242-e2.stp")


def _non_smooth_lines(inv, face):
    return {f.id for f in inv.features if f.kind == "line" and face in f.faces and not f.smooth}


def test_every_item_is_used_or_said_to_be_not_evaluated(ctc01, ctc03):
    for pmi, _, ps in (ctc01, ctc03):
        used = set(ps.applies_to)
        skipped = {n.item for n in ps.not_evaluated}
        assert not used & skipped
        assert {i.id for i in pmi.items} <= used | skipped
        assert all(n.reason for n in ps.not_evaluated)


def test_diameter_goes_to_the_hole_rims(ctc01):
    pmi, inv, ps = ctc01
    d4 = pmi["dim-4"]  # diameter 35 +0/-0.2 on two half-cylinder faces
    rims = ps.applies_to["dim-4"]
    assert len(rims) == 2
    for cid in rims:
        f = inv[cid]
        assert f.kind == "circle" and 2 * f.radius == pytest.approx(35.0)
        assert set(f.faces) & set(d4.faces)
        assert ps.data["features"][cid]["diameter"] == {"upper": 0.0, "lower": -0.2}
        assert ps.sources[("features", cid, "diameter")] == "dim-4"


def test_flatness_goes_to_the_plane_edges_and_datum_a(ctc01):
    pmi, inv, ps = ctc01
    flat = pmi["gtol-6"]
    lines = _non_smooth_lines(inv, flat.faces[0])
    assert set(ps.applies_to["gtol-6"]) == lines
    assert all(ps.data["features"][lid]["straightness"] == {"tolerance": pytest.approx(0.2)} for lid in lines)
    # Datum A is that face; B and C point at no face in this file.
    assert set(ps.data["datums"]) == lines
    reasons = {n.item: n.reason for n in ps.not_evaluated}
    assert "no face" in reasons["datum-B"] and "no face" in reasons["datum-C"]


def test_perpendicularity_becomes_an_angle_over_the_edge_length(ctc01):
    pmi, inv, ps = ctc01
    perp = pmi["gtol-5"]  # 1.5 mm to datum A
    (angle,) = [a for i, a in enumerate(ps.data["angles"]) if ps.sources[("angles", i)] == "gtol-5"]
    line, datum_line = (inv[x] for x in angle["between"])
    assert perp.faces[0] in line.faces
    assert np.linalg.norm(np.cross(line.direction, inv[pmi["datum-A"].faces[0]].normal)) < 1e-6
    assert angle["upper"] == pytest.approx(math.degrees(math.atan(1.5 / line.length)))
    assert angle["lower"] == -angle["upper"]


def test_not_evaluated_reasons(ctc01, ctc03):
    reasons = {n.item: n.reason for n in ctc01[2].not_evaluated}
    assert "surface" in reasons["gtol-3"]  # a surface profile
    assert "plane" in reasons["gtol-1"]  # position of a slot's centre plane
    assert "no value" in reasons["dim-1"]
    reasons3 = {n.item: n for n in ctc03[2].not_evaluated}
    # The flatness OCCT drops is said, with its value from the text.
    assert "not read by OCCT" in reasons3["Flatness.1"].reason and "0.127" in reasons3["Flatness.1"].reason
    assert "thickness" in reasons3["dim-9"].reason


def test_inch_position_at_mmc(ctc03):
    pmi, inv, ps = ctc03
    pos = pmi["gtol-5"]  # Position.3: 0.05 in at MMC on the 0.438 in holes
    assert pos.name == "Position.3"
    chars = {c.id: c for c in characteristics_for(ps.spec(), inv)}
    for cid in ps.applies_to["gtol-5"]:
        assert ps.data["features"][cid]["position"]["tolerance"] == pytest.approx(0.05 * INCH)
        assert ps.data["features"][cid]["position"]["material"] == "MMC"
        assert 2 * inv[cid].radius == pytest.approx(0.438 * INCH, abs=1e-3)
        # the bonus is taken from the hole's size: 0.438 +-0.005 in, MMC 0.433 in
        m = chars[f"{cid}.position"].material
        assert m.internal and m.size.id == f"{cid}.diameter" and m.reference == pytest.approx(0.433 * INCH, abs=1e-6)
    # `inspect spec` writes the modifier, and it reads back
    again = parse_spec(dump_spec(ps.spec()))
    assert again.features[ps.applies_to["gtol-5"][0]].position.material == "MMC"


def test_spec_round_trips_and_resolves(ctc01):
    pmi, inv, ps = ctc01
    spec = ps.spec()
    again = parse_spec(dump_spec(spec))
    assert spec_to_dict(again) == spec_to_dict(spec)
    assert spec.features  # not an empty spec round-tripping
    resolved = resolve_spec(again, inv)
    by_id = {c.id: c for c in resolved.characteristics}
    c = by_id[f"{ps.applies_to['dim-4'][0]}.diameter"]
    assert (c.lower_limit, c.upper_limit) == pytest.approx((34.8, 35.0))
    # With the general tolerances, nothing is given twice.
    ids = [c.id for c in characteristics_for(spec, inv)]
    assert len(ids) == len(set(ids))


def test_spec_file_overrides_the_pmi_item_by_item(ctc01, tmp_path):
    from partinspect.tolerances.loading import load_characteristics

    pmi, inv, ps = ctc01
    a, b = ps.applies_to["dim-4"]  # the two rims of one PMI diameter
    spec_file = tmp_path / "part.tol.yaml"
    spec_file.write_text(f"features:\n  {a}:\n    diameter: {{upper: 0.01, lower: -0.01}}\n")
    resolved, chars = load_characteristics(inv, spec_file, part=STEP_DIR / "nist_ctc_01_asme1_ap242-e1.stp")
    by_id = {c.id: c for c in chars}
    assert len(by_id) == len(chars)
    assert by_id[f"{a}.diameter"].source == "spec" and by_id[f"{a}.diameter"].rule == "part.tol.yaml line 3"
    assert by_id[f"{a}.diameter"].upper_limit == pytest.approx(35.01)
    other = by_id[f"{b}.diameter"]
    assert other.source == "PMI" and "dim-4" in other.rule and "diameter 35 +0/-0.2" in other.rule
    assert (other.lower_limit, other.upper_limit) == pytest.approx((34.8, 35.0))
    # Where neither says anything, ISO 2768 still applies; what the PMI holds
    # and edges cannot check is carried to the report.
    assert any(c.source.startswith("ISO 2768") for c in chars)
    assert {n.item for n in resolved.not_evaluated} == {n.item for n in ps.not_evaluated}


def test_no_pmi_leaves_the_spec_alone():
    from partinspect.tolerances.loading import load_characteristics

    plate = Path(__file__).resolve().parents[2] / "examples" / "plate" / "part.step"
    inv = inventory(load_step(plate))
    with_part = load_characteristics(inv, None, part=plate)
    without = load_characteristics(inv, None)
    assert with_part[0].not_evaluated == ()
    assert [c.to_dict() for c in with_part[1]] == [c.to_dict() for c in without[1]]


def test_zero_position_at_mmc_is_all_bonus(ctc01):
    # ASME Y14.5 allows "0 (M)": all the tolerance is bonus from the size
    # (ftc_10 has one at MMC, one at LMC); a zero without a modifier is no zone.
    from partinspect.cad.pmi import Pmi, PmiItem

    pmi, inv, _ = ctc01
    hole = pmi["dim-4"].faces
    items = (pmi["dim-4"],
             PmiItem("gtol-1", "tolerance", "position", "Position.0", 0.0, modifiers=("MMC",), faces=hole),
             PmiItem("gtol-2", "tolerance", "position", "Position.1", 0.0, faces=hole))
    ps = spec_from_pmi(Pmi(items), inv)
    reasons = {n.item: n.reason for n in ps.not_evaluated}
    assert reasons["gtol-2"] == "zero tolerance" and "gtol-1" not in reasons
    assert all(ps.data["features"][c]["position"] == {"tolerance": 0.0, "material": "MMC"} for c in ps.applies_to["gtol-1"])
    chars = {c.id: c for c in characteristics_for(ps.spec(), inv)}
    for cid in ps.applies_to["gtol-1"]:
        # the hole's size is the PMI's 35 +0/-0.2: at MMC 34.8 mm
        c = chars[f"{cid}.position"]
        assert c.upper_limit == 0 and c.material.reference == pytest.approx(34.8) and c.material.internal


def test_unusable_pmi_falls_back_and_says_so(ctc01, monkeypatch):
    from partinspect.tolerances import from_pmi
    from partinspect.tolerances.loading import load_characteristics

    _, inv, _ = ctc01

    def broken(part, inventory):
        raise ValueError("datum reference to a missing entity #4711")

    monkeypatch.setattr(from_pmi, "load_pmi_spec", broken)
    resolved, chars = load_characteristics(inv, None, part=STEP_DIR / "nist_ctc_01_asme1_ap242-e1.stp")
    (why,) = resolved.not_evaluated
    assert "#4711" in why.reason and "ISO 2768 apply instead" in why.reason
    assert all(c.source.startswith("ISO 2768") for c in chars)


def test_parallelism_to_a_datum_plane_becomes_a_tilt_over_the_edge_length():
    # ftc_08: five parallelism tolerances; 0.762 mm of face-121 (datum D) to datum A, and 0.508 mm of
    # face-118 to D map to the longest edge of the face against a parallel edge of the datum plane;
    # the other three sit on faces no straight edge bounds.
    pmi, inv, ps = _load("nist_ftc_08_asme1_ap242-e1.stp")
    par = [i for i in pmi.items if i.type == "parallelism"]
    assert [(i.id, i.value) for i in par] == [("gtol-1", 0.381), ("gtol-3", 0.762), ("gtol-7", 0.381),
                                             ("gtol-8", 0.762), ("gtol-30", 0.508)]
    reasons = {n.item: n.reason for n in ps.not_evaluated}
    for gid in ("gtol-1", "gtol-7", "gtol-8"):
        assert "no straight edge bounds the face" in reasons[gid]
    datum = {i.name: i.faces for i in pmi.items if i.kind == "datum"}
    for gid in ("gtol-3", "gtol-30"):
        item = pmi[gid]
        (k,) = [k for k, v in ps.sources.items() if v == gid]
        entry = ps.data["angles"][k[1]]
        line, dl = (inv[x] for x in entry["between"])
        assert item.faces[0] in line.faces and datum[item.datums[0]][0] in dl.faces
        assert line.length == max(f.length for f in inv.features if f.kind == "line" and item.faces[0] in f.faces
                                  and not f.smooth)
        assert entry["towards"] == pytest.approx(list(inv[datum[item.datums[0]][0]].normal))
        assert entry["upper"] == pytest.approx(math.degrees(math.atan(item.value / line.length)))
        assert entry["lower"] == -entry["upper"]
    chars = {c.id: c for c in resolve_spec(parse_spec(dump_spec(ps.spec())), inv).characteristics}
    c = chars["angle(line-33,line-2)"]  # gtol-3: 0.762 mm over the 152.4 mm edge
    assert c.type == "parallelism" and c.upper_limit == pytest.approx(math.atan(0.762 / 152.4))


def test_perpendicularity_nominal_is_the_right_angle_between_planes(ctc01):
    # ctc_01 gtol-5 and ftc_10 gtol-8 pair an edge of the face with a datum-plane edge that does not
    # meet it (50 and 72 mm apart); the angle they bound is the planes', 90 degrees (was 90.68 and 103.49).
    for (pmi, inv, ps), gid, pair in ((ctc01, "gtol-5", ["line-214", "line-106"]),
                                      (_load("nist_ftc_10_asme1_ap242-e2.stp"), "gtol-8", ["line-204", "line-85"])):
        (k,) = [k for k, v in ps.sources.items() if v == gid]
        entry = ps.data["angles"][k[1]]
        assert entry["between"] == pair
        face = {f.id: f for f in inv.faces}[pmi[gid].faces[0]]
        datum = {f.id: f for f in inv.faces}[pmi["datum-A"].faces[0]]
        assert abs(face.normal @ datum.normal) < 1e-12  # the CAD planes are perpendicular
        chars = {c.id: c for c in resolve_spec(parse_spec(dump_spec(ps.spec())), inv).characteristics}
        c = chars[f"angle({pair[0]},{pair[1]})"]
        assert c.type == "angle" and c.nominal == pytest.approx(math.pi / 2, abs=1e-12)
        half = math.atan(pmi[gid].value / inv[pair[0]].length)
        assert (c.lower_limit, c.upper_limit) == pytest.approx((math.pi / 2 - half, math.pi / 2 + half))


def test_angle_dimension_takes_edges_that_meet(ctc01):
    # dim-3, 60 degrees between the two walls of a vee: their top edges meet (where the walls'
    # planes would), as do their bottom ones; a top edge with a bottom one is 60 degrees too, 50 mm apart.
    pmi, inv, ps = ctc01
    (k,) = [k for k, v in ps.sources.items() if v == "dim-3"]
    a, b = (inv[x] for x in ps.data["angles"][k[1]]["between"])
    assert a.start[2] == b.start[2] == 0.0 and a.end[2] == b.end[2] == 0.0


def test_pmi_datums_drive_the_alignment_without_a_spec_file(ctc01, tmp_path):
    # `inspect part.step images/` aligns on the features `inspect spec`
    # writes as datums; a spec file keeps its own (every feature without any).
    from partinspect.tolerances.loading import load_characteristics
    from partinspect.tolerances.pmi_text import spec_yaml

    pmi, inv, ps = ctc01
    part = STEP_DIR / "nist_ctc_01_asme1_ap242-e1.stp"
    resolved, _ = load_characteristics(inv, None, part=part)
    assert resolved.alignment_datums == tuple(ps.data["datums"])
    assert resolved.datum_source == "nist_ctc_01_asme1_ap242-e1.stp PMI datums A"
    (letter, ids), = resolved.datum_frame
    assert letter == "A" and set(ids) == set(ps.data["datums"])
    # Datum A is a plane: the straight edges that bound its faces.
    (datum_a,) = [i for i in pmi.items if i.kind == "datum" and i.name == "A"]
    assert set(ids) == set().union(*(_non_smooth_lines(inv, face) for face in datum_a.faces))

    written = tmp_path / "written.tol.yaml"
    written.write_text(spec_yaml(ps, pmi, part.name))
    from_file, _ = load_characteristics(inv, written, part=part)
    assert from_file.alignment_datums == resolved.alignment_datums
    assert from_file.datum_source.startswith("written.tol.yaml line ") and from_file.datum_frame == ()

    plain = tmp_path / "plain.tol.yaml"
    plain.write_text("general: ISO2768-mK\n")
    assert load_characteristics(inv, plain, part=part)[0].alignment_datums is None


def test_datum_entry_says_which_datum_features_were_fitted(ctc01):
    from partinspect.tolerances.from_pmi import datum_entry
    from partinspect.tolerances.loading import load_characteristics

    _, inv, ps = ctc01
    resolved, _ = load_characteristics(inv, None, part=STEP_DIR / "nist_ctc_01_asme1_ap242-e1.stp")
    a = ps.datums["A"]
    entry = datum_entry(resolved, a[:3])
    assert entry["applied"] and entry["source"].endswith("PMI datums A")
    assert entry["frame"] == [{"datum": "A", "features": a, "fitted": a[:3]}]
    # A pose that had to use other features too: the datums were not applied.
    other = next(f.id for f in inv.features if f.id not in a)
    fell_back = datum_entry(resolved, a[:3] + [other])
    assert not fell_back["applied"] and "every matched feature" in fell_back["reason"]
    assert fell_back["frame"][0]["fitted"] == []
    assert datum_entry(load_characteristics(inv, None)[0], a) is None


def test_ctc03_datums_at_mmb_go_through_inspect_spec_and_back(ctc03):
    """gtol-5 (position 0.05 in at MMC | A | B(M) | C(M)): `inspect spec` writes the frame with its datum
    modifiers, the spec reads back to positions carrying them, and the PMI alone gives the same. The file
    attaches datums B and C to no face, so the spec says to name them; evaluated, the shift says why it is
    not applied."""
    from partinspect.tolerances.loading import load_characteristics
    from partinspect.tolerances.pmi_text import spec_yaml

    pmi, inv, ps = ctc03
    holes = ps.applies_to["gtol-5"]
    for cid in holes:
        assert ps.data["features"][cid]["position"]["datums"] == ["A", "B(M)", "C(M)"]
    # positions whose frames have no datum at a boundary keep no datums key
    assert all("datums" not in body.get("position", {}) for cid, body in ps.data["features"].items() if cid not in holes)
    text = spec_yaml(ps, pmi, "nist_ctc_03_asme1_ap242-e2.stp")
    assert "datums: [A, B(M), C(M)]" in text
    assert "# datum(s) B, C at MMB/LMB: the file attaches them to no face" in text
    chars = {c.id: c for c in characteristics_for(parse_spec(text), inv)}
    refs = chars[f"{holes[0]}.position"].datums
    assert [d.label for d in refs] == ["A", "B(M)", "C(M)"] and not any(d.features for d in refs)
    # named by hand (the NIST drawing's B and C: the 0.438 in holes at y = 466.4 mm), they are holes whose
    # MMB is their MMC size, 0.438 - 0.005 in
    named = characteristics_for(parse_spec(text + "datum_features: {B: [circle-19, circle-20], C: [circle-3, circle-4]}\n"), inv)
    refs = {c.id: c for c in named}[f"{holes[0]}.position"].datums
    assert [d.of_size for d in refs] == [False, True, True] and refs[1].internal and refs[2].internal
    assert refs[1].reference(refs[1].sizes[0]) == pytest.approx(0.433 * INCH, abs=1e-6)
    # without a spec file the PMI gives the same frame
    _, from_pmi = load_characteristics(inv, None, STEP_DIR / "nist_ctc_03_asme1_ap242-e2.stp", pmi=pmi)
    assert [d.label for d in {c.id: c for c in from_pmi}[f"{holes[0]}.position"].datums] == ["A", "B(M)", "C(M)"]


def test_pmi_datum_features_are_written_for_a_shifted_frame():
    """A PMI position with a datum at MMB whose datum has faces: datum_features names its rims."""
    from types import SimpleNamespace

    from partinspect.tolerances.from_pmi import spec_from_pmi
    from tests.cad.conftest import EXAMPLES

    inv = inventory(load_step(EXAMPLES / "plate" / "part.step"))
    hole = next(f for f in inv.faces if f.surface == "cylinder" and abs(f.radius - 6.0) < 1e-6)
    small = next(f for f in inv.faces if f.surface == "cylinder" and abs(f.radius - 4.0) < 1e-6)

    def item(**kw):
        base = dict(id="", kind="", type="", name="", value=None, upper=None, lower=None, faces=[], faces2=[],
                    modifiers=(), datums=(), notes=[])
        return SimpleNamespace(**{**base, **kw})

    pmi = SimpleNamespace(items=[
        item(id="datum-B", kind="datum", type="datum", name="B", faces=[hole.id]),
        item(id="gtol-1", kind="tolerance", type="position", value=0.1, faces=[small.id], datums=("B",),
             modifiers=("datum_B_MMB",))], unread=())
    ps = spec_from_pmi(pmi, inv)
    rims = ps.data["datum_features"]["B"]
    assert rims and all(inv[r].kind == "circle" and abs(inv[r].radius - 6.0) < 1e-6 for r in rims)
    body = next(b for b in ps.data["features"].values() if "position" in b)
    assert body["position"]["datums"] == ["B(M)"]
    refs = {c.id: c for c in characteristics_for(ps.spec(), inv)}
    ref = next(c for c in refs.values() if c.type == "position").datums[0]
    assert ref.of_size and ref.internal and set(ref.features) == set(rims)
