"""Why an edge was not measured names the condition: here, saturation (a highlight or over-exposure)."""

import json
import shutil

import cv2
import numpy as np

from partinspect.diagnosis import saturated_along, saturation_level


def test_saturation_level_is_the_sensors_top():
    img8 = np.full((10, 10), 100, np.uint8)
    assert saturation_level(img8, 8) == 255
    img12 = np.full((100, 100), 1000, np.uint16)
    img12[:5] = 4095  # a 12-bit sensor's clipped pixels in a 16-bit file
    assert saturation_level(img12, 16) == 4095
    img12[:5] = 3000
    img12[0, 0] = 3001  # one bright pixel is no pile-up
    assert saturation_level(img12, 16) == 65535


def test_saturated_along_counts_points_with_clipped_pixels_nearby():
    img = np.zeros((50, 50), np.uint8)
    img[:, 30:] = 255
    uv = np.column_stack([np.linspace(5, 45, 41), np.full(41, 20.0)])  # a horizontal edge across the image
    frac = saturated_along(img, uv, 255)
    assert abs(frac - 19 / 41) < 0.03  # x >= 27 lies within 3 px of the clipped half
    assert saturated_along(img, uv + [0, 1000], 255) == 0.0  # outside the image: nothing counts


def test_a_rim_under_a_highlight_says_so(repo, tmp_path):
    """The plate's 12 mm hole clipped to 255 around its rim in the left image: not measured, and the reason says why."""
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.cad.edge_sampling import feature_geometry, sample_edge
    from partinspect.pipeline import run_inspection
    from partinspect.vision.calibration import project_points, read_calibration

    src = repo / "examples" / "plate"
    images = tmp_path / "images"
    shutil.copytree(src / "images", images)
    truth = json.loads((src / "truth.json").read_text())
    pose = np.asarray(truth["part_to_camera"], float)
    calib = read_calibration(images)
    inv = inventory(load_step(src / "part.step"))
    rim = max((f for f in inv.of_kind("circle") if abs(f.radius - 6.0) < 1e-6), key=lambda f: f.center[2])
    pts, _ = sample_edge(rim.kind, feature_geometry(rim))
    uv = project_points(pts @ pose[:3, :3].T + pose[:3, 3], calib.K1, calib.D1, np.eye(3), np.zeros(3))
    left = cv2.imread(str(images / "left.png"), cv2.IMREAD_UNCHANGED)
    mask = np.zeros(left.shape, np.uint8)
    cv2.polylines(mask, [np.rint(uv).astype(np.int32)], True, 1, thickness=13)
    left[mask > 0] = 255
    cv2.imwrite(str(images / "left.png"), left)

    report = run_inspection(src / "part.step", images, tmp_path / "out").report
    entry = next(f for f in report["features"] if f["id"] == rim.id)
    assert entry["measured"] is None
    assert "saturated (grey level 255)" in entry["reason"] and "left image" in entry["reason"]
    others = [f for f in report["features"] if f["measured"] is None and f["id"] != rim.id]
    assert not any("saturated" in f["reason"] for f in others)
