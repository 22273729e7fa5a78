"""``inspect render``: a synthetic stereo pair of a STEP part, with its truth, in a folder.

Writes ``OUT_DIR/images/left.png``, ``OUT_DIR/images/right.png``,
``OUT_DIR/images/calibration.yaml`` and ``OUT_DIR/truth.json``, each
atomically; the same arguments give the same bytes. With several views
(``--views``), ``OUT_DIR/view-1/``, ``OUT_DIR/view-2/``, ... each hold a
pair, its calibration and its truth.
"""

import os
from pathlib import Path

import numpy as np

from partinspect.errors import InputError
from partinspect.simulate.render import SAMPLES
from partinspect.simulate.rig import FULL_SIZE, PIXEL_PITCH
from partinspect.cad.raycast import DEFAULT_SHADING, RENDER_ANGULAR_TOLERANCE, RENDER_TOLERANCE

__all__ = ["BLUR_SIGMA", "SAMPLES", "render_to_folder", "render_views_to_folder", "render_noiseless", "stated_calibration", "shading_with_light"]

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
    noise=None,
    seed=0,
    deviations=(),
    distortion=False,
    image_size=(2448, 2048),
    calib_error=None,
    drift=None,
    edge_break=None,
    material=None,
    defocus=None,
    photon=None,
    light=None,
    progress=None,
    images_dir="images",
    rig=None,
    pixel_pitch=None,
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
    noise : float or None
        Sensor noise, grey levels (standard deviation), >= 0; None: 2, or
        none at all with ``photon``.
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
    edge_break : str, EdgeBreak or None
        ``R`` / ``R0.1`` (fillet radius, mm) or ``C0.2`` (chamfer leg): the
        rendered solid has every convex edge broken so
        (:func:`partinspect.simulate.edge_break.break_edges`); the truth's
        features stay the sharp model's, their visibility judged on the
        sharp solid, and truth.json lists the edges left sharp.
    material : str or None
        ``matte`` (the Lambertian default), ``aluminium`` or ``steel``,
        optionally ``:SEED`` for the machining marks
        (:mod:`partinspect.simulate.material`).
    defocus : str, ThinLens or None
        ``F_NUMBER,FOCUS_MM``: depth of field of a thin lens
        (:mod:`partinspect.simulate.defocus`), pixel pitch
        ``PIXEL_PITCH * 2448 / width``, or ``pixel_pitch`` with ``rig``.
    photon : str, PhotonSensor or None
        ``FULL_WELL,GAIN,READ`` (e-, DN/e-, e-): Poisson-Gaussian noise and
        cos^4 vignetting (:mod:`partinspect.simulate.photon`) instead of
        ``noise``, which must then be None.
    light : str, sequence of 3 floats or None
        Direction towards the light in the left camera's frame (``X,Y,Z``
        text or numbers, need not be unit length); None: the default
        light near the cameras (:class:`partinspect.cad.raycast.Shading`).
    progress : callable or None
        ``progress(message)`` at each stage.
    images_dir : str
        Sub-folder of ``out_dir`` for the images and the calibration; ``""``
        writes them beside ``truth.json`` (a view of a views folder).
    rig : StereoCalibration or None
        The rig that makes the images (a user's calibration file, or
        :func:`partinspect.simulate.rig.random_rig`); its image size and
        distortion are the render's, so ``image_size`` is not used and
        ``distortion`` must be off, and ``defocus`` needs ``pixel_pitch``
        (a calibration states the focal length in pixels, the thin lens
        needs it in mm). None: the simulator's
        :func:`~partinspect.simulate.rig.default_rig`.
    pixel_pitch : float or None
        The sensor's pixel pitch behind ``rig``, mm (> 0); only with
        ``rig``.

    Returns
    -------
    dict
        The truth (schema ``truth/1``) as written to ``truth.json``.

    Raises
    ------
    partinspect.errors.InputError
        Unreadable STEP file or pose file, unknown feature id in a deviation.
    ValueError
        Bad pose text, negative noise, a bad option, or an edge break the
        part cannot take anywhere.
    """
    from partinspect.simulate.render import render_pair

    say = progress or (lambda message: None)
    realism = _realism(edge_break, material, defocus, photon)
    shading = DEFAULT_SHADING if light is None else shading_with_light(light)
    if photon is not None and noise is not None:
        raise ValueError("give either noise (grey levels) or photon (the sensor's electrons), not both")
    noise = 2.0 if noise is None and photon is None else noise
    if noise is not None and noise < 0:
        raise ValueError(f"noise must be >= 0 grey levels, got {noise}")

    def form(rs, rig, part_to_camera, finish, pitch):
        return render_pair(
            rs, rig, part_to_camera, noise=noise or 0.0, seed=seed, blur_sigma=BLUR_SIGMA, samples=SAMPLES,
            progress=say, shading=shading, finish=finish, lens=realism["defocus"], photon=realism["photon"],
            pitch=pitch,
        )

    (left, right), stated, truth = _form(
        step_path, form, pose=pose, deviations=deviations, distortion=distortion, image_size=image_size,
        calib_error=calib_error, drift=drift, realism=realism, shading=shading, noise=noise, seed=seed, say=say,
        rig=rig, pixel_pitch=pixel_pitch,
    )
    say(f"writing {out_dir}")
    _write(out_dir, left, right, stated, truth, images_dir)
    return truth


def render_views_to_folder(step_path, out_dir, views, *, pose=None, seed=0, image_size=(2448, 2048),
                           distortion=False, progress=None, rig=None, **options):
    """Render the part in several views, one image folder each, with the same rig.

    Parameters
    ----------
    step_path : str or Path
    out_dir : str or Path
        Receives ``view-1/``, ``view-2/``, ...: each holds ``left.png``,
        ``right.png``, ``calibration.yaml`` and ``truth.json``, and alone is
        an images folder ``inspect`` reads.
    views : sequence of (3,) or str
        Each view's turn of the part in its own frame (degrees, see
        :func:`partinspect.poses.turned_pose`), or ``--views`` text
        (:func:`partinspect.poses.parse_views`).
    pose : None, str, Path or ndarray (4, 4)
        The pose the turns are applied to, as :func:`render_to_folder`
        takes it (None: the default pose).
    seed : int
        View ``k`` (from 1) is rendered with noise seed ``seed + 1000 (k - 1)``:
        each pair has its own noise, as separate exposures do.
    image_size, distortion, progress, rig
        As :func:`render_to_folder`.
    **options
        Any other :func:`render_to_folder` option (``noise``,
        ``deviations``, ``calib_error``, ...), the same for every view.

    Returns
    -------
    list of dict
        Each view's truth, as written.
    """
    from partinspect.cad.step import load_step
    from partinspect.poses import bounds_of, parse_views, turned_pose
    from partinspect.simulate.rig import default_rig

    say = progress or (lambda message: None)
    turns = parse_views(views) if isinstance(views, str) else [np.asarray(v, float) for v in views]
    bounds = bounds_of(load_step(Path(step_path)))
    base = _resolve_pose(pose, bounds, rig if rig is not None else default_rig(image_size, distortion=distortion))
    truths = []
    for k, turn in enumerate(turns, 1):
        say(f"view {k} of {len(turns)}: the part turned {','.join(f'{a:g}' for a in turn)} degrees")
        truth = render_to_folder(step_path, Path(out_dir) / f"view-{k}", pose=turned_pose(base, turn, bounds),
                                 seed=seed + 1000 * (k - 1), image_size=image_size, distortion=distortion,
                                 progress=progress, images_dir="", rig=rig, **options)
        truths.append(truth)
    return truths


def render_noiseless(
    step_path,
    *,
    pose=None,
    deviations=(),
    distortion=False,
    image_size=(2448, 2048),
    edge_break=None,
    material=None,
    defocus=None,
    light=None,
    progress=None,
    rig=None,
    pixel_pitch=None,
):
    """The noiseless radiance pair :func:`render_to_folder` would sense, with its truth and rig.

    For Monte Carlo checks: the rays are cast once, and each draw adds the
    sensor's noise (:func:`partinspect.simulate.render.sensor`, or
    :func:`partinspect.simulate.photon.photon_sensor` with
    :func:`partinspect.simulate.render.camera_vignetting`) and, if wanted,
    a stated calibration (:func:`stated_calibration`). Parameters are
    :func:`render_to_folder`'s.

    Returns
    -------
    radiance : tuple of two ndarray of float, shape (H, W)
        Left, right, grey levels before noise and quantisation.
    rig : StereoCalibration
        The true rig the pair is formed by.
    truth : dict
        The truth (schema ``truth/1``), with ``settings.noise`` None.
    """
    from partinspect.simulate.render import scene_radiance_pair

    say = progress or (lambda message: None)
    realism = _realism(edge_break, material, defocus, None)
    shading = DEFAULT_SHADING if light is None else shading_with_light(light)

    def form(rs, rig, part_to_camera, finish, pitch):
        return scene_radiance_pair(
            rs, rig, part_to_camera, blur_sigma=BLUR_SIGMA, samples=SAMPLES, progress=say, shading=shading,
            finish=finish, lens=realism["defocus"], pitch=pitch,
        )

    radiance, rig, truth = _form(
        step_path, form, pose=pose, deviations=deviations, distortion=distortion, image_size=image_size,
        calib_error=None, drift=None, realism=realism, shading=shading, noise=None, seed=0, say=say, rig=rig,
        pixel_pitch=pixel_pitch,
    )
    return radiance, rig, truth


def stated_calibration(rig, seed):
    """What a board session calibrates ``rig`` to, with its stated uncertainties (``--calib-error SEED``)."""
    return _stated_calibration(rig, seed)[0]


def _form(step_path, form, *, pose, deviations, distortion, image_size, calib_error, drift, realism, shading, noise,
          seed, say, rig=None, pixel_pitch=None):
    """The part's scene formed into images by ``form``; (images, the stated calibration, truth)."""
    from partinspect.cad.raycast import build_scene
    from partinspect.simulate.truth import make_truth

    step_path = Path(step_path)
    inv, devs, shape, bounds = _load_part(step_path, deviations, say)
    calibrated, pitch = _making_rig(rig, image_size, distortion, realism, pixel_pitch)
    rig = calibrated
    if drift is not None:
        from partinspect.simulate.calibration import drifted_rig

        rig = drifted_rig(calibrated, *drift)
    part_to_camera = _resolve_pose(pose, bounds, calibrated)

    say("tessellating")
    from partinspect.cad.mesh import tessellate

    mesh = tessellate(shape, RENDER_TOLERANCE, RENDER_ANGULAR_TOLERANCE, inventory=None if devs else inv)
    truth_scene = build_scene(mesh)
    rs, finish, extra = _real_part(step_path, shape, inv if not devs else None, truth_scene, realism, say)
    extra.update(_real_camera(realism, rig, pitch))
    images, stats = form(rs, rig, part_to_camera, finish, pitch)
    if "defocus" in extra:
        extra["defocus"]["coc_px"] = {name: stats[name].pop("coc_px") for name in ("left", "right")}

    say("computing the ground truth")
    distorted = bool(np.any(calibrated.D1) or np.any(calibrated.D2))
    settings = _settings(step_path, rig, noise, seed, distorted, stats, len(rs.triangles), shading)
    if finish is not None:
        settings["shading"]["model"] = "lambertian + cook-torrance (see material)"
    if "edge_break" in extra:
        settings["tessellation"]["min_size"] = extra["edge_break"].pop("mesh_min_size")
    settings.update(extra)
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
    truth = make_truth(inv, devs, truth_scene, rig, part_to_camera, settings, shading)
    return images, stated, truth


def _making_rig(rig, image_size, distortion, realism, pixel_pitch=None):
    """The rig that makes the images and its pixel pitch, mm: ``rig`` as given, else the default rig at ``image_size``."""
    from partinspect.simulate.rig import default_rig

    if rig is None:
        if pixel_pitch is not None:
            raise ValueError("a pixel pitch is given with a rig: the simulator's rig has its own")
        rig = default_rig(image_size, distortion=distortion)
        return rig, PIXEL_PITCH * FULL_SIZE[0] / float(rig.image_size[0])
    if distortion:
        raise ValueError("a given rig renders through its own distortion: not with the default lens's distortion")
    if pixel_pitch is not None and not (np.isfinite(pixel_pitch) and pixel_pitch > 0):
        raise ValueError(f"the pixel pitch must be a positive length, got {pixel_pitch}")
    if realism["defocus"] is not None and pixel_pitch is None:
        raise ValueError("defocus needs the sensor's pixel pitch, which a calibration does not state: give it with the rig")
    if rig.image_size is None:
        raise ValueError("the rig states no image size")
    return rig, pixel_pitch


def _realism(edge_break, material, defocus, photon):
    """The realism options parsed (texts accepted); None for each that is off, matte included."""
    from partinspect.simulate.defocus import ThinLens, parse_defocus
    from partinspect.simulate.edge_break import EdgeBreak, parse_edge_break
    from partinspect.simulate.material import parse_material
    from partinspect.simulate.photon import PhotonSensor, parse_photon

    out = {"edge_break": edge_break, "material": None, "defocus": defocus, "photon": photon}
    if edge_break is not None and not isinstance(edge_break, EdgeBreak):
        out["edge_break"] = parse_edge_break(edge_break)
    if material is not None:
        chosen, marks_seed = parse_material(material)
        out["material"] = None if chosen is None else (chosen, marks_seed)
    if defocus is not None and not isinstance(defocus, ThinLens):
        out["defocus"] = parse_defocus(defocus)
    if photon is not None and not isinstance(photon, PhotonSensor):
        out["photon"] = parse_photon(photon)
    return out


def _real_part(step_path, shape, inv, scene, realism, say):
    """The scene to render, its metal finish and their truth.json records.

    ``scene`` is the sharp solid's; with an edge break, the broken solid's
    scene is made and returned instead (``inv``: the shape's inventory, or
    None to make it).
    """
    from partinspect.cad.raycast import build_scene

    extra, finish = {}, None
    spec = realism["edge_break"]
    if spec is not None:
        from partinspect.cad.features import inventory
        from partinspect.cad.mesh import tessellate
        from partinspect.simulate.edge_break import break_edges, mesh_min_size

        try:
            broken, extra["edge_break"] = break_edges(shape, spec, inv if inv is not None else inventory(shape), say)
        except ValueError as exc:
            raise InputError(step_path, f"edge break {spec.kind} {spec.size:g} mm: {exc}") from None
        say("tessellating the broken solid")
        extra["edge_break"]["mesh_min_size"] = mesh_min_size(spec)
        scene = build_scene(tessellate(broken, RENDER_TOLERANCE, RENDER_ANGULAR_TOLERANCE,
                                       min_size=mesh_min_size(spec)))
        # The visibility rules look for two faces meeting at the edge; a
        # fillet puts a third between them, so each feature's visibility is
        # judged on the sharp solid: whether its faces are in sight and contrast.
        extra["edge_break"]["visibility"] = "features' visibility is judged on the sharp solid"
    if realism["material"] is not None:
        from partinspect.simulate.material import finish as lay_finish

        finish = lay_finish(scene, *realism["material"])
        extra["material"] = finish.to_dict()
        extra["material"]["visibility"] = "features' contrast is judged with the Lambertian shading"
    return scene, finish, extra


def _real_camera(realism, rig, pitch):
    """truth.json's records of the lens's depth of field and the photon sensor."""
    extra = {}
    lens = realism["defocus"]
    if lens is not None:
        extra["defocus"] = {
            "f_number": lens.f_number, "focus": lens.focus, "pixel_pitch": pitch,
            "focal_length": [float(rig.K1[0, 0]) * pitch, float(rig.K2[0, 0]) * pitch],
            "model": "thin lens: blur circle c = (f/N) f |z - z_f| / (z (z_f - f)) / pitch px, z the surface depth "
                     "seen by each pixel centre; a uniform disc, levels 0.5 px apart blended linearly, after the "
                     "optics PSF",
        }
    if realism["photon"] is not None:
        extra["photon"] = realism["photon"].to_dict()
    return extra


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


def shading_with_light(light):
    """The default shading with the light moved to ``light`` (text ``X,Y,Z`` or 3 numbers, rig frame)."""
    from dataclasses import replace

    try:
        v = [float(x) for x in (light.split(",") if isinstance(light, str) else light)]
        if len(v) != 3 or not np.isfinite(v).all() or np.linalg.norm(v) == 0:
            raise ValueError
    except (TypeError, ValueError):
        raise ValueError(f"light: expected X,Y,Z, a direction towards the light in the left camera frame, got {light!r}") from None
    return replace(DEFAULT_SHADING, light=tuple(v))


def _settings(step_path, rig, noise, seed, distortion, stats, triangles, shading=DEFAULT_SHADING):
    """truth.json's "settings": everything the render was made with."""
    return {
        "part": step_path.name,
        "image_size": [int(v) for v in rig.image_size],
        "noise": None if noise is None else float(noise),
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
            "light_direction_rig": list(shading.direction()),
            "ambient": shading.ambient,
            "albedo": shading.albedo,
            "background": shading.background,
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


def _write(out_dir, left, right, rig, truth, images_dir="images"):
    """The images, the calibration and truth.json, each written atomically."""
    from partinspect.atomic import prepare_output_dir, write_bytes_atomic, write_text_atomic
    from partinspect.simulate.truth import to_json
    from partinspect.vision.calibration import write_calibration

    out = prepare_output_dir(out_dir)
    images = prepare_output_dir(out / images_dir) if images_dir else out
    write_bytes_atomic(images / "left.png", _png(left))
    write_bytes_atomic(images / "right.png", _png(right))
    write_calibration(images / "calibration.yaml", rig)
    os.chmod(images / "calibration.yaml", 0o644)  # a temporary file's 0600 would survive the rename
    write_text_atomic(out / "truth.json", to_json(truth))
