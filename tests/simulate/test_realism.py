"""The render's realism options: edge breaks, metal, defocus, photon noise.

Each changes what it models and nothing else: checked on a small box with a
hole (fast to break, mesh and render) and on the functions' own arithmetic.
"""

import json

import numpy as np
import pytest

from partinspect.cad.raycast import Shading, build_scene, cast, pixel_rays

BOX = (20.0, 10.0, 5.0)  # x, y, z extent, mm; the part frame's origin at the box's front-bottom-left
HOLE = (6.0, 5.0, 1.5)  # x, y, radius of a through hole, mm


def _box():
    import cadquery as cq

    w, d, h = BOX
    part = cq.Workplane("XY").box(w, d, h, centered=False)
    x, y, r = HOLE
    return part.cut(cq.Solid.makeCylinder(r, h, cq.Vector(x, y, 0.0))).val()


@pytest.fixture(scope="module")
def box():
    return _box()


@pytest.fixture(scope="module")
def box_step(tmp_path_factory):
    import cadquery as cq

    path = tmp_path_factory.mktemp("box") / "box.step"
    cq.exporters.export(_box(), str(path))
    return path


@pytest.fixture(scope="module")
def cube_step(tmp_path_factory):
    """A 4 mm cube: no edge of it can take a 5 mm break."""
    import cadquery as cq

    path = tmp_path_factory.mktemp("cube") / "cube.step"
    cq.exporters.export(cq.Workplane("XY").box(4, 4, 4).val(), str(path))
    return path


def _scene(shape, min_size=None):
    from partinspect.cad.mesh import tessellate
    from partinspect.cad.raycast import RENDER_ANGULAR_TOLERANCE, RENDER_TOLERANCE

    return build_scene(tessellate(shape, RENDER_TOLERANCE, RENDER_ANGULAR_TOLERANCE, min_size=min_size))


def _look_at(C, target, f, size):
    """K, D, R, t of a camera at ``C`` looking at ``target`` with the part's x axis along the image's rows."""
    w, h = size
    K = np.array([[f, 0, w / 2 - 0.5], [0, f, h / 2 - 0.5], [0, 0, 1.0]])
    d = np.asarray(target, float) - C
    d /= np.linalg.norm(d)
    x = np.cross([0, 0, -1.0], d)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(d, x), d])
    return K, np.zeros(5), R, -R @ C


def _camera_above_edge(alpha, distance, f=4000.0, size=(200, 120)):
    """A camera at elevation ``alpha`` looking along +y at the box's top back edge's middle."""
    edge = np.array([BOX[0] / 2, BOX[1], BOX[2]])
    C = edge - distance * np.array([0.0, np.cos(alpha), -np.sin(alpha)])
    return (*_look_at(C, edge, f, size), C)


def _project(K, R, t, X):
    x = R @ X + t
    return np.array([K[0, 0] * x[0] / x[2] + K[0, 2], K[1, 1] * x[1] / x[2] + K[1, 2]])


# --- edge breaks -------------------------------------------------------------


def test_parse_edge_break():
    from partinspect.simulate.edge_break import EdgeBreak, parse_edge_break

    assert parse_edge_break("0.1") == EdgeBreak("fillet", 0.1)
    assert parse_edge_break("R0.25") == EdgeBreak("fillet", 0.25)
    assert parse_edge_break("C0.2") == EdgeBreak("chamfer", 0.2)
    for bad in ("", "R", "X0.1", "-0.1", "0", "C11"):
        with pytest.raises(ValueError):
            parse_edge_break(bad)


def test_every_convex_edge_is_broken_and_concave_ones_are_not():
    import cadquery as cq

    from partinspect.cad.features import inventory
    from partinspect.simulate.edge_break import EdgeBreak, break_edges

    # An L-shaped block: one concave edge (the inner corner), 17 convex ones (5 along y, 6 round each end).
    block = cq.Workplane("XY").box(20, 10, 10, centered=False).cut(cq.Workplane("XY").box(10, 10, 5, centered=False)
                                                                  .translate((10, 0, 5))).val()
    broken, record = break_edges(block, EdgeBreak("fillet", 0.5), inventory(block))
    assert record["edges"]["convex"] == 17 and record["edges"]["concave"] == 1
    assert record["broken"] == 17 and record["unbroken"] == []
    # 8 faces + 17 fillets + the corner blends where three fillets meet
    assert len(broken.Faces()) > 8 + 17
    # The volume removed by a fillet of radius r along a length L is (1 - pi/4) r^2 L.
    assert block.Volume() - broken.Volume() > (1 - np.pi / 4) * 0.25 * 100


def test_an_edge_the_part_cannot_take_is_reported_the_rest_broken(box):
    import cadquery as cq

    from partinspect.cad.features import inventory
    from partinspect.simulate.edge_break import EdgeBreak, break_edges

    # A 2 mm radius fits the box's 5 mm high sides but not the rims of its
    # 1.5 mm hole: the rims stay sharp and are named.
    broken, record = break_edges(box, EdgeBreak("fillet", 2.0), inventory(box))
    assert record["edges"]["convex"] == 14
    unbroken = sorted(u["feature"] for u in record["unbroken"])
    assert unbroken == ["circle-1", "circle-2"]
    assert record["broken"] == 12
    assert broken.isValid() and broken.Volume() < box.Volume()
    cube = cq.Workplane("XY").box(4, 4, 4).val()
    with pytest.raises(ValueError, match="too large"):
        break_edges(cube, EdgeBreak("fillet", 5.0))


@pytest.mark.parametrize("kind, size", [("fillet", 0.3), ("chamfer", 0.3)])
def test_a_broken_silhouette_edge_moves_by_the_predicted_amount(box, kind, size):
    """A camera 30 degrees above the top face sees its back edge as the
    silhouette: rounded, the silhouette is the fillet's tangent ray; chamfered,
    the chamfer's upper line. Flat shading (no light) makes the image the
    silhouette's pixel coverage, so its position is read to 1/256 px."""
    from partinspect.simulate.edge_break import EdgeBreak, break_edges, mesh_min_size
    from partinspect.simulate.render import render_radiance

    alpha, distance = np.radians(30.0), 100.0
    K, D, R, t, C = _camera_above_edge(alpha, distance)
    flat = Shading(ambient=200.0, albedo=0.0, background=25.0)
    spec = EdgeBreak(kind, size)
    broken, _ = break_edges(box, spec)
    rows = slice(40, 80)  # the silhouette row is near the image's middle (row 59.5)

    def silhouette_row(scene):
        img, _ = render_radiance(scene, K, D, R, t, (200, 120), np.array([0, 0, 1.0]), flat)
        cover = (img[rows, 90:110] - 25.0) / 175.0  # the object fills the window below the silhouette
        return rows.stop - 0.5 - cover.sum(axis=0).mean()

    measured = silhouette_row(_scene(broken, mesh_min_size(spec))) - silhouette_row(_scene(box))

    def v_of(p):
        x = R @ p + t
        return K[1, 1] * x[1] / x[2] + K[1, 2]

    y1, z1 = BOX[1], BOX[2]
    if kind == "fillet":
        # tangent from the camera to the fillet's circle (centre Q, radius r) in the plane x = const
        Q = np.array([BOX[0] / 2, y1 - size, z1 - size])
        q = Q - C
        L = np.linalg.norm(q)
        beta = np.arcsin(size / L)
        axis = np.array([1.0, 0, 0])
        candidates = [np.cos(b) * q + np.sin(b) * np.cross(axis, q) for b in (beta, -beta)]
        v_edge = min(v_of(C + c) for c in candidates)
    else:
        v_edge = min(v_of(np.array([BOX[0] / 2, y1 - size, z1])), v_of(np.array([BOX[0] / 2, y1, z1 - size])))
    predicted = v_edge - v_of(np.array([BOX[0] / 2, y1, z1]))
    # about 4.4 px for the fillet (0.3 mm x (sin + cos - 1) x 40 px/mm)
    assert predicted > 2.0
    assert measured == pytest.approx(predicted, abs=0.05)


def test_a_fillet_changes_the_image_near_the_edges_only():
    import cadquery as cq
    from scipy import ndimage

    from partinspect.simulate.edge_break import EdgeBreak, break_edges, mesh_min_size
    from partinspect.simulate.render import render_radiance

    size = (160, 120)
    camera = _look_at(np.array([-20.0, -50.0, 60.0]), np.array([10.0, 5.0, 2.5]), 1500.0, size)
    light = np.array([-0.3, -0.5, 0.8]) / np.linalg.norm([-0.3, -0.5, 0.8])
    spec = EdgeBreak("fillet", 0.2)
    box = cq.Workplane("XY").box(*BOX, centered=False).val()
    sharp = _scene(box)
    broken = _scene(break_edges(box, spec)[0], mesh_min_size(spec))
    a, _ = render_radiance(sharp, *camera, size, light, psf=0.6)
    b, _ = render_radiance(broken, *camera, size, light, psf=0.6)
    v, u = np.mgrid[0:size[1], 0:size[0]]
    origin, d = pixel_rays(np.stack([u.ravel(), v.ravel()], 1).astype(float), *camera)
    label = cast(sharp, origin, d).label.reshape(v.shape)
    edges = (np.diff(label, axis=0, append=label[-1:]) != 0) | (np.diff(label, axis=1, append=label[:, -1:]) != 0)
    # the fillet is up to 4 px wide here, its supersampled band 1 px wider, and the PSF reaches 5 px
    near = ndimage.binary_dilation(edges, iterations=10)
    assert ((label >= 0) & ~near).sum() > 2000  # most of the faces' area is checked
    assert np.abs(a - b)[~near].max() < 0.01
    assert np.abs(a - b)[near].max() > 20


def test_a_small_fillet_is_meshed_as_a_curve(box):
    """A 0.1 mm fillet is split into many facets across its quarter turn:
    its smooth normals then turn by at most 1/8 rad between mesh rows."""
    from partinspect.cad.mesh import tessellate
    from partinspect.cad.raycast import RENDER_ANGULAR_TOLERANCE, RENDER_TOLERANCE
    from partinspect.simulate.edge_break import EdgeBreak, break_edges, mesh_min_size

    spec = EdgeBreak("fillet", 0.1)
    broken, _ = break_edges(box, spec)
    mesh = tessellate(broken, RENDER_TOLERANCE, RENDER_ANGULAR_TOLERANCE, min_size=mesh_min_size(spec))
    assert mesh.is_watertight
    # vertices on the top back edge's fillet (a quarter cylinder along x at the box's middle)
    v = np.asarray(mesh.vertices)
    dy, dz = v[:, 1] - (BOX[1] - 0.1), v[:, 2] - (BOX[2] - 0.1)
    on = (np.abs(np.hypot(dy, dz) - 0.1) < 1e-5) & (dy > -1e-6) & (dz > -1e-6) & (np.abs(v[:, 0] - 10) < 9.95)
    angles = np.unique(np.round(np.arctan2(dz[on], dy[on]), 6))
    assert angles.min() == pytest.approx(0, abs=1e-6) and angles.max() == pytest.approx(np.pi / 2, abs=1e-6)
    assert len(angles) >= 8 and np.diff(angles).max() <= 1 / 8 + 1e-6


# --- photon noise and vignetting ---------------------------------------------


def test_photon_noise_follows_the_photon_transfer_line():
    """var(DN) = K mean + K^2 read^2 + 1/12 over flat patches (EMVA 1288)."""
    from partinspect.simulate.photon import PhotonSensor, photon_sensor

    sensor = PhotonSensor(full_well=20000.0, gain=0.05, read_noise=8.0)
    means = np.array([20.0, 60.0, 100.0, 140.0, 180.0, 220.0])
    image = np.repeat(means, 200 * 200).reshape(len(means) * 200, 200)
    out = photon_sensor(image, sensor, np.random.default_rng(3)).astype(float).reshape(len(means), -1)
    np.testing.assert_allclose(out.mean(axis=1), means, atol=0.05)
    slope, intercept = np.polyfit(out.mean(axis=1), out.var(axis=1), 1)
    assert slope == pytest.approx(sensor.gain, rel=0.03)
    assert intercept == pytest.approx(sensor.gain ** 2 * sensor.read_noise ** 2 + 1 / 12, abs=0.05)


def test_photon_full_well_saturates():
    from partinspect.simulate.photon import PhotonSensor, photon_sensor

    # 200 DN / 0.05 = 4000 e- on average, capped at 3000 e- = 150 DN
    out = photon_sensor(np.full((50, 50), 200.0), PhotonSensor(3000.0, 0.05, 0.0), np.random.default_rng(0))
    assert np.all(out == 150)


def test_vignetting_is_cos4_of_the_chief_ray():
    from partinspect.simulate.photon import cos4_vignetting

    K = np.array([[500.0, 0, 100], [0, 500.0, 50], [0, 0, 1]])
    v = cos4_vignetting(K, np.zeros(5), (201, 101))
    assert v[50, 100] == pytest.approx(1.0)
    theta = np.arctan(np.hypot(100, 50) / 500.0)
    assert v[0, 0] == pytest.approx(np.cos(theta) ** 4, rel=1e-9)
    assert v[0, 200] == pytest.approx(v[100, 0], rel=1e-9)


# --- defocus -----------------------------------------------------------------


def test_circle_of_confusion_is_the_thin_lens_one():
    from partinspect.simulate.defocus import ThinLens, circle_of_confusion

    lens, f, pitch = ThinLens(4.0, 400.0), 25.0, 3.45e-3
    assert circle_of_confusion(400.0, lens, f, pitch) == 0.0
    # image distances, and the cone from the aperture cut by the sensor
    s_f, s = f * 400 / (400 - f), f * 450 / (450 - f)
    assert circle_of_confusion(450.0, lens, f, pitch) == pytest.approx((f / 4.0) * (s_f - s) / s / pitch, rel=1e-12)
    c = circle_of_confusion(np.array([360.0, 380.0, 400.0, 420.0, 440.0]), lens, f, pitch)
    assert np.all(np.diff(c[:3]) < 0) and np.all(np.diff(c[2:]) > 0)


def test_edge_spread_grows_with_the_distance_from_focus():
    """A vertical step edge blurred by a blur circle growing along it: the
    line spread's variance at each row is the disc's, c^2 / 16, plus the
    level blend's."""
    from partinspect.simulate.defocus import defocus

    h, w = 60, 80
    image = np.where(np.arange(w) < 40, 50.0, 200.0)[None, :].repeat(h, axis=0)
    coc = np.repeat(np.linspace(0.0, 12.0, h)[:, None], w, axis=1)
    out = defocus(image, coc)
    lsf = np.diff(out, axis=1) / 150.0
    x = np.arange(w - 1) + 0.5
    mean = (lsf * x).sum(axis=1)
    var = (lsf * (x - mean[:, None]) ** 2).sum(axis=1)
    assert np.all(np.abs(mean - 39.5) < 0.01)  # the edge stays where it is
    np.testing.assert_array_equal(defocus(image, np.zeros_like(coc)), image)  # in focus: untouched
    assert np.all(np.diff(var[::6]) > 0)
    # at the ladder's levels the spread is the disc's (anti-aliased on the pixel grid)
    rows = np.nonzero(np.isclose(coc[:, 0] % 0.5, 0) & (coc[:, 0] >= 4))[0]
    np.testing.assert_allclose(var[rows], coc[rows, 0] ** 2 / 16, rtol=0.06)


def test_depth_map_is_the_camera_z_of_the_surface(box):
    from partinspect.simulate.defocus import depth_map

    K, D, R, t, _ = _camera_above_edge(np.radians(50.0), 120.0, f=2000.0, size=(80, 60))
    scene = _scene(box)
    depth = depth_map(scene, K, D, R, t, (80, 60))
    v, u = np.mgrid[0:60, 0:80]
    origin, d = pixel_rays(np.stack([u.ravel(), v.ravel()], 1).astype(float), K, D, R, t)
    hit = cast(scene, origin, d)
    top = np.isfinite(hit.distance) & (np.abs((origin + hit.distance[:, None] * d)[:, 2] - BOX[2]) < 1e-6)
    assert top.sum() > 500
    # the ray meets the plane z = BOX[2]; its depth is the camera-frame z of that point
    X = origin + ((BOX[2] - origin[2]) / d[top, 2])[:, None] * d[top]
    np.testing.assert_allclose(depth.ravel()[top], (X @ R.T + t)[:, 2], atol=1e-4)
    assert np.isnan(depth.ravel()[~np.isfinite(hit.distance)]).all()


# --- metal ---------------------------------------------------------------------


def _radiance(scene, camera, light, fin, size):
    from partinspect.simulate.render import render_radiance

    img, _ = render_radiance(scene, *camera, size, light, Shading(), finish=fin)
    return img


def _mirror_light(n, C, X):
    """Unit direction towards a light whose mirror reflection at X (normal n) reaches C."""
    v = (C - X) / np.linalg.norm(C - X)
    return 2 * (v @ n) * n - v


def test_a_highlight_on_a_hole_wall_sits_where_it_mirrors_the_light_and_moves_with_it(box):
    """Inside the hole, the brightest point of the wall is at the azimuth
    where the wall mirrors the light into the camera; a light aimed at
    another azimuth moves it there."""
    from dataclasses import replace

    from partinspect.simulate.material import MATERIALS, finish

    size = (160, 120)
    x0, y0, r = HOLE
    C = np.array([x0, y0 - 60.0, BOX[2] + 90.0])
    camera = _look_at(C, np.array([x0, y0, BOX[2] / 2]), 4000.0, size)
    scene = _scene(box)
    fin = finish(scene, replace(MATERIALS["steel"], mark_slope=0.0, mark_albedo=0.0))
    v, u = np.mgrid[0:size[1], 0:size[0]]
    origin, d = pixel_rays(np.stack([u.ravel(), v.ravel()], 1).astype(float), *camera)
    hits = cast(scene, origin, d)
    X = origin + np.where(np.isfinite(hits.distance), hits.distance, 0)[:, None] * d
    wall = np.isfinite(hits.distance) & (np.abs(np.hypot(X[:, 0] - x0, X[:, 1] - y0) - r) < 1e-3) \
        & (X[:, 2] > 0.5) & (X[:, 2] < BOX[2] - 0.5)
    assert wall.sum() > 1000
    found = []
    for azimuth in np.radians([65.0, 115.0]):
        P = np.array([x0 + r * np.cos(azimuth), y0 + r * np.sin(azimuth), 3.0])
        n = -np.array([np.cos(azimuth), np.sin(azimuth), 0.0])  # the wall faces the hole's axis
        img = _radiance(scene, camera, _mirror_light(n, C, P), fin, size).ravel()
        brightest = np.flatnonzero(wall)[np.argmax(img[wall])]
        found.append(np.arctan2(X[brightest, 1] - y0, X[brightest, 0] - x0))
        assert found[-1] == pytest.approx(azimuth, abs=np.radians(4.0))
        assert img[brightest] > 255  # a highlight saturates the sensor
    assert found[1] - found[0] > np.radians(40.0)


def test_left_and_right_see_a_metal_face_differently_a_matte_one_alike(box):
    """The same point of the top face, seen from two cameras 30 mm apart:
    Lambertian greys agree, a metal's highlight does not."""
    from partinspect.simulate.material import MATERIALS, finish

    size = (120, 90)
    X = np.array([15.0, 6.0, BOX[2]])
    Cl = X + np.array([-15.0, -80.0, 120.0])
    Cr = Cl + np.array([30.0, 0, 0])
    left, right = _look_at(Cl, X, 1500.0, size), _look_at(Cr, X, 1500.0, size)
    scene = _scene(box)
    light = _mirror_light(np.array([0, 0, 1.0]), Cl, X)
    fin = finish(scene, MATERIALS["aluminium"])

    def grey_at(camera, fin):
        img = _radiance(scene, camera, light, fin, size)
        u, v = np.rint(_project(camera[0], camera[2], camera[3], X)).astype(int)
        return img[v - 1:v + 2, u - 1:u + 2].mean()

    assert grey_at(left, None) == pytest.approx(grey_at(right, None), abs=0.5)
    assert abs(grey_at(left, fin) - grey_at(right, fin)) > 20


def test_machining_marks_are_grooves_of_the_stated_period(box):
    """Along a plane face's groove normal the grey oscillates with the stated
    period; across it, it does not; a pixel as wide as a period clamps them away."""
    from partinspect.simulate.material import MATERIALS, finish, shade_material

    scene = _scene(box)
    m = MATERIALS["aluminium"]
    fin = finish(scene, m, seed=4)
    top = next(k for k in range(len(fin.grooves)) if np.any((scene.labels == k)
                                                              & (scene.flat_normals[:, 2] > 0.99)))
    g = fin.grooves[top]
    assert abs(g[2]) < 1e-9  # within the top plane
    across = np.cross([0, 0, 1.0], g)
    light = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])

    def greys(direction, pixel_angle):
        s = np.linspace(0, 4 * m.mark_period, 200, endpoint=False)
        X = np.array([16.0, 5.0, BOX[2]]) + s[:, None] * direction
        C = np.array([16.0, -60.0, 100.0])
        d = (X - C) / np.linalg.norm(X - C, axis=1)[:, None]
        hits = cast(scene, C, d)
        assert np.all(hits.label == top)
        return s, shade_material(scene, hits, C, d, light, Shading(), fin, pixel_angle).astype(float)

    _, along = greys(g, 1e-7)
    spectrum = np.abs(np.fft.rfft(along - along.mean()))
    assert np.argmax(spectrum) == 4  # four periods in the sample
    assert along.std() > 1.0
    _, flat = greys(across, 1e-7)
    assert flat.std() < 0.05 * along.std()
    # footprint = distance * pixel angle / |n.v| = one period: sinc(1) = 0
    dist = np.linalg.norm(np.array([16.0, 5.0, BOX[2]]) - np.array([16.0, -60.0, 100.0]))
    nv = 95.0 / dist
    _, clamped = greys(g, m.mark_period * nv / dist)
    assert clamped.std() < 0.05 * along.std()


# --- the command ---------------------------------------------------------------


def test_options_off_give_the_same_bytes_and_on_are_recorded(box_step, tmp_path):
    from partinspect.simulate.folder import render_to_folder

    size = (320, 256)
    plain = render_to_folder(box_step, tmp_path / "plain", seed=2, image_size=size)
    render_to_folder(box_step, tmp_path / "matte", seed=2, image_size=size, material="matte")
    for name in ("images/left.png", "images/right.png", "truth.json"):
        assert (tmp_path / "plain" / name).read_bytes() == (tmp_path / "matte" / name).read_bytes()
    assert not {"edge_break", "material", "defocus", "photon"} & set(plain)

    render_to_folder(box_step, tmp_path / "real", seed=2, image_size=size, edge_break="0.2",
                            material="steel:3", defocus="2.8,380", photon="10000,0.0255,5", light="0,-1,-1")
    truth = json.loads((tmp_path / "real" / "truth.json").read_text())
    assert truth["noise"] is None
    assert truth["edge_break"]["kind"] == "fillet" and truth["edge_break"]["size"] == 0.2
    assert truth["edge_break"]["broken"] == 14 and truth["edge_break"]["unbroken"] == []
    assert truth["tessellation"]["min_size"] == pytest.approx(0.025)
    assert truth["material"]["name"] == "steel" and truth["material"]["seed"] == 3
    assert truth["defocus"]["f_number"] == 2.8 and truth["defocus"]["focus"] == 380.0
    lo, hi = truth["defocus"]["coc_px"]["left"]
    assert 0 <= lo < hi
    assert truth["photon"]["gain"] == 0.0255 and truth["photon"]["units"]["gain"] == "DN/e-"
    np.testing.assert_allclose(truth["shading"]["light_direction_rig"], [0, -0.5 ** 0.5, -0.5 ** 0.5])
    # the features stay the sharp model's
    before = json.loads((tmp_path / "plain" / "truth.json").read_text())
    # the features, their visibility included, are the sharp model's
    assert truth["features"] == before["features"]
    assert truth["part_to_camera"] == before["part_to_camera"]


@pytest.mark.parametrize("args, words", [
    (["--edge-break", "X1"], "--edge-break"),
    (["--edge-break", "5"], "too large"),
    (["--material", "gold"], "unknown material"),
    (["--defocus", "0.1,400"], "f-number"),
    (["--defocus", "8"], "F_NUMBER,FOCUS_MM"),
    (["--photon", "1000,0.1"], "FULL_WELL,GAIN,READ"),
    (["--photon", "1000,-0.1,2"], "gain"),
    (["--photon", "1000,0.1,2", "--noise", "1"], "exclude"),
    (["--light", "0,0"], "--light"),
])
def test_bad_realism_values_are_one_line_exit_2(cube_step, tmp_path, capsys, args, words):
    from partinspect.cli import main

    out = tmp_path / "r"
    code = main(["render", str(cube_step), str(out), "--size", "64x48", "-q", *args])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and words in err and "Traceback" not in err
    assert not out.exists()


def test_noiseless_radiance_plus_each_draw_is_the_render(box_step, tmp_path):
    """render_noiseless + the sensor's draw + stated_calibration give render_to_folder's bytes."""
    import cv2

    from partinspect.simulate.folder import render_noiseless, render_to_folder, stated_calibration
    from partinspect.simulate.photon import parse_photon, photon_sensor
    from partinspect.simulate.render import camera_vignetting, sensor
    from partinspect.vision.calibration import write_calibration

    size = (320, 256)
    real = {"material": "aluminium:2", "defocus": "4,380"}
    render_to_folder(box_step, tmp_path / "r", seed=5, image_size=size, photon="10000,0.0255,5", calib_error=3,
                     **real)
    (left, right), rig, truth = render_noiseless(box_step, image_size=size, **real)
    rng = np.random.default_rng(5)
    for index, (name, radiance) in enumerate((("left", left), ("right", right))):
        drawn = photon_sensor(radiance, parse_photon("10000,0.0255,5"), rng, camera_vignetting(rig, index))
        written = cv2.imread(str(tmp_path / "r" / "images" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(drawn, written)
    write_calibration(tmp_path / "stated.yaml", stated_calibration(rig, 3))
    assert (tmp_path / "stated.yaml").read_bytes() == (tmp_path / "r" / "images" / "calibration.yaml").read_bytes()
    from partinspect.simulate.truth import to_json

    truth, written = json.loads(to_json(truth)), json.loads((tmp_path / "r" / "truth.json").read_text())
    assert truth["features"] == written["features"] and truth["defocus"] == written["defocus"]
    # Gaussian noise of the plain render: the left image's noise drawn first
    render_to_folder(box_step, tmp_path / "p", seed=6, image_size=size, noise=1.5)
    (left, _), _, _ = render_noiseless(box_step, image_size=size)
    plain = cv2.imread(str(tmp_path / "p" / "images" / "left.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(sensor(left, 1.5, np.random.default_rng(6)), plain)
