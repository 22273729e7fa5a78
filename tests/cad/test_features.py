import json
import math
from collections import Counter

import numpy as np
import pytest

from partinspect.cad.features import (
    AmbiguousFeatureError,
    canonical_direction,
    inventory,
    nearest_feature,
    occ_edges,
)
from partinspect.frames import reference_direction
from partinspect.cad.step import load_step, save_step

from .conftest import nist_files

# --- the sample plate -------------------------------------------------------


@pytest.fixture(scope="module")
def plate(plate_path):
    shape = load_step(plate_path)
    return shape, inventory(shape)


@pytest.fixture(scope="module")
def bracket(bracket_path):
    shape = load_step(bracket_path)
    return shape, inventory(shape)


def _plate_holes(m):
    """(centre x, y, radius, top z) of every plate hole, from make_part's parameters."""
    x0, x1, y0, y1 = m.STEP_REGION
    return [(x, y, d / 2, m.STEP_HEIGHT if (x0 < x < x1 and y0 < y < y1) else m.THICKNESS) for x, y, d in m.HOLES]


def test_plate_has_two_circles_per_hole_with_the_drawn_radii(plate, plate_module):
    _, inv = plate
    holes = _plate_holes(plate_module)
    circles = inv.of_kind("circle")
    assert len(circles) == 2 * len(holes) == 10
    assert inv.of_kind("arc") == ()
    expected = sorted((x, y, z, r) for x, y, r, top in holes for z in (0.0, top))
    got = sorted((*c.center, c.radius) for c in circles)
    np.testing.assert_allclose(got, expected, atol=1e-9)
    for c in circles:
        np.testing.assert_allclose(c.normal, [0, 0, 1], atol=1e-12)
        assert c.length == pytest.approx(2 * math.pi * c.radius, rel=1e-12)
        assert c.n_edges == 1 and not c.smooth
        assert c.start is None and c.angle_start is None


def test_plate_circle_ids_follow_the_geometric_order(plate, plate_module):
    # Ids sort by centre x, then y, then z: each hole's bottom rim, then its top.
    _, inv = plate
    holes = sorted(_plate_holes(plate_module))
    for i, (x, y, r, top) in enumerate(holes):
        bottom, upper = inv[f"circle-{2 * i + 1}"], inv[f"circle-{2 * i + 2}"]
        np.testing.assert_allclose(bottom.center, [x, y, 0.0], atol=1e-9)
        np.testing.assert_allclose(upper.center, [x, y, top], atol=1e-9)
        assert bottom.radius == upper.radius == pytest.approx(r, abs=1e-12)


def test_each_hole_circle_bounds_one_plane_and_one_hole_wall(plate):
    _, inv = plate
    for c in inv.of_kind("circle"):
        faces = [inv[f] for f in c.faces]
        assert sorted(f.surface for f in faces) == ["cylinder", "plane"]
        plane = next(f for f in faces if f.surface == "plane")
        wall = next(f for f in faces if f.surface == "cylinder")
        assert wall.convex is False  # material outside: a hole
        assert wall.radius == pytest.approx(c.radius, abs=1e-12)
        np.testing.assert_allclose(wall.axis_direction, [0, 0, 1], atol=1e-12)
        # A bottom rim lies on the downward-facing bottom face, a top rim on an upward one.
        expected_nz = -1.0 if c.center[2] == pytest.approx(0.0) else 1.0
        np.testing.assert_allclose(plane.normal, [0, 0, expected_nz], atol=1e-12)


def test_plate_lines_count_and_total_length(plate, plate_module):
    m = plate_module
    _, inv = plate
    lines = inv.of_kind("line")
    x0, x1, y0, y1 = m.STEP_REGION
    assert (x1, y0) == (m.LENGTH, 0.0), "the formula below assumes the step is at the front-right corner"
    dz = m.THICKNESS - m.STEP_HEIGHT
    expected = (
        2 * (m.LENGTH + m.WIDTH)  # bottom outline
        + 2 * (m.LENGTH + m.WIDTH)  # upper face: an L with the perimeter of the full rectangle
        + 2 * ((x1 - x0) + (y1 - y0))  # milled face
        + 3 * m.THICKNESS  # three full-height corners
        + m.STEP_HEIGHT  # the corner under the step
        + 3 * dz  # the step's three vertical edges
    )
    assert len(lines) == 4 + 6 + 4 + 3 + 1 + 3
    assert sum(f.length for f in lines) == pytest.approx(expected, abs=1e-9)
    for f in lines:
        assert len(f.faces) == 2 and all(inv[x].surface == "plane" for x in f.faces)
        assert not f.smooth
        # start sorts before end
        assert tuple(np.round(f.start, 9)) < tuple(np.round(f.end, 9))
        assert f.length == pytest.approx(np.linalg.norm(f.end - f.start))


def test_plate_edge_accounting(plate):
    shape, inv = plate
    assert inv.seam_edges == {"line": 5}  # one seam per hole wall
    assert inv.skipped_edges == {} and inv.degenerated_edges == 0
    assert sum(inv.edge_counts.values()) == len(shape.Edges())
    assert len(inv.faces) == len(shape.Faces()) == 14
    assert Counter(f.surface for f in inv.faces) == {"plane": 9, "cylinder": 5}
    assert [f.id for f in inv.faces] == [f"face-{i}" for i in range(1, 15)]


def test_same_file_gives_the_same_inventory(plate_path, plate):
    _, inv = plate
    again = inventory(load_step(plate_path))
    assert again.to_dict() == inv.to_dict()


def _geometry(f):
    return np.concatenate([np.ravel(v) for v in (f.start, f.end, f.center, f.normal) if v is not None] + [[f.length]])


def _assert_same_features(a, b, atol=1e-9):
    assert [f.id for f in a.features] == [f.id for f in b.features]
    for fa in a.features:
        fb = b[fa.id]
        assert fa.kind == fb.kind and fa.faces == fb.faces
        np.testing.assert_allclose(_geometry(fa), _geometry(fb), atol=atol, err_msg=fa.id)
    for fa, fb in zip(a.faces, b.faces):
        assert fa.id == fb.id and fa.surface == fb.surface
        np.testing.assert_allclose(fa.centroid, fb.centroid, atol=atol)


def _edge_midpoints(shape):
    return np.array([e.Center().toTuple() for e in shape.Edges()])


def _rotated_traversal(shape, k):
    """The same solid with its faces stored from the k-th on, reversed.

    The geometry and topology are untouched; only the order in which OCCT
    (and a STEP file written from it) lists faces, edges and vertices changes.
    """
    import cadquery as cq
    from OCP.BRep import BRep_Builder
    from OCP.TopoDS import TopoDS_Shell, TopoDS_Solid

    faces = shape.Faces()
    faces = list(reversed(faces[k:] + faces[:k]))
    builder = BRep_Builder()
    shell = TopoDS_Shell()
    builder.MakeShell(shell)
    for f in faces:
        builder.Add(shell, f.wrapped)
    solid = TopoDS_Solid()
    builder.MakeSolid(solid)
    builder.Add(solid, shell)
    return cq.Solid(solid)


@pytest.mark.parametrize("part", ["plate", "bracket"])
def test_ids_do_not_depend_on_occt_traversal_order(tmp_path, part, request):
    shape, inv = request.getfixturevalue(part)
    path = tmp_path / "reordered.step"
    save_step(_rotated_traversal(shape, 5), path)
    other = load_step(path)
    assert other.isValid()
    assert other.Volume() == pytest.approx(shape.Volume(), rel=1e-12)
    # The test means something only if OCCT really lists things in another order.
    a, b = _edge_midpoints(shape), _edge_midpoints(other)
    assert a.shape == b.shape and not np.allclose(a, b)
    _assert_same_features(inv, inventory(other))


def test_located_shape_gives_moved_geometry_and_same_ids(plate):
    import cadquery as cq

    shape, inv = plate
    shift = np.array([100.0, -20.0, 5.0])
    moved = inventory(shape.moved(cq.Location(cq.Vector(*shift))))
    assert [f.id for f in moved.features] == [f.id for f in inv.features]
    for f in inv.of_kind("circle"):
        np.testing.assert_allclose(moved[f.id].center, f.center + shift, atol=1e-9)
    for f in inv.of_kind("line"):
        np.testing.assert_allclose(moved[f.id].start, f.start + shift, atol=1e-9)


def test_half_arc_circles_are_merged(plate, plate_module):
    # Many CAD systems write a hole's rim as two half arcs and its wall as two
    # half cylinders; OCCT's ShapeDivideClosed produces just that.
    import cadquery as cq
    from OCP.ShapeUpgrade import ShapeUpgrade_ShapeDivideClosed

    shape, inv = plate
    divide = ShapeUpgrade_ShapeDivideClosed(shape.wrapped)
    divide.SetNbSplitPoints(1)
    divide.Perform()
    split = cq.Shape.cast(divide.Result())
    assert len(split.Faces()) == len(shape.Faces()) + 5
    sinv = inventory(split)
    assert sinv.of_kind("arc") == ()
    assert [c.id for c in sinv.of_kind("circle")] == [c.id for c in inv.of_kind("circle")]
    for c in inv.of_kind("circle"):
        s = sinv[c.id]
        assert s.n_edges == 2
        np.testing.assert_allclose(s.center, c.center, atol=1e-9)
        assert s.radius == pytest.approx(c.radius, abs=1e-9)
        assert [sinv[f].surface for f in s.faces].count("cylinder") == 2
    # The old seams now run between the two half walls: tangent, not creases.
    # (OCCT writes the new split lines as B-splines, which are skipped.)
    creases = [f for f in sinv.of_kind("line") if not f.smooth]
    assert len(creases) == len(inv.of_kind("line"))
    depths = sorted(top for *_, top in _plate_holes(plate_module))
    assert sorted(f.length for f in sinv.of_kind("line") if f.smooth) == pytest.approx(depths)


# --- the bracket ------------------------------------------------------------


def test_bracket_inventory(bracket, bracket_module):
    m = bracket_module
    _, inv = bracket
    assert Counter(f.kind for f in inv.features) == {"line": 29, "circle": 6, "arc": 4}
    radii = sorted(c.radius for c in inv.of_kind("circle"))
    expected = sorted([d / 2 for *_, d in m.BASE_HOLES] * 2 + [d / 2 for *_, d in m.WALL_HOLES] * 2)
    np.testing.assert_allclose(radii, expected, atol=1e-12)
    for x, z, d in m.WALL_HOLES:
        rims = [c for c in inv.of_kind("circle") if np.allclose(c.center[[0, 2]], [x, z])]
        assert sorted(c.center[1] for c in rims) == pytest.approx(list(m.WALL_Y))
        for c in rims:
            np.testing.assert_allclose(c.normal, [0, 1, 0], atol=1e-12)


def test_bracket_slot_arcs_and_tangent_lines(bracket, bracket_module):
    _, inv = bracket
    sx, sy, length, width = bracket_module.SLOT
    r = width / 2
    arcs = inv.of_kind("arc")
    for a in arcs:
        assert a.radius == pytest.approx(r, abs=1e-12)
        assert a.angle_end - a.angle_start == pytest.approx(math.pi, abs=1e-12)
        assert a.length == pytest.approx(math.pi * r, abs=1e-12)
        assert 0 <= a.angle_start < 2 * math.pi
        assert sorted(inv[f].surface for f in a.faces) == ["cylinder", "plane"]
    left = [a for a in arcs if a.center[0] == pytest.approx(sx - length / 2)]
    right = [a for a in arcs if a.center[0] == pytest.approx(sx + length / 2)]
    assert len(left) == len(right) == 2
    for a in left:  # the left end bulges to -x: from +y round to -y
        assert (a.angle_start, a.angle_end) == pytest.approx((math.pi / 2, 3 * math.pi / 2))
        np.testing.assert_allclose(a.start, a.center + [0, r, 0], atol=1e-12)
        np.testing.assert_allclose(a.end, a.center + [0, -r, 0], atol=1e-12)
    for a in right:  # the right end bulges to +x: the range runs through angle 0 (2 pi)
        assert (a.angle_start, a.angle_end) == pytest.approx((3 * math.pi / 2, 5 * math.pi / 2))
        np.testing.assert_allclose(a.start, a.center + [0, -r, 0], atol=1e-12)
    smooth = [f for f in inv.features if f.smooth]
    assert len(smooth) == 4 and all(f.kind == "line" for f in smooth)
    corners = sorted((round(f.start[0], 9), round(f.start[1], 9)) for f in smooth)
    assert corners == [(sx - length / 2, sy - r), (sx - length / 2, sy + r), (sx + length / 2, sy - r), (sx + length / 2, sy + r)]


# --- selectors ----------------------------------------------------------------


def test_nearest_feature_on_a_circle(plate):
    _, inv = plate
    top = inv["circle-10"]  # 6 mm hole at (67, 48), top rim
    p = top.center + [top.radius + 0.03, 0.0, 0.04]
    f, d = nearest_feature(inv, p)
    assert f.id == "circle-10" and d == pytest.approx(0.05, abs=1e-12)


def test_nearest_feature_on_a_line(plate):
    _, inv = plate
    f, d = nearest_feature(inv, [24.0, -0.02, 10.0])
    assert f.id == "line-5" and d == pytest.approx(0.02, abs=1e-12)


def test_nearest_feature_at_a_corner_is_ambiguous(plate):
    _, inv = plate
    with pytest.raises(AmbiguousFeatureError, match="line-1, line-2, line-6") as info:
        nearest_feature(inv, [0.0, 0.0, 0.0])
    assert isinstance(info.value, ValueError)


def test_nearest_feature_respects_arc_ranges(bracket):
    _, inv = bracket
    left_top = next(a for a in inv.of_kind("arc") if a.center[0] < 40 and a.center[2] > 5)
    right_top = next(a for a in inv.of_kind("arc") if a.center[0] > 40 and a.center[2] > 5)
    f, d = nearest_feature(inv, left_top.center + [-3.5, 0.0, 0.0])
    assert f is left_top and d == pytest.approx(0.5)
    # Angle 0 lies inside the right arc only through its range running past 2 pi.
    f, d = nearest_feature(inv, right_top.center + [3.5, 0.0, 0.0])
    assert f is right_top and d == pytest.approx(0.5)
    # Inside the slot, facing away from the left arc: the arc counts by its ends only.
    f, d = nearest_feature(inv, left_top.center + [1.0, -1.0, 0.0])
    assert f.kind == "line" and d == pytest.approx(3.0)


def test_nearest_feature_rejects_bad_points(plate):
    _, inv = plate
    with pytest.raises(ValueError):
        nearest_feature(inv, [1.0, 2.0])
    with pytest.raises(ValueError):
        nearest_feature(inv, [1.0, np.nan, 2.0])


# --- conventions ----------------------------------------------------------------


def test_circle_frame_conventions():
    rng = np.random.default_rng(7)
    for n in list(rng.normal(size=(200, 3))) + [np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), np.array([0, -1e-17, 1.0])]:
        c = canonical_direction(n)
        assert np.linalg.norm(c) == pytest.approx(1.0)
        assert abs(abs(c @ n) - np.linalg.norm(n)) < 1e-12
        np.testing.assert_array_equal(canonical_direction(-n), c)
        x = reference_direction(c)
        assert abs(x @ c) < 1e-12 and np.linalg.norm(x) == pytest.approx(1.0)
    np.testing.assert_array_equal(canonical_direction([0, -1e-17, -2.0]), [0, 1e-17 / 2, 1.0])
    np.testing.assert_allclose(reference_direction([0, 0, 1]), [1, 0, 0])
    np.testing.assert_allclose(reference_direction([1, 0, 0]), [0, 1, 0])


def test_lookup_and_json(plate):
    _, inv = plate
    assert inv["face-3"].id == "face-3" and "circle-1" in inv and "circle-99" not in inv
    with pytest.raises(KeyError, match="circle-99"):
        inv["circle-99"]
    d = json.loads(json.dumps(inv.to_dict()))
    assert d["schema"] == "inventory/1" and d["units"] == "mm"
    assert d["counts"] == {"line": 21, "circle": 10, "arc": 0}
    assert len(d["features"]) == 31 and len(d["faces"]) == 14
    assert d["skipped"] == {} and d["seams"] == {"line": 5}
    with pytest.raises(ValueError):
        inv["circle-1"].center[0] = 1.0  # geometry is read-only


def test_tolerance_files_name_real_features(plate, bracket, plate_path, bracket_path):
    spec_mod = pytest.importorskip("partinspect.tolerances.spec")
    resolve = pytest.importorskip("partinspect.tolerances.resolve")
    for (_, inv), step in ((plate, plate_path), (bracket, bracket_path)):
        tol = step.with_name("part.tol.yaml")
        resolved = resolve.resolve_spec(spec_mod.load_spec(tol), inv, tol)
        assert len(resolved.characteristics) == 5


# --- NIST files -------------------------------------------------------------------

# SOURCES.md section 2, "edges: total / LINE / CIRCLE / other" and faces. These
# count the whole STEP file; some files also hold curves and surfaces outside
# the solid (presentation or supplemental geometry), which load_step drops.
SOURCES_COUNTS = {
    "nist_ctc_01_asme1_ap242-e1.stp": (214, 90, 117),
    "nist_ctc_01_asme1_rd.stp": (318, 122, 139),
    "nist_ctc_02_asme1_ap242-e2.stp": (775, 590, 637),
    "nist_ctc_03_asme1_ap242-e2.stp": (296, 144, 120),
    "nist_ctc_04_asme1_ap242-e1.stp": (501, 442, 484),
    "nist_ftc_06_asme1_rd.stp": (239, 161, 144),
    "nist_ftc_08_asme1_ap242-e1.stp": (448, 312, 248),
    "nist_ftc_09_asme1_ap242-e1.stp": (273, 190, 161),
    "nist_ftc_10_asme1_ap242-e2.stp": (298, 245, 282),
    "nist_ftc_11_asme1_rb.stp": (0, 8, 6),
}
# Files with nothing outside the solid: the solid's counts are the table's.
SOLID_ONLY = {"nist_ctc_01_asme1_ap242-e1.stp", "nist_ftc_09_asme1_ap242-e1.stp", "nist_ftc_11_asme1_rb.stp"}


def _edge_types(shape):
    from OCP.BRep import BRep_Tool
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.GeomAbs import GeomAbs_Circle, GeomAbs_Line

    names = {GeomAbs_Line: "line", GeomAbs_Circle: "circle"}
    return [
        "degenerated" if BRep_Tool.Degenerated_s(e) else names.get(BRepAdaptor_Curve(e).GetType(), "other")
        for e in occ_edges(shape)
    ]


@pytest.mark.parametrize("name", nist_files())
def test_nist_every_line_and_circle_edge_is_accounted_for_once(name, step_dir, cad_cache):
    shape = cad_cache.shape(step_dir / name)
    inv = cad_cache.inventory(step_dir / name)
    types = _edge_types(shape)
    used = [i for f in inv.features for i in f.edge_indices]
    assert len(used) == len(set(used)), "an edge is in two features"
    for kind, feature_kinds in (("line", {"line"}), ("circle", {"circle", "arc"})):
        in_features = [i for f in inv.features if f.kind in feature_kinds for i in f.edge_indices]
        assert all(types[i] == kind for i in in_features)
        assert len(in_features) + inv.seam_edges.get(kind, 0) == types.count(kind) == inv.edge_counts.get(kind, 0)
    assert inv.degenerated_edges == types.count("degenerated")
    n_other = sum(v for k, v in inv.edge_counts.items() if k not in ("line", "circle"))
    assert n_other == sum(inv.skipped_edges.values()) + sum(v for k, v in inv.seam_edges.items() if k not in ("line", "circle"))

    lines, circles, faces = SOURCES_COUNTS[name]
    if name in SOLID_ONLY:
        assert (inv.edge_counts.get("line", 0), inv.edge_counts.get("circle", 0), len(inv.faces)) == (lines, circles, faces)
    else:
        assert inv.edge_counts.get("line", 0) <= lines and inv.edge_counts.get("circle", 0) <= circles
        assert len(inv.faces) <= faces

    ids = [f.id for f in inv.features]
    assert len(set(ids)) == len(ids)
    for kind in ("line", "circle", "arc"):
        assert [f.id for f in inv.of_kind(kind)] == [f"{kind}-{i}" for i in range(1, len(inv.of_kind(kind)) + 1)]
    json.dumps(inv.to_dict())


def test_nist_ftc09_half_arcs_merge_into_holes(step_dir, cad_cache):
    # FTC-09 writes every hole rim as two half arcs whose centres differ by up
    # to 1e-4 mm (the file's modelling uncertainty is 0.01 mm).
    inv = cad_cache.inventory(step_dir / "nist_ftc_09_asme1_ap242-e1.stp")
    circles = inv.of_kind("circle")
    assert len(circles) == 62
    assert all(c.n_edges == 2 for c in circles)
    assert sum(f.n_edges for f in inv.features if f.kind != "line") == 190
    for a in inv.of_kind("arc"):
        assert 0 < a.angle_end - a.angle_start < 2 * math.pi - 1e-3


def test_nist_ids_are_stable_across_loads(step_dir, cad_cache):
    path = step_dir / "nist_ctc_03_asme1_ap242-e2.stp"
    assert inventory(load_step(path)).to_dict() == cad_cache.inventory(path).to_dict()
