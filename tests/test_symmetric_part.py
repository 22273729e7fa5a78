"""A part whose CAD model maps onto itself: one of the equal poses taken, and the report says so.

Issue 46's flange (a disc, a hub with its bore, six like bolt holes): every
turn of 60 degrees about its axis maps the model onto itself, so the poses
those turns relate explain the images equally well and give the same
characteristics. The run takes one and names the turns, through every
registration after the first (the posed stage's, which starts from the
chosen pose and searches no more).
"""

import json

import pytest

from partinspect.cli import main


@pytest.fixture(scope="module")
def flange_run(tmp_path_factory):
    """The flange rendered at a quarter size, noise 2, and inspected."""
    from partinspect.simulate.folder import render_to_folder
    from partinspect.simulate.parts import flange, write_part

    d = tmp_path_factory.mktemp("flange")
    write_part(flange(), d / "part.step")
    render_to_folder(d / "part.step", d, image_size=(612, 512), noise=2.0, seed=7)
    out = d / "out"
    code = main([str(d / "part.step"), str(d / "images"), "-o", str(out), "-q"])
    return code, json.loads((out / "report.json").read_text())


def test_the_symmetric_flange_is_inspected_and_its_turns_named(flange_run):
    code, report = flange_run
    assert code in (0, 3)
    reg = report["registration"]
    assert "ambiguity" not in reg
    assert reg["symmetry"].startswith("the CAD model maps onto itself under a turn of")
    assert "60.0 deg about" in reg["symmetry"]
    assert not any(c["decision"] == "inconclusive" and "depends on which of" in c["decision_reason"]
                   for c in report["characteristics"])
