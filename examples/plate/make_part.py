"""Sample part `plate`: a stepped plate with five through holes.

An 80 x 60 mm plate, 10 mm thick, whose front-right corner region
(x 48..80, y 0..36) is milled down to 6 mm, so its edges lie at two heights.
Five through holes of 4, 6, 8, 10 and 12 mm diameter sit at no symmetric
positions (all diameters differ too), so the part has no symmetry that could
make registration ambiguous; the 10 mm hole is in the milled-down region.

Part frame (= STEP frame), mm: origin at the front-left bottom corner,
x along the 80 mm length, y along the 60 mm width, z up; the bottom face is
z = 0. All edges are sharp (no fillets or chamfers), so every edge is a
straight line or a circle.

Run ``python3 examples/plate/make_part.py`` to (re)write ``part.step`` beside
this file; the output is the same bytes every time.
"""

from pathlib import Path

import cadquery as cq

LENGTH = 80.0  # x
WIDTH = 60.0  # y
THICKNESS = 10.0  # z
# The milled-down corner region: x0, x1, y0, y1, and the height left there.
STEP_REGION = (48.0, 80.0, 0.0, 36.0)
STEP_HEIGHT = 6.0
# Through holes along z: (x, y, diameter).
HOLES = (
    (12.0, 14.0, 8.0),
    (20.0, 42.0, 12.0),
    (38.0, 51.0, 4.0),
    (64.0, 18.0, 10.0),  # in the milled-down region
    (67.0, 48.0, 6.0),
)


def build(holes=HOLES):
    """The plate as a cadquery Solid (mm, part frame).

    Parameters
    ----------
    holes : sequence of (x, y, diameter)
        The through holes, mm.
    """
    part = cq.Workplane("XY").box(LENGTH, WIDTH, THICKNESS, centered=False)
    x0, x1, y0, y1 = STEP_REGION
    pocket = cq.Solid.makeBox(x1 - x0, y1 - y0, THICKNESS - STEP_HEIGHT, cq.Vector(x0, y0, STEP_HEIGHT))
    part = part.cut(pocket)
    for x, y, d in holes:
        part = part.cut(cq.Solid.makeCylinder(d / 2, THICKNESS, cq.Vector(x, y, 0.0)))
    return part.val()


def write_step(shape, path, name):
    """Write a STEP AP214 file (mm) whose bytes depend on the shape only.

    OCCT stamps the current time into the header and numbers the product
    name by a per-process count of writes; fixed values are written instead.
    """
    from OCP.APIHeaderSection import APIHeaderSection_MakeHeader
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.Interface import Interface_Static
    from OCP.StepBasic import StepBasic_Product
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer
    from OCP.TCollection import TCollection_HAsciiString

    Interface_Static.SetCVal_s("xstep.cascade.unit", "MM")
    Interface_Static.SetCVal_s("write.step.unit", "MM")
    Interface_Static.SetCVal_s("write.step.schema", "AP214IS")
    writer = STEPControl_Writer()
    writer.Transfer(shape.wrapped, STEPControl_AsIs)
    model = writer.Model()
    for i in range(1, model.NbEntities() + 1):
        # OCCT names the product after a per-process count of writes.
        if isinstance(model.Value(i), StepBasic_Product):
            model.Value(i).SetId(TCollection_HAsciiString(name))
            model.Value(i).SetName(TCollection_HAsciiString(name))
    header = APIHeaderSection_MakeHeader(model)
    header.SetName(TCollection_HAsciiString(name))
    header.SetTimeStamp(TCollection_HAsciiString("2000-01-01T00:00:00"))
    if writer.Write(str(path)) != IFSelect_RetDone:
        raise SystemExit(f"{path}: could not write the STEP file")


def main():
    out = Path(__file__).resolve().parent / "part.step"
    write_step(build(), out, "plate")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
