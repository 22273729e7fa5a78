"""calibration.html: the stereo calibration report, self-contained like report.html.

It shows what a metrologist needs to trust a calibration: how much of each
image the board covered (distortion is only known where corners were seen),
the reprojection error of each view, the average epipolar error, every
parameter with its standard uncertainty, and each rejected view with its
reason. Images are inline PNGs (base64), the bar chart inline SVG; nothing is
fetched from the network.
"""

from __future__ import annotations

import base64
import datetime as _dt
import os
from pathlib import Path

import numpy as np

from partinspect.atomic import write_text_atomic

__all__ = ["coverage_png", "parameter_rows", "render_calibration_html", "write_calibration_report"]

_FIG_WIDTH = 480


def coverage_png(size, point_sets):
    """A PNG of where the board corners fell in one camera's image.

    Parameters
    ----------
    size : tuple of int
        ``(width, height)`` of the image, px.
    point_sets : list of ndarray, shape (N_i, 2)
        Corners of each used view, px.

    Returns
    -------
    bytes
        PNG data, ``_FIG_WIDTH`` px wide: each view's board area as a
        translucent hull, its corners as dots, on the image frame.
    """
    import cv2

    w, h = size
    s = _FIG_WIDTH / w
    H = max(1, int(round(h * s)))
    fill = np.zeros((H, _FIG_WIDTH), np.float32)
    for pts in point_sets:
        hull = cv2.convexHull(np.round(np.asarray(pts) * s * 16).astype(np.int32))
        mask = np.zeros_like(fill)
        cv2.fillPoly(mask, [hull], 1.0, lineType=cv2.LINE_AA, shift=4)
        fill += mask
    # Darker where more views overlap; white where no view reached: the uncovered image area.
    shade = 1.0 - 0.55 * np.clip(fill / max(1, len(point_sets)) * 2.5, 0, 1)
    tint = np.array([1.0, 0.93, 0.86])  # BGR: covered area in a cool blue-grey, uncovered stays white
    img = (255 * (1 - (1 - shade)[..., None] * (2 - tint))).clip(0, 255).astype(np.uint8)
    for pts in point_sets:
        for u, v in np.asarray(pts) * s:
            cv2.circle(img, (int(round(u * 16)), int(round(v * 16))), 2 * 16, (58, 122, 27), -1, cv2.LINE_AA, shift=4)
    cv2.rectangle(img, (0, 0), (_FIG_WIDTH - 1, H - 1), (48, 35, 29), 1)
    return cv2.imencode(".png", img)[1].tobytes()


def _data_uri(png):
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def parameter_rows(calib):
    """Rows ``(camera, name, value, standard uncertainty, unit)`` of every parameter.

    Parameters
    ----------
    calib : StereoCalibration
        With ``std`` entries.
    """
    import cv2

    dist_names = ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "τx", "τy"]
    rows = []
    for cam, K, D, key in (("left", calib.K1, calib.D1, "intrinsics1"), ("right", calib.K2, calib.D2, "intrinsics2")):
        values = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *D]
        names = ["fx", "fy", "cx", "cy", *dist_names[: len(D)]]
        units = ["px"] * 4 + ["–"] * len(D)
        std = calib.std.get(key)
        for i, (n, v, u) in enumerate(zip(names, values, units)):
            rows.append((cam, n, float(v), None if std is None else float(std[i]), u))
    rvec = cv2.Rodrigues(calib.R)[0].ravel()
    std = calib.std.get("extrinsics")
    for i, (n, v) in enumerate(zip(("rx", "ry", "rz", "tx", "ty", "tz"), [*rvec, *calib.T])):
        unit = "mrad" if i < 3 else "mm"
        f = 1e3 if i < 3 else 1.0
        rows.append(("rig", n, float(v) * f, None if std is None else float(std[i]) * f, unit))
    return rows


def _bars(views, width=640, bar_h=14, gap=4):
    """Geometry of the per-view error bar chart (inline SVG): one row per view, left and right bars."""
    vmax = max([max(v.errors) for v in views] + [1e-9])
    label_w, scale = 48, (width - 48 - 60) / vmax
    rows = []
    for i, v in enumerate(views):
        y = i * (2 * bar_h + gap)
        rows.append(
            {"name": v.name, "y": y, "yl": y + bar_h - 3, "left": v.errors[0] * scale, "right": v.errors[1] * scale,
             "el": v.errors[0], "er": v.errors[1]}
        )
    return {"rows": rows, "width": width, "height": len(views) * (2 * bar_h + gap), "x0": label_w, "bar_h": bar_h}


def _created():
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    t = _dt.datetime.fromtimestamp(int(epoch), _dt.timezone.utc) if epoch else _dt.datetime.now(_dt.timezone.utc)
    return t.strftime("%Y-%m-%d %H:%M UTC")


def render_calibration_html(result, *, folder, calibration_file):
    """The calibration.html text.

    Parameters
    ----------
    result : StereoCalibrationResult
    folder : str or Path
        The image-pair folder, as named in the report.
    calibration_file : str or Path
        The calibration.yaml written, as named in the report.
    """
    from partinspect.reports.html import environment

    calib, board = result.calibration, result.board
    used = result.used
    board_text = (
        f"{board.cols}×{board.rows} ChArUco squares, {board.square:g} mm squares, {board.marker:g} mm markers ({board.dictionary})"
        if board.kind == "charuco"
        else f"chessboard, {board.cols}×{board.rows} inner corners, {board.square:g} mm squares"
    )
    coverage = {
        side: _data_uri(coverage_png(calib.image_size, [getattr(v, f"{side}_points") for v in used]))
        for side in ("left", "right")
    }
    return (
        environment()
        .get_template("calibration.html.j2")
        .render(
            r=result,
            calib=calib,
            used=used,
            rejected=result.rejected,
            folder=str(folder),
            calibration_file=str(calibration_file),
            board_text=board_text,
            created=_created(),
            coverage=coverage,
            params=parameter_rows(calib),
            bars=_bars(used),
            baseline=calib.baseline,
        )
    )


def write_calibration_report(path, result, *, folder, calibration_file):
    """Write calibration.html atomically; returns its Path."""
    return write_text_atomic(Path(path), render_calibration_html(result, folder=folder, calibration_file=calibration_file))
