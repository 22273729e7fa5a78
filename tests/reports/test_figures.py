"""The report's figures from synthetic run data: valid SVG/JPEG, notes for missing data, caps, escaping, size."""

import base64
import json
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from partinspect.reports import figures as F
from partinspect.reports.html import render_html
from tests.reports.synthetic import PART_TO_CAMERA, make_figures, make_report

SVG = "{http://www.w3.org/2000/svg}"


@pytest.fixture(scope="module")
def data():
    return make_figures(seed=1, width=1224, height=1024, n_pts=60)


def _data_uri(body, mime):
    m = re.search(rf'src="data:{re.escape(mime)};base64,([A-Za-z0-9+/=]+)"', body)
    assert m, f"no {mime} data URI in the figure"
    return base64.b64decode(m.group(1))


def test_image_figure_is_svg_with_jpeg_and_coloured_overlays(data):
    fig = F.image_figure(data)
    assert fig.body and fig.note is None
    panels = re.findall(r"<svg class=\"photo\".*?</svg>", fig.body, flags=re.S)
    assert len(panels) == 2
    for panel in panels:
        root = ET.fromstring(panel)  # well-formed XML
        x0, y0, w, h = map(int, root.get("viewBox").split())
        assert root.tag == SVG + "svg" and 0 < w < 1224 and 0 < h < 1024  # cropped to the plate
        img = root.find(SVG + "image")
        assert (img.get("x"), img.get("y"), img.get("width"), img.get("height")) == tuple(map(str, (x0, y0, w, h)))
        jpeg = base64.b64decode(img.get("href").split(",", 1)[1])
        assert jpeg[:3] == b"\xff\xd8\xff"  # JPEG magic
        import cv2

        small = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
        assert small.shape == (h, w)  # the crop is narrower than IMAGE_WIDTH: not scaled
        groups = root.findall(f"{SVG}g[@class]")
        classes = {g.get("class") for g in groups}
        assert {"ov st-fail", "ov st-pass", "ov st-unmatched", "ov st-measured"} <= classes
    # circle-5 is missing in the right image: inconclusive only once.
    assert fig.body.count("ov st-inconclusive") == 1
    assert "fail (2)" in fig.body and "unmatched (2)" in fig.body


def test_crop_box_frames_the_overlays_or_keeps_the_whole_image():
    small = [{"xy": np.array([[400.0, 300.0], [600.0, 500.0]])}]
    x0, y0, x1, y1 = F.crop_box((1000, 2000), small)
    assert x0 < 400 < 600 < x1 and y0 < 300 < 500 < y1 and (x1 - x0) * (y1 - y0) < 0.7 * 2e6
    assert F.crop_box((1000, 2000), []) == (0, 0, 2000, 1000)
    wide = [{"xy": np.array([[10.0, 10.0], [1990.0, 990.0]])}]
    assert F.crop_box((1000, 2000), wide) == (0, 0, 2000, 1000)


def test_overlays_are_placed_on_pixel_centres_and_decimated():
    img = np.zeros((100, 200), np.uint8)
    t = np.linspace(0, 2 * np.pi, 5000)
    xy = np.c_[100 + 30 * np.cos(t), 50 + 30 * np.sin(t)]
    fig = F.image_figure({"left": img, "overlays": [
        {"image": "left", "xy": np.array([[0.0, 0.0], [10.0, 20.0]]), "kind": "line", "label": "line-1", "status": "pass"},
        {"image": "left", "xy": xy, "kind": "circle", "label": "circle-1", "status": "fail"},
        {"image": "left", "xy": np.array([[np.nan, 1.0], [2.0, 3.0]]), "kind": "line", "label": "x", "status": "pass"},
    ]})
    root = ET.fromstring(re.search(r"<svg class=\"photo\".*?</svg>", fig.body, flags=re.S).group(0))
    lines = root.findall(f".//{SVG}polyline[@class='fg']")
    assert lines[0].get("points") == "0.5,0.5 10.5,20.5"  # pass drawn first, failures on top  # OpenCV pixel centre (0, 0) is SVG (0.5, 0.5)
    assert len(lines) == 2  # the polyline with one finite point is dropped
    assert len(lines[1].get("points").split()) <= F.MAX_OVERLAY_POINTS
    assert "The right image was not given." in fig.note


def test_residual_histograms_are_svg_and_capped(data):
    fig = F.residual_figure(data)
    svg = _data_uri(fig.body, "image/svg+xml")
    assert ET.fromstring(svg).tag == SVG + "svg"
    assert b"<image" not in svg  # vector, not a raster in disguise
    assert "rms/σ" in fig.caption and "2 of 8" not in fig.caption
    assert F.MAX_RESIDUAL_PANELS == 24
    many = {"residuals": [{"label": f"line-{i}", "image": "left", "residuals": np.random.default_rng(i).normal(0, 0.1, 50),
                           "sigma": 0.1} for i in range(30)]}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(F, "MAX_RESIDUAL_PANELS", 5)  # the cap's logic, without drawing 24 panels twice
        capped = F.residual_figure(many)
    assert capped.note.startswith("Showing the first 5 of 30 fits")
    # A fit without a usable sigma still gets its histogram (no curve).
    odd = F.residual_figure({"residuals": [{"label": "a", "image": "left", "residuals": [0.1, -0.2, 0.05], "sigma": None}]})
    assert odd.body and "Median rms/σ" not in odd.caption


def test_sigma_figure_shows_depth_dominates_in_camera_frame(data):
    fig = F.sigma_figure(data, PART_TO_CAMERA)
    assert ET.fromstring(_data_uri(fig.body, "image/svg+xml")).tag == SVG + "svg"
    assert "left camera frame (Z = depth)" in fig.caption
    ratio = float(re.search(r"median σZ is ([0-9.]+)×", fig.caption).group(1))
    assert 3.0 < ratio < 4.5  # synthetic: depth sigma 12 um vs lateral ~3.3 um
    no_pose = F.sigma_figure(data)
    assert "part frame" in no_pose.caption and "cannot be named" in no_pose.caption


def test_scene_data_magnification_and_views(data):
    scene = F.scene_data(data, PART_TO_CAMERA)
    assert list(scene["views"])[0] == "iso" and "camera" in scene["views"]
    R = np.array(scene["views"]["camera"])
    assert np.allclose(R, PART_TO_CAMERA[:3, :3], atol=1e-6)
    for v in scene["views"].values():
        assert np.allclose(np.array(v) @ np.array(v).T, np.eye(3), atol=1e-5) and np.linalg.det(v) > 0
    assert scene["mag"] >= 1 and str(scene["mag"])[0] in "125"
    n_ell = sum(len(f["ep"]) for f in scene["features"])
    assert 0 < n_ell <= F.MAX_SCENE_ELLIPSOIDS
    assert all(len(f["ec"]) == len(f["ep"]) for f in scene["features"])
    fig = F.scene_figure(data, PART_TO_CAMERA)
    assert f"magnified {scene['mag']}×" in fig.caption
    assert "<canvas" in fig.body and "camera" in fig.body
    json.loads(F.scene_json(scene))


def test_missing_or_empty_keys_give_one_line_notes():
    figs = F.build_figures({"left": None, "overlays": [], "residuals": [], "points3d": []})
    assert [f.key for f in figs] == ["images", "residuals", "sigmas", "scene"]
    assert all(f.body is None and f.note and "\n" not in f.note for f in figs)
    assert F.build_figures(None) == [] and F.build_figures({}) == []
    # Only CAD edges: the 3D view still draws them.
    only_cad = F.build_figures({"cad_edges": [{"label": "line-1", "polyline": np.array([[0, 0, 0], [1, 0, 0.0]])}]})
    assert [f.key for f in only_cad if f.body] == ["scene"]


def test_a_figure_that_cannot_be_drawn_becomes_a_note():
    figs = F.build_figures({"residuals": [{"label": "a", "image": "left", "residuals": "not numbers", "sigma": 1.0}]})
    res = next(f for f in figs if f.key == "residuals")
    assert res.body is None and "could not be drawn" in res.note


def test_sixteen_bit_images_are_stretched_for_display():
    img = np.zeros((20, 30), np.uint16)
    img[:, 15:] = 1000  # a 10-bit camera's image in a 16-bit file
    out = F.display_image(img)
    assert out.dtype == np.uint8 and out.min() == 0 and out.max() == 255
    rgb = np.dstack([np.full((4, 4), 90, np.uint8)] * 3)
    assert F.display_image(rgb).shape == (4, 4)


def test_labels_are_escaped_in_figures_and_scene_json():
    nasty = '</script><script>alert("x")</script>'
    data = {
        "left": np.zeros((50, 60), np.uint8),
        "overlays": [{"image": "left", "xy": np.array([[1.0, 1], [20, 20]]), "kind": "line", "label": nasty, "status": "fail"}],
        "points3d": [{"label": nasty, "points": np.zeros((3, 3)), "covs": np.tile(np.eye(3) * 1e-6, (3, 1, 1)), "status": "fail"}],
        "cad_edges": [{"label": nasty, "polyline": np.array([[0, 0, 0], [1, 1, 1.0]])}],
        "residuals": [{"label": nasty, "image": "left", "residuals": np.linspace(-1, 1, 20), "sigma": 0.5}],
    }
    html = render_html(make_report(part=nasty), data)
    assert "<script>alert" not in html and "</script><script>" not in html
    assert html.count("<script") == 2  # the scene data block and the report's own script, nothing injected
    block = re.search(r'<script type="application/json" id="scene-data">(.*?)</script>', html, flags=re.S).group(1)
    assert json.loads(block)["features"][0]["label"] == nasty


def test_report_with_full_size_images_stays_under_3_mb():
    # 2448 x 2048 noise is the worst case for JPEG; real images compress better.
    data = make_figures(seed=2, n_pts=120)
    rng = np.random.default_rng(3)
    data["left"] = rng.integers(0, 256, data["left"].shape, dtype=np.uint8)
    for side in ("left", "right"):  # edges all over the images: nothing is cropped
        data["overlays"].append({"image": side, "xy": np.array([[0.0, 0.0], [2447.0, 2047.0]]), "kind": "line",
                                 "label": "", "status": "unmatched"})
    html = render_html(make_report(), data)
    assert len(html.encode()) < 3_000_000
    import cv2

    for uri in re.findall(r'href="data:image/jpeg;base64,([A-Za-z0-9+/=]+)"', html):
        small = cv2.imdecode(np.frombuffer(base64.b64decode(uri), np.uint8), cv2.IMREAD_UNCHANGED)
        assert small.shape[1] == F.IMAGE_WIDTH and abs(small.shape[0] - round(2048 * F.IMAGE_WIDTH / 2448)) <= 1


def test_same_data_same_bytes():
    data = make_figures(seed=6, width=612, height=512, n_pts=40)
    assert render_html(make_report(), data) == render_html(make_report(), data)


def _svg_root(fig):
    return ET.fromstring(_data_uri(fig.body, "image/svg+xml"))


def _by_class(root, tag, cls):
    return [e for e in root.iter(SVG + tag) if cls in (e.get("class") or "").split()]


def test_residual_panels_paths_and_red_exactly_outside_the_band():
    ratios = [0.5, 0.79, 0.81, 1.0, 1.24, 1.26, 2.0]
    z = np.random.default_rng(7).normal(size=400)
    z /= np.sqrt(np.mean(z**2))
    items = [{"label": f"line-{i}", "image": "left", "residuals": q * 0.1 * z, "sigma": 0.1}
             for i, q in enumerate(ratios)]
    items.append({"label": "no-sigma", "image": "right", "residuals": z, "sigma": None})
    root = _svg_root(F.residual_figure({"residuals": items}))
    panels = _by_class(root, "g", "panel")
    assert len(panels) == 8
    assert len(_by_class(root, "path", "hist")) == 8 and len(_by_class(root, "path", "hist-edge")) == 8
    assert len(_by_class(root, "path", "curve")) == 7  # no predicted curve without a sigma
    red = [p.find(f"{SVG}text[@class='box']").get("fill") == F.RED for p in panels]
    assert red == [True, True, False, False, False, True, True, False]
    box = [t.text for t in panels[0].find(f"{SVG}text[@class='box']")]
    assert box == ["n = 400", "rms 0.05 px", "σ 0.1 px", "rms/σ 0.50"]
    titles = [t.text for t in _by_class(root, "text", "title")]
    assert titles[0] == "line-0 (left)" and titles[-1] == "no-sigma (right)"
    # Rows of 4: the x label under the lowest panel of each column.
    assert len(_by_class(root, "text", "xlabel")) == 4


def test_residual_figure_drops_non_finite_and_escapes_labels():
    res = np.r_[np.linspace(-0.1, 0.1, 30), np.nan, np.inf, -np.inf]
    fig = F.residual_figure({"residuals": [{"label": "<&>", "image": "a&b", "residuals": res, "sigma": 0.05}]})
    root = _svg_root(fig)  # well-formed despite the label
    assert [t.text for t in _by_class(root, "text", "title")] == ["<&> (a&b)"]
    assert root.find(f".//{SVG}text[@class='box']")[0].text == "n = 30"


def test_sigma_figure_panels_lines_rules_and_legend(data):
    fig = F.sigma_figure(data, PART_TO_CAMERA)
    root = _svg_root(fig)
    assert len(_by_class(root, "g", "panel")) == 2
    assert [e.get("class") for e in _by_class(root, "path", "line")] == ["line sigma-X", "line sigma-Y", "line sigma-Z"]
    n_feats = len(data["points3d"])
    assert _by_class(root, "path", "rule")[0].get("d").count("M") == n_feats - 1  # between features
    assert len(_by_class(root, "path", "hist")) == 3 and len(_by_class(root, "path", "hist-edge")) == 3
    legend = [t.text for g in _by_class(root, "g", "legend") for t in g.iter(SVG + "text")]
    med = re.search(r"medians X ([0-9.]+), Y ([0-9.]+), Z ([0-9.]+) µm", fig.caption).groups()
    assert legend == ["σX", "σY", "σZ"] + [f"σ{a}: median {m} µm" for a, m in zip("XYZ", med)]
    n = sum(len(p["points"]) for p in data["points3d"])
    assert f"({n_feats} features, {n} points)" in "".join(t.text or "" for t in _by_class(root, "text", "xlabel"))


def test_sigma_figure_drops_non_finite_covariances_and_pools_long_runs():
    covs = np.tile(np.eye(3) * 1e-6, (5000, 1, 1))
    covs[:10] = np.nan
    fig = F.sigma_figure({"points3d": [{"label": "a", "points": np.zeros((5000, 3)), "covs": covs},
                                       {"label": "b", "points": np.zeros((2, 3)), "covs": np.full((2, 3, 3), np.inf)}]})
    root = _svg_root(fig)
    assert "(1 features, 4990 points)" in "".join(t.text or "" for t in _by_class(root, "text", "xlabel"))
    assert all(2 <= e.get("d").count(",") <= 3000 for e in _by_class(root, "path", "line"))
    assert _by_class(root, "path", "rule") == []  # one feature: no boundary


def test_figures_svg_same_bytes(data):
    assert F.residual_figure(data).body == F.residual_figure(data).body
    assert F.sigma_figure(data, PART_TO_CAMERA).body == F.sigma_figure(data, PART_TO_CAMERA).body


def test_sigma_figure_of_one_point_keeps_its_ticks_inside():
    fig = F.sigma_figure({"points3d": [{"label": "a", "points": np.zeros((1, 3)), "covs": np.eye(3)[None] * 1e-6}]})
    root = _svg_root(fig)
    panel = _by_class(root, "g", "panel")[0]
    ticks = [t.text for t in panel.iter(SVG + "text") if t.get("text-anchor") == "middle" and not t.get("class")]
    assert ticks == ["0"]  # the x axis runs from -0.5 to 0.5: no tick at 1 or at fractions of a point
