"""Sample part `bracket`: an L-shaped angle bracket with holes and a slot.

A 70 x 50 mm base plate, 10 mm thick, carries a 12 mm thick upright wall
along its back edge (y 38..50) that is 40 mm tall and only 52 mm long
(x 0..52), so the base sticks out past the wall on the right. The base has
one 8 mm through hole and one through slot with rounded ends (8 mm wide,
20 mm between its end centres, along x), which gives arcs and the straight
slot sides. The wall has two through holes along y, 10 mm and 6 mm. No two
features mirror each other, so the part has no symmetry.

Part frame (= STEP frame), mm: origin at the front-left bottom corner,
x along the 70 mm length, y along the 50 mm depth (wall at the back),
z up; the bottom face is z = 0. All outer edges are sharp; the only tangent
(smooth) edges are where the slot's flat sides meet its round ends.

Run ``python3 examples/bracket/make_part.py`` to (re)write ``part.step``
beside this file; the output is the same bytes every time.
"""

from pathlib import Path

import cadquery as cq

BASE = (70.0, 50.0, 10.0)  # x, y, z extent of the base plate
WALL_X = (0.0, 52.0)
WALL_Y = (38.0, 50.0)
WALL_HEIGHT = 40.0  # top of the wall above the bottom face
# Through holes in the base, along z: (x, y, diameter).
BASE_HOLES = ((12.0, 14.0, 8.0),)
# Through slot in the base, along z: centre x, y, length between the end
# centres (along x), width.
SLOT = (40.0, 20.0, 20.0, 8.0)
# Through holes in the wall, along y: (x, z, diameter).
WALL_HOLES = ((16.0, 26.0, 10.0), (40.0, 30.0, 6.0))


def build():
    """The bracket as a cadquery Solid (mm, part frame)."""
    bx, by, bz = BASE
    part = cq.Workplane("XY").box(bx, by, bz, centered=False)
    wall = cq.Solid.makeBox(WALL_X[1] - WALL_X[0], WALL_Y[1] - WALL_Y[0], WALL_HEIGHT, cq.Vector(WALL_X[0], WALL_Y[0], 0))
    part = part.union(wall)

    cutters = [cq.Solid.makeCylinder(d / 2, bz, cq.Vector(x, y, 0.0)) for x, y, d in BASE_HOLES]
    sx, sy, slot_length, slot_width = SLOT
    slot = cq.Workplane("XY").center(sx, sy).slot2D(slot_length + slot_width, slot_width).extrude(bz).val()
    cutters.append(slot)
    depth = WALL_Y[1] - WALL_Y[0]
    cutters += [
        cq.Solid.makeCylinder(d / 2, depth, cq.Vector(x, WALL_Y[0], z), cq.Vector(0, 1, 0)) for x, z, d in WALL_HOLES
    ]
    for cutter in cutters:
        part = part.cut(cutter)
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
    write_step(build(), out, "bracket")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
