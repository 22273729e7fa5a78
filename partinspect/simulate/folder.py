"""``inspect render``: a synthetic stereo pair of a STEP part, with its truth, in a folder.

Writes ``OUT_DIR/images/left.png``, ``OUT_DIR/images/right.png``,
``OUT_DIR/images/calibration.yaml`` and ``OUT_DIR/truth.json``, each
atomically; the same arguments give the same bytes.
"""

import os
from pathlib import Path

import numpy as np

from partinspect.simulate.render import SAMPLES
from partinspect.cad.raycast import DEFAULT_SHADING, RENDER_ANGULAR_TOLERANCE, RENDER_TOLERANCE

__all__ = ["BLUR_SIGMA", "SAMPLES", "render_to_folder"]

BLUR_SIGMA = 0.6
"""Optics point-spread function, pixels."""


def _parse_deviations(deviations):
    from partinspect.cad.deviate import parse_deviation

    out = []
    for d in deviations or ():
        out.append(tuple(parse_deviation(d)) if isinstance(d, str) else tuple(d))
    return out


def _resolve_pose(pose, bounds, rig):
    from partinspect.poses import default_pose, parse_pose

    if pose is None:
        return default_pose(bounds, rig)
    if isinstance(pose, (str, Path)):
        return parse_pose(pose, bounds, rig)
    P = np.asarray(pose, dtype=float)
    if P.shape != (4, 4):
        raise ValueError(f"pose must be a 4x4 part_to_camera matrix, got shape {P.shape}")
    return P


def _png(image):
    import cv2

    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def render_to_folder(
    step_path,
    out_dir,
    *,
    pose=None,
    noise=2.0,
    seed=0,
    deviations=(),
    distortion=False,
    image_size=(2448, 2048),
    calib_error=None,
    drift=None,
    progress=None,
):
    """Render a stereo pair of a STEP part and write it with its ground truth.

    Parameters
    ----------
    step_path : str or Path
        The nominal part.
    out_dir : str or Path
        Created if needed. Receives ``images/left.png``,
        ``images/right.png``, ``images/calibration.yaml`` and
        ``truth.json``.
    pose : None, str, Path or ndarray (4, 4)
        None: :func:`~partinspect.poses.default_pose`. A string:
        ``--pose`` text (see :func:`~partinspect.poses.parse_pose`).
        An array: part_to_camera. The bounding box used is the nominal
        part's, so a deviation never moves the part.
    noise : float
        Sensor noise, grey levels (standard deviation), >= 0.
    seed : int
        Noise seed.
    deviations : sequence
        Each ``"ID.PARAM=DELTA"`` text or a ``(feature_id, param, delta)``
        tuple, as :func:`partinspect.cad.deviate.parse_deviation` gives; the
        rendered part is the nominal one so changed.
    distortion : bool
        Render through the rig's realistic lens distortion.
    image_size : (int, int)
        ``(width, height)``; the field of view is the same at every size.
    calib_error : int or None
        None: ``calibration.yaml`` is the true rig. A seed: the images are
        made by the true rig, but ``calibration.yaml`` is what a board
        session calibrates it to (:func:`partinspect.simulate.calibration.simulated_calibration`),
        with its stated uncertainties; truth.json keeps the true rig.
    drift : (str, float) or None
        ``(kind, px)``: the images are made by the rig after its right
        camera drifted (:func:`partinspect.simulate.calibration.drifted_rig`),
        while ``calibration.yaml`` states the rig before (exact, or as
        ``calib_error`` calibrates it); truth.json records both.
    progress : callable or None
        ``progress(message)`` at each stage.

    Returns
    -------
    dict
        The truth (schema ``truth/1``) as written to ``truth.json``.

    Raises
    ------
    partinspect.errors.InputError
        Unreadable STEP file or pose file, unknown feature id in a deviation.
    ValueError
        Bad pose text, negative noise.
    """
    from partinspect.cad.raycast import build_scene
    from partinspect.simulate.render import render_pair
    from partinspect.simulate.rig import default_rig
    from partinspect.simulate.truth import make_truth

    say = progress or (lambda message: None)
    if noise < 0:
        raise ValueError(f"noise must be >= 0 grey levels, got {noise}")
    step_path = Path(step_path)
    inv, devs, shape, bounds = _load_part(step_path, deviations, say)
    calibrated = default_rig(image_size, distortion=distortion)
    rig = calibrated
    if drift is not None:
        from partinspect.simulate.calibration import drifted_rig

        rig = drifted_rig(calibrated, *drift)
    part_to_camera = _resolve_pose(pose, bounds, calibrated)

    say("tessellating")
    from partinspect.cad.mesh import tessellate

    mesh = tessellate(shape, RENDER_TOLERANCE, RENDER_ANGULAR_TOLERANCE, inventory=None if devs else inv)
    rs = build_scene(mesh)
    (left, right), stats = render_pair(
        rs, rig, part_to_camera, noise=noise, seed=seed, blur_sigma=BLUR_SIGMA, samples=SAMPLES, progress=say
    )

    say("computing the ground truth")
    settings = _settings(step_path, rig, noise, seed, distortion, stats, len(mesh.faces))
    stated = calibrated
    if calib_error is not None:
        say("calibrating the rig as a board session would")
        stated, settings["calibration_error"] = _stated_calibration(calibrated, calib_error)
    if drift is not None:
        settings["drift"] = {
            "kind": drift[0], "px": float(drift[1]),
            "method": "the images are made by the rig after its right camera drifted; calibration.yaml states it before",
            "rig_after_drift": {name: np.asarray(getattr(rig, name), float).tolist() for name in ("K1", "K2", "R", "T")},
        }
    truth = make_truth(inv, devs, rs, rig, part_to_camera, settings)

    say(f"writing {out_dir}")
    _write(out_dir, left, right, stated, truth)
    return truth


def _load_part(step_path, deviations, say):
    """The nominal part's inventory, the deviations, the solid to render and the nominal bounds."""
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.poses import bounds_of

    say(f"loading {step_path}")
    nominal = load_step(step_path)
    inv = inventory(nominal)
    devs = _parse_deviations(deviations)
    shape = nominal
    if devs:
        from partinspect.cad.deviate import deviate

        say(f"applying {len(devs)} deviation(s)")
        shape = deviate(nominal, inv, devs)
    # The nominal part's box: a deviation never moves the part.
    return inv, devs, shape, bounds_of(nominal)


def _settings(step_path, rig, noise, seed, distortion, stats, triangles):
    """truth.json's "settings": everything the render was made with."""
    return {
        "part": step_path.name,
        "image_size": [int(v) for v in rig.image_size],
        "noise": float(noise),
        "seed": int(seed),
        "blur_sigma": BLUR_SIGMA,
        "distortion": bool(distortion),
        "sampling": {
            "method": "adaptive",
            "coarse": "one ray at every pixel corner and pixel centre",
            "supersampled": "pixels whose coarse rays do not all hit the same CAD face or differ by more "
            "than 1 grey level, and their 8 neighbours",
            "rays_per_supersampled_pixel": SAMPLES * SAMPLES,
            "pattern": f"rotated {SAMPLES}x{SAMPLES} lattice: offsets ((n i + j + 0.5) / n^2 - 0.5, "
            f"(n j + i + 0.5) / n^2 - 0.5) px, n = {SAMPLES}, all x and all y distinct",
            "supersampled_pixels": {k: int(v["supersampled"]) for k, v in stats.items()},
        },
        "shading": {
            "model": "lambertian",
            "light_direction_rig": list(DEFAULT_SHADING.direction()),
            "ambient": DEFAULT_SHADING.ambient,
            "albedo": DEFAULT_SHADING.albedo,
            "background": DEFAULT_SHADING.background,
        },
        "tessellation": {
            "tolerance": RENDER_TOLERANCE,
            "angular_tolerance": RENDER_ANGULAR_TOLERANCE,
            "triangles": int(triangles),
        },
    }


def _stated_calibration(rig, seed):
    """The calibration a board session states for ``rig``, and what truth.json says of it."""
    from partinspect.simulate.calibration import CORNER_NOISE, N_VIEWS, calibration_board, simulated_calibration

    board = calibration_board(rig)
    stated = simulated_calibration(rig, np.random.default_rng([seed, 7919]), board=board)
    note = {
        "seed": int(seed),
        "method": "a chessboard in several poses, corners projected by the true rig with noise, calibrated as "
                  "inspect calibrate does; calibration.yaml is that result, the true rig is below",
        "views": N_VIEWS,
        "corner_noise_px": CORNER_NOISE,
        "board": f"{board.cols}x{board.rows} inner corners, {float(board.square)} mm squares",
        "true_rig": {name: np.asarray(getattr(rig, name), float).tolist() for name in ("K1", "D1", "K2", "D2", "R", "T")},
    }
    return stated, note


def _write(out_dir, left, right, rig, truth):
    """The images, the calibration and truth.json, each written atomically."""
    from partinspect.atomic import prepare_output_dir, write_bytes_atomic, write_text_atomic
    from partinspect.simulate.truth import to_json
    from partinspect.vision.calibration import write_calibration

    out = prepare_output_dir(out_dir)
    images = prepare_output_dir(out / "images")
    write_bytes_atomic(images / "left.png", _png(left))
    write_bytes_atomic(images / "right.png", _png(right))
    write_calibration(images / "calibration.yaml", rig)
    os.chmod(images / "calibration.yaml", 0o644)  # a temporary file's 0600 would survive the rename
    write_text_atomic(out / "truth.json", to_json(truth))
