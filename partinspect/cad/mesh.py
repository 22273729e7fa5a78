"""Triangle mesh of a CAD part, each triangle labelled with its CAD face.

The renderer and the visibility tests need the part as triangles; the
labels let them tell which image edge comes from which CAD edge (an edge is
where the label changes).
"""

import numpy as np

__all__ = ["tessellate"]


def tessellate(shape, tolerance=0.005, angular_tolerance=0.05, inventory=None, min_size=None):
    """Triangulate a part in its part frame with a bounded chord error.

    Parameters
    ----------
    shape : cadquery.Shape
        Solid or compound, part frame, mm.
    tolerance : float
        Largest distance between a triangle and the exact surface (chord
        error), mm. The default 0.005 mm is a tenth of a pixel's footprint on
        the part for the rig the project targets.
    angular_tolerance : float
        Largest angle between the normals of neighbouring triangles along a
        curved surface, radians; keeps small circles round too, which the
        chord error alone would draw with few segments.
    inventory : partinspect.cad.features.Inventory, optional
        The part's inventory, if already made; it must come from this shape.
    min_size : float, optional
        Shortest segment BRepMesh makes, mm (its ``MinSize``); None leaves
        BRepMesh's default. A small fillet's radius, split by the angular
        tolerance alone, would take hundreds of facets.

    Returns
    -------
    trimesh.Trimesh
        Vertices (V, 3) in mm, part frame; faces (T, 3) wound so that normals
        point out of the material. Vertices on a CAD edge are shared by both
        faces' triangles, so a valid solid's mesh is watertight.
        ``mesh.face_attributes["cad_face"]`` (int64, (T,)) gives each
        triangle's CAD face as an index into ``inventory(shape).faces``.

    Raises
    ------
    ValueError
        If OCCT cannot triangulate the shape.

    Notes
    -----
    Any triangulation stored in the shape is discarded first, so that the same
    call gives the same mesh; the new one is stored in the shape (and shared
    by its copies). BRepMesh bounds the chord error on faces and edges alike: a
    circle of radius r in n segments sags by r (1 - cos(pi / n)).
    """
    if not tolerance > 0 or not angular_tolerance > 0:
        raise ValueError(f"tolerances must be > 0, got {tolerance} mm and {angular_tolerance} rad")
    wrapped = getattr(shape, "wrapped", shape)
    face_map, face_label = _face_labels(shape, wrapped, inventory)
    _triangulate(wrapped, tolerance, angular_tolerance, min_size)
    vertices, triangles, labels = _face_triangles(face_map, face_label)
    return _closed_mesh(vertices, triangles, labels)


def _face_labels(shape, wrapped, inventory):
    """The shape's faces (OCCT indexed map) and, per map index, the face's label in the inventory's order."""
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp
    from OCP.TopTools import TopTools_IndexedMapOfShape

    if inventory is None:
        from partinspect.cad.features import face_inventory

        faces = face_inventory(shape)
    else:
        faces = inventory.faces
    face_map = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(wrapped, TopAbs_FACE, face_map)
    if face_map.Extent() != len(faces):
        raise ValueError(f"the inventory has {len(faces)} faces, the shape {face_map.Extent()}: not made from this shape")
    face_label = np.empty(len(faces), dtype=np.int64)
    for label, info in enumerate(faces):
        face_label[info.shape_index] = label
    return face_map, face_label


def _triangulate(wrapped, tolerance, angular_tolerance, min_size=None):
    """Discard any stored triangulation and mesh every face anew (BRepMesh), stored in the shape."""
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.BRepTools import BRepTools
    from OCP.IMeshTools import IMeshTools_MeshAlgoType, IMeshTools_Parameters

    BRepTools.Clean_s(wrapped)
    params = IMeshTools_Parameters()
    params.Deflection = tolerance
    params.Angle = angular_tolerance
    params.Relative = False
    if min_size is not None:
        params.MinSize = min_size
    # Serial: the parallel mode gains too little to be worth both cores of a
    # shared machine. Delabella gives the same triangles as the default
    # (Watson) triangulator, several times faster at these tolerances.
    params.InParallel = False
    params.MeshAlgo = IMeshTools_MeshAlgoType.IMeshTools_MeshAlgoType_Delabella
    BRepMesh_IncrementalMesh(wrapped, params)


def _face_triangles(face_map, face_label):
    """Each triangulated face's nodes (part frame), triangles (wound outward, global node indices) and labels."""
    from OCP.BRep import BRep_Tool
    from OCP.TopAbs import TopAbs_REVERSED
    from OCP.TopLoc import TopLoc_Location
    from OCP.TopoDS import TopoDS

    vertices, triangles, labels = [], [], []
    offset = 0
    for k in range(face_map.Extent()):
        face = TopoDS.Face_s(face_map.FindKey(k + 1))
        location = TopLoc_Location()
        poly = BRep_Tool.Triangulation_s(face, location)
        if poly is None or poly.NbTriangles() == 0:
            continue
        nodes = np.array([poly.Node(i).Coord() for i in range(1, poly.NbNodes() + 1)], dtype=float)
        if not location.IsIdentity():
            nodes = _transform(nodes, location.Transformation())
        tri = np.array([poly.Triangle(i).Get() for i in range(1, poly.NbTriangles() + 1)], dtype=np.int64) - 1
        # OCCT stores triangles counter-clockwise about the surface's own
        # normal; a reversed face has its material on the other side.
        if face.Orientation() == TopAbs_REVERSED:
            tri = tri[:, ::-1]
        vertices.append(nodes)
        triangles.append(tri + offset)
        labels.append(np.full(len(tri), face_label[k], dtype=np.int64))
        offset += len(nodes)
    if not triangles:
        raise ValueError("OCCT produced no triangles for this shape")
    return vertices, triangles, labels


def _closed_mesh(vertices, triangles, labels):
    """One labelled trimesh of the faces' triangles: shared edge nodes merged, collapsed triangles dropped."""
    import trimesh

    mesh = trimesh.Trimesh(
        vertices=np.concatenate(vertices),
        faces=np.concatenate(triangles),
        face_attributes={"cad_face": np.concatenate(labels)},
        process=False,
    )
    # Faces store their own copies of the nodes on shared edges; merging by
    # position makes the solid's mesh one closed surface.
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    # Triangles at a cone's apex or a sphere's pole collapse onto one vertex
    # after merging; they have no area and would make the apex edges look
    # non-manifold.
    f = mesh.faces
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    if not keep.all():
        mesh = trimesh.Trimesh(
            vertices=mesh.vertices,
            faces=f[keep],
            face_attributes={"cad_face": mesh.face_attributes["cad_face"][keep]},
            process=False,
        )
    return mesh


def _transform(points, trsf):
    """Apply an OCCT gp_Trsf to points (N, 3)."""
    m = np.array([[trsf.Value(i, j) for j in range(1, 5)] for i in range(1, 4)])
    return points @ m[:, :3].T + m[:, 3]
