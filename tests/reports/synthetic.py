"""A synthetic run for the report tests: a plate with holes, its report dict and figures dict.

Built directly (random images with drawn edges, points with anisotropic
covariances), not through the pipeline, so the report tests stay fast.
"""

import copy
import math

import numpy as np

HOLES = [  # id, centre (part frame, mm), radius
    ("circle-1", (12.0, 12.0), 2.0),
    ("circle-2", (68.0, 12.0), 3.0),
    ("circle-3", (40.0, 30.0), 6.0),
    ("circle-4", (20.0, 42.0), 4.0),
    ("circle-5", (62.0, 46.0), 5.0),
]
CORNERS = [(0.0, 0.0), (80.0, 0.0), (80.0, 60.0), (0.0, 60.0)]
THICK = 10.0


def rot_x(deg):
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def rot_z(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


# Camera above the plate, looking down and a little tilted: part -> left camera.
R_PC = rot_x(200.0) @ rot_z(8.0)
T_PC = np.array([-40.0, 25.0, 420.0])
PART_TO_CAMERA = np.eye(4)
PART_TO_CAMERA[:3, :3] = R_PC
PART_TO_CAMERA[:3, 3] = T_PC


def char(cid, decision, measured=12.013, nominal=12.0, lower=11.95, upper=12.05, U=0.006, **kw):
    c = {
        "id": cid, "feature": cid.split(".")[0], "features": [cid.split(".")[0]], "type": cid.split(".")[1],
        "nominal": nominal, "measured": measured,
        "deviation": None if measured is None else round(measured - nominal, 9),
        "standard_uncertainty": None if measured is None else U / 2,
        "expanded_uncertainty": None if measured is None else U,
        "lower_limit": lower, "upper_limit": upper, "unit": "mm", "source": "spec", "rule": "part.tol.yaml line 9",
        "coverage_factor": 2.0, "method": "first order (pose-invariant)", "decision": decision,
        "reason": None if decision == "pass" else ("not measured" if measured is None else "measured value +- U straddles a specification limit"),
    }
    c.update(kw)
    return c


CHARS = [
    char("circle-1.diameter", "pass", 4.004, 4.0, 3.95, 4.05, 0.008),
    char("circle-3.diameter", "fail", 12.21, 12.0, 12.0, 12.05, 0.01, reason="measured value - U above the upper limit"),
    char("circle-3.position", "inconclusive", 0.095, 0.0, 0.0, 0.1, 0.012, type="position", method="Monte Carlo (JCGM 101), 4000 draws"),
    char("line-2.straightness", "pass", 0.004, 0.0, 0.0, 0.02, 0.003, feature="line-2", features=["line-2"], type="straightness", source="ISO2768-mK", rule="ISO 2768-2 K"),
    char("line-1.angle", "pass", 90.02, 90.0, 89.5, 90.5, 0.04, feature="line-1", features=["line-1", "line-2"], type="angle", unit="deg", source="ISO2768-mK", rule="ISO 2768-1 m"),
    char("circle-5.diameter", "inconclusive", None, 10.0, 9.8, 10.2),
    char("circle-4.diameter", "pass", 8.01, 8.0, 7.9, 8.1, 0.01),
]


def make_report(chars=CHARS, part="part.step", verdict="fail", registration=True):
    feats = []
    for fid, (cx, cy), r in HOLES:
        measured = None if fid == "circle-5" else {
            "center": [cx + 0.002, cy - 0.001, THICK + 0.004], "normal": [0, 0, 1], "radius": r + 0.003,
            "covariance": [[1e-6, 0, 0], [0, 1.2e-6, 0], [0, 0, 9e-6]], "radius_std": 0.002}
        f = {"id": fid, "kind": "circle", "nominal": {"center": [cx, cy, THICK], "normal": [0, 0, 1], "radius": r},
             "measured": measured}
        if measured is None:
            f.update(status="not measured", reason="occluded in the right image")
        feats.append(f)
    for i, (a, b) in enumerate(zip(CORNERS, CORNERS[1:] + CORNERS[:1]), start=1):
        feats.append({"id": f"line-{i}", "kind": "line",
                      "nominal": {"start": [*a, THICK], "end": [*b, THICK]},
                      "measured": {"point": [*a, THICK], "direction": [1, 0, 0], "start": [*a, THICK],
                                   "end": [*b, THICK], "covariance": [[4e-6, 0, 0], [0, 4e-6, 0], [0, 0, 2.5e-5]]}})
    report = {
        "schema": "report/1", "part": part, "units": "mm", "verdict": verdict,
        "created": "2026-11-22T10:00:00+00:00",
        "inputs": [
            {"role": "part", "path": f"examples/plate/{part}", "sha256": "3f" * 32},
            {"role": "left image", "path": "examples/plate/images/left.png", "sha256": "a1" * 32},
            {"role": "right image", "path": "examples/plate/images/right.png", "sha256": "b2" * 32},
            {"role": "calibration", "path": "examples/plate/images/calibration.yaml", "sha256": "c3" * 32},
        ],
        "images": {"width": 2448, "height": 2048, "bit_depth": 8},
        "tolerances": {"file": "examples/plate/part.tol.yaml", "general": "ISO2768-mK", "decision_rule": "iso14253"},
        "registration": {"part_to_camera": np.round(PART_TO_CAMERA, 9).tolist(), "rms": 0.0042,
                         "weighted_rms": 1.07, "chi2": 12.6, "dof": 11, "datums": ["line-1", "line-2", "circle-3"],
                         "rotation_std_deg": [0.002, 0.0021, 0.0008], "translation_std": [0.004, 0.0041, 0.011],
                         "frame": "pose error xi = (rotation vector [rad], translation [mm]) in the part frame"}
        if registration else None,
        "features": feats,
        "characteristics": copy.deepcopy(list(chars)),  # a test may change them
        "not_inspected": [char("line-9.straightness", "inconclusive", None, 0.0, 0.0, 0.1, type="straightness",
                               feature="line-9", source="ISO2768-mK (general tolerance)",
                               reason="line-9 faces away from both cameras")],
        "summary": {"features": len(feats), "features_measured": sum(f["measured"] is not None for f in feats),
                    "characteristics": len(chars),
                    **{d: sum(c["decision"] == d for c in chars) for d in ("pass", "fail", "inconclusive")}},
    }
    return report


def _project(P, K):
    """Pinhole projection of part-frame points (no distortion: synthetic)."""
    Xc = P @ R_PC.T + T_PC
    uv = Xc[:, :2] / Xc[:, 2:3]
    return uv * K[0] + K[1]


def make_figures(seed=0, width=2448, height=2048, n_pts=180, noise=True):
    """A figures dict (partinspect.reports.figures interface) for the report above."""
    import cv2

    rng = np.random.default_rng(seed)
    f = 2.4 * width
    K = (np.array([f, f]), np.array([width / 2, height / 2]))
    status = {"circle-1": "pass", "circle-2": "measured", "circle-3": "fail", "circle-4": "pass", "circle-5": "inconclusive",
              "line-1": "pass", "line-2": "pass", "line-3": "measured", "line-4": "measured"}
    images, overlays, residuals, points3d, cad_edges = {}, [], [], [], []
    for side, shift in (("left", 0.0), ("right", 60.0)):
        img = np.full((height, width), 28.0)
        plate = _project(np.array([[*c, THICK] for c in CORNERS]), K) + [shift, 0]
        cv2.fillPoly(img, [np.round(plate * 16).astype(np.int32)], 150.0, cv2.LINE_AA, shift=4)
        for fid, (cx, cy), r in HOLES:
            t = np.linspace(0, 2 * np.pi, 400)
            ring = np.c_[cx + r * np.cos(t), cy + r * np.sin(t), np.full_like(t, THICK)]
            uv = _project(ring, K) + [shift, 0]
            cv2.fillPoly(img, [np.round(uv * 16).astype(np.int32)], 40.0, cv2.LINE_AA, shift=4)
            if not (fid == "circle-5" and side == "right"):
                overlays.append({"image": side, "xy": uv, "kind": "circle", "label": fid, "status": status[fid]})
        for i, (a, b) in enumerate(zip(CORNERS, CORNERS[1:] + CORNERS[:1]), start=1):
            seg = np.linspace([*a, THICK], [*b, THICK], 50)
            overlays.append({"image": side, "xy": _project(seg, K) + [shift, 0], "kind": "line",
                             "label": f"line-{i}", "status": status[f"line-{i}"]})
        # An edge of the image that matched nothing (a shadow, say).
        overlays.append({"image": side, "xy": np.array([[200.0, 1800.0], [700.0, 1900.0]]), "kind": "line",
                         "label": "", "status": "unmatched"})
        img = cv2.GaussianBlur(img, (0, 0), 1.2)
        if noise:
            img += rng.normal(0, 2.0, img.shape)
        images[side] = np.clip(np.round(img), 0, 255).astype(np.uint8)
    for fid, _, _ in HOLES[:4]:
        for side in ("left", "right"):
            sigma = 0.045 if side == "left" else 0.05
            scale = 1.6 if fid == "circle-3" else 1.0  # one fit whose noise is not as predicted
            residuals.append({"label": fid, "image": side, "residuals": rng.normal(0, sigma * scale, 300),
                              "sigma": sigma})
    lateral, depth = 0.003, 0.012
    C_cam = np.diag([lateral**2, (1.1 * lateral) ** 2, depth**2])
    C_part = R_PC.T @ C_cam @ R_PC
    for fid, (cx, cy), r in HOLES:
        if fid == "circle-5":
            continue
        t = np.linspace(0, 2 * np.pi, n_pts, endpoint=False)
        P = np.c_[cx + r * np.cos(t), cy + r * np.sin(t), np.full_like(t, THICK)]
        scale = 1 + 0.4 * np.sin(t) ** 2
        covs = C_part[None] * scale[:, None, None] ** 2
        P = P + np.einsum("nij,nj->ni", np.linalg.cholesky(covs), rng.normal(size=(n_pts, 3)))
        points3d.append({"label": fid, "points": P, "covs": covs, "status": status[fid]})
        t = np.linspace(0, 2 * np.pi, 97)
        cad_edges.append({"label": fid, "polyline": np.c_[cx + r * np.cos(t), cy + r * np.sin(t), np.full_like(t, THICK)]})
    for i, (a, b) in enumerate(zip(CORNERS, CORNERS[1:] + CORNERS[:1]), start=1):
        for z in (0.0, THICK):
            cad_edges.append({"label": f"line-{i}", "polyline": np.array([[*a, z], [*b, z]])})
        cad_edges.append({"label": "", "polyline": np.array([[*a, 0.0], [*a, THICK]])})
        if i <= 2:
            seg = np.linspace([*a, THICK], [*b, THICK], n_pts)
            points3d.append({"label": f"line-{i}", "points": seg + rng.normal(0, 0.004, seg.shape),
                             "covs": np.repeat(C_part[None] * 1.5, n_pts, axis=0), "status": status[f"line-{i}"]})
    return {**images, "overlays": overlays, "residuals": residuals, "points3d": points3d, "cad_edges": cad_edges}
