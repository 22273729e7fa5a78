import gzip
import math

import numpy as np
import pytest

from partinspect.cad.step import load_step, save_step
from partinspect.errors import InputError

from .conftest import nist_files


def _bbox(shape):
    """Exact extents (mm); cadquery's default box is loose on curved faces."""
    from OCP.Bnd import Bnd_Box
    from OCP.BRepBndLib import BRepBndLib

    box = Bnd_Box()
    BRepBndLib.AddOptimal_s(shape.wrapped, box, False, False)
    x0, y0, z0, x1, y1, z1 = box.Get()
    return np.array([x1 - x0, y1 - y0, z1 - z0])


def test_plate_loads_as_one_solid_in_mm(plate_path, plate_module):
    m = plate_module
    shape = load_step(plate_path)
    assert type(shape).__name__ == "Solid"
    assert shape.isValid()
    bb = shape.BoundingBox()
    assert (bb.xmin, bb.ymin, bb.zmin) == pytest.approx((0, 0, 0), abs=1e-6)
    assert (bb.xmax, bb.ymax, bb.zmax) == pytest.approx((m.LENGTH, m.WIDTH, m.THICKNESS), abs=1e-6)
    x0, x1, y0, y1 = m.STEP_REGION
    pocket = (x1 - x0) * (y1 - y0) * (m.THICKNESS - m.STEP_HEIGHT)
    holes = 0.0
    for x, y, d in m.HOLES:
        inside = x0 < x < x1 and y0 < y < y1
        holes += math.pi * d * d / 4 * (m.STEP_HEIGHT if inside else m.THICKNESS)
    assert shape.Volume() == pytest.approx(m.LENGTH * m.WIDTH * m.THICKNESS - pocket - holes, rel=1e-9)


def test_committed_example_steps_are_what_make_part_writes(tmp_path, plate_module, bracket_module, plate_path, bracket_path):
    for module, committed, name in ((plate_module, plate_path, "plate"), (bracket_module, bracket_path, "bracket")):
        out = tmp_path / f"{name}.step"
        module.write_step(module.build(), out, name)
        assert out.read_bytes() == committed.read_bytes(), f"{committed} is stale: run examples/{name}/make_part.py"


def test_save_step_is_byte_reproducible_and_round_trips(tmp_path, plate_module):
    shape = plate_module.build()
    a, b = tmp_path / "a.step", tmp_path / "b.step"
    save_step(shape, a)
    save_step(shape, b)
    assert a.read_bytes() == b.read_bytes()
    assert load_step(a).Volume() == pytest.approx(shape.Volume(), rel=1e-12)


def test_inch_file_is_converted_to_mm(step_dir):
    # FTC-06 is written in inches: 12 x 3.85 x 9.75 in. (SOURCES.md's 106.68
    # mm for y is the box of the whole file, which holds geometry outside
    # the solid; load_step returns the solid only.)
    shape = load_step(step_dir / "nist_ftc_06_asme1_rd.stp")
    assert _bbox(shape) == pytest.approx(np.array([12.0, 3.85, 9.75]) * 25.4, abs=1e-3)


def test_unit_does_not_depend_on_occt_global_setting(step_dir):
    from OCP.Interface import Interface_Static

    # cadquery's importer sets this process-wide value; load_step must not care.
    Interface_Static.SetCVal_s("xstep.cascade.unit", "M")
    try:
        shape = load_step(step_dir / "nist_ftc_09_asme1_ap242-e1.stp")
    finally:
        Interface_Static.SetCVal_s("xstep.cascade.unit", "MM")
    assert _bbox(shape) == pytest.approx([190.5, 3.038, 279.4], abs=1e-3)


@pytest.mark.parametrize("name", nist_files())
def test_every_nist_file_loads_as_one_valid_solid(name, step_dir, cad_cache):
    shape = cad_cache.shape(step_dir / name)
    assert type(shape).__name__ == "Solid"
    assert len(shape.Faces()) > 0
    assert shape.Volume() > 0


# --- bad files -------------------------------------------------------------


def _assert_input_error(path, fragment):
    with pytest.raises(InputError) as info:
        load_step(path)
    message = str(info.value)
    assert str(path) in message
    assert fragment in message
    assert "\n" not in message
    return message


def test_missing_file(tmp_path):
    _assert_input_error(tmp_path / "nope.step", "no such file")


def test_directory(tmp_path):
    _assert_input_error(tmp_path, "directory")


def test_empty_file(tmp_path):
    path = tmp_path / "empty.step"
    path.write_bytes(b"")
    _assert_input_error(path, "empty")


def test_text_file_renamed_step(tmp_path):
    path = tmp_path / "notes.step"
    path.write_text("Remember to order 12 mm drills.\n" * 20)
    _assert_input_error(path, "not a STEP file")


def test_compressed_step(tmp_path, plate_path):
    path = tmp_path / "part.stpZ"
    path.write_bytes(gzip.compress(plate_path.read_bytes()))
    _assert_input_error(path, "compressed")


def test_truncated_half_of_a_real_step(tmp_path, plate_path):
    data = plate_path.read_bytes()
    path = tmp_path / "half.step"
    path.write_bytes(data[: len(data) // 2])
    _assert_input_error(path, "truncated")


def test_truncated_nist_file(tmp_path, step_dir):
    data = (step_dir / "nist_ctc_03_asme1_ap242-e2.stp").read_bytes()
    path = tmp_path / "half.stp"
    path.write_bytes(data[: len(data) // 2])
    _assert_input_error(path, "truncated")


def test_syntax_error_is_caught_quietly(tmp_path, capfd):
    # A correct frame around a broken entity reaches OCCT, whose reader fails;
    # OCCT's own console message must not leak onto stdout.
    path = tmp_path / "broken.step"
    path.write_text(
        "ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION((''),'2;1');\nENDSEC;\nDATA;\n#1=CARTESIAN_POINT('',(0.,0.;\n"
        "ENDSEC;\nEND-ISO-10303-21;\n"
    )
    _assert_input_error(path, "could not parse")
    out, err = capfd.readouterr()
    assert "StepFile" not in out + err


def test_occt_printers_are_restored(tmp_path):
    from OCP.Message import Message

    before = Message.DefaultMessenger_s().Printers().Size()
    path = tmp_path / "bad.step"
    path.write_text("ISO-10303-21;\nHEADER;\nbroken\nEND-ISO-10303-21;\n")
    with pytest.raises(InputError):
        load_step(path)
    assert Message.DefaultMessenger_s().Printers().Size() == before


def test_step_with_product_but_no_geometry(tmp_path, plate_path):
    # Keep the header and the product records, drop every shape record.
    text = plate_path.read_text()
    head, data = text.split("DATA;\n", 1)
    keep = [line for line in data.splitlines() if "PRODUCT" in line and "SHAPE" not in line and "#" in line]
    path = tmp_path / "empty-product.step"
    path.write_text(head + "DATA;\n" + "\n".join(keep) + "\nENDSEC;\nEND-ISO-10303-21;\n")
    with pytest.raises(InputError) as info:
        load_step(path)
    assert str(path) in str(info.value)


def test_surface_model_without_solid(tmp_path):
    import cadquery as cq

    path = tmp_path / "face.step"
    save_step(cq.Workplane("XY").rect(20, 10).extrude(5).faces(">Z").val(), path)
    message = _assert_input_error(path, "no solid")
    assert "1 faces" in message
