"""Check predicted uncertainties against the real chain on rendered images (JCGM 101).

The part is ray-cast once per camera (noiseless, blurred radiance); each
draw adds fresh sensor noise (:attr:`Renderer.sensor`) and runs the whole
chain as ``inspect`` does (measurement, registration with the true pose as
hint so that a rare ambiguous draw does not stop the check, evaluation).
Each characteristic's spread over the draws is set beside its predicted
``u`` and the ``u`` the chain reported. The spread is the values' standard
deviation, except for position, a norm: there ``2 sqrt(tr Cov(d))`` of the
centre's in-plane offset d, what ``true_position`` states at the true
position (the render's small systematic offset is no part of the spread).
A position at MMC or LMC is decided on ``position - bonus(d)``: its spread
takes in the measured size's spread over the draws by the law
:func:`partinspect.tolerances.material.position_with_bonus` applies in
each evaluation, at the true position (where the position and the centre's
error are uncorrelated).

:func:`check_pose` is ``inspect plan --check``. The draws show only the
image-noise part of u (one scene, its Type B displacements fixed), so they
are set beside the prediction without its Type B part. A spread above what
chance allows (:func:`chance_interval`, with the draws' kurtosis; for form
values the spreads their error model gives over scenes,
:func:`form_interval`) is a random component the first-order model lacks,
added to u in quadrature; a spread below it leaves u as it is
(conservative). A characteristic not measured in every draw is not called
decidable.

References
----------
.. [1] JCGM 101:2008, GUM Supplement 1: propagation of distributions using
       a Monte Carlo method, 7.6 (the standard deviation of the output
       values as the standard uncertainty).
.. [2] JCGM 100:2008 (GUM), 4.2 (Type A evaluation) and 5.1.2 (combining
       uncorrelated components in quadrature).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RenderedCheck", "CheckedCharacteristic", "PoseCheck", "Renderer", "measure_pair",
           "monte_carlo_check", "spread", "chance_interval", "form_interval", "spread_interval",
           "checked_uncertainty", "check_pose"]


@dataclass(frozen=True)
class Renderer:
    """How a check makes its images (the caller's image formation model).

    Attributes
    ----------
    radiance : callable
        ``radiance(scene, calib, part_to_camera, blur_sigma=...)`` -> the
        noiseless, blurred left and right images (float32 grey levels).
    sensor : callable
        ``sensor(image, noise, rng)`` -> one recorded image: noise of
        standard deviation ``noise`` grey levels added and quantised.
    """

    radiance: object
    sensor: object


@dataclass(frozen=True, eq=False)
class RenderedCheck:
    """Measured values of every characteristic over noise draws.

    Attributes
    ----------
    ids : tuple of str
        Characteristic ids, in the order given.
    values : dict of str to ndarray, shape (n,)
        Measured value per successful draw (NaN where not measured).
    reported_u : dict of str to ndarray, shape (n,)
        The standard uncertainty the chain reported in each draw.
    offsets : dict of str to ndarray, shape (n, 3)
        Position characteristics: the centre's offset from its true
        position in the nominal plane, part frame, mm.
    draws : int
        Draws whose chain run completed.
    failed : list of str
        Why the other draws failed.
    bonus : dict of str to (MaterialCondition, ndarray shape (n,))
        Positions at MMC or LMC: the modifier and the measured diameter its
        bonus came from in each draw, mm (NaN where not measured).
    """

    ids: tuple
    types: dict
    values: dict
    reported_u: dict
    offsets: dict
    draws: int
    failed: list
    bonus: dict = None

    def spread(self, cid):
        """Measured standard uncertainty of one characteristic (module notes), NaN with < 3 values."""
        if self.types[cid] == "position":
            d = self.offsets[cid]
            ok = np.isfinite(d).all(axis=1)
            material = (self.bonus or {}).get(cid)
            if material is not None:
                ok &= np.isfinite(material[1])
            if ok.sum() < 3:
                return float("nan")
            u_position = 2.0 * float(np.sqrt(np.trace(np.cov(d[ok], rowvar=False))))
            return u_position if material is None else _with_bonus(u_position, material[1][ok], material[0])
        return spread(self.values[cid])

    def rms_error(self, cid, true_value):
        """Root mean square error of the measured values about ``true_value``, NaN with < 3 values.

        Position: the RMS of ``2 |d|`` (the true offset being zero), which,
        unlike :meth:`spread`, includes the render's systematic offset.
        """
        if self.types[cid] == "position":
            d = self.offsets[cid]
            d = d[np.isfinite(d).all(axis=1)]
            return 2.0 * float(np.sqrt(np.mean((d * d).sum(axis=1)))) if len(d) >= 3 else float("nan")
        v = self.values[cid]
        v = v[np.isfinite(v)]
        return float(np.sqrt(np.mean((v - true_value) ** 2))) if len(v) >= 3 else float("nan")

    def measured_fraction(self, cid):
        return float(np.mean(np.isfinite(self.values[cid]))) if self.draws else 0.0


def _with_bonus(u_position, sizes, material):
    """The spread of ``position - bonus(d)`` over the draws, from the position's and the size's.

    As each evaluation does (:func:`partinspect.tolerances.material.position_with_bonus`):
    ``u(q)^2 = u(position)^2 + u(d)^2 - 2 s grad . Cov(centre, d)``, with
    the gradient at the true position, as the position's spread is taken:
    zero there (the render's systematic offset is no part of it), so the
    size's variance adds to the position's.
    """
    from partinspect.tolerances.material import position_with_bonus

    _, u_q, _, _, _ = position_with_bonus(0.0, u_position, np.zeros(3), 0.0, float(np.std(sizes, ddof=1)), np.zeros(3),
                                          material.modifier, material.internal, 0.0)
    return u_q


def spread(values):
    """Sample standard deviation of the finite values (ddof 1), NaN with fewer than 3."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.std(v, ddof=1)) if len(v) >= 3 else float("nan")


def _position_offset(c, parts, inventory):
    fid = c.features[0]
    cands = [p for p in parts if p.cad_id == fid and p.kind == "circle"]
    if not cands:
        return np.full(3, np.nan)
    nominal = inventory[fid]
    N = np.asarray(nominal.normal, float)
    Pn = np.eye(3) - np.outer(N, N)
    return Pn @ (cands[0].center - np.asarray(nominal.center, float))


def measure_pair(left, right, calib, inventory, characteristics, *, datums=None, pose_hint=None, seed=0, scene=None):
    """Run the measurement chain on one image pair and evaluate the characteristics.

    ``scene``: the part as rendered (RaycastScene), for its curved faces'
    outlines (:func:`partinspect.cad.outlines.outline_images`), as inspect
    takes them from its mesh; None to take none.

    Returns
    -------
    evaluations : list of Evaluation
    offsets : dict of str to ndarray, shape (3,)
        For position characteristics (see :class:`RenderedCheck`).
    registration : Registration
    points : dict of str to (int, int)
        Edge points of each registered CAD feature in the left and right
        image features the chain matched (how much of the edge it kept).
    """
    from partinspect.cad.outlines import outline_images
    from partinspect.cad.registration import register
    from partinspect.cad.projection import edge_polylines
    from partinspect.tolerances.evaluate import evaluate_characteristic
    from partinspect.vision.posed import posed_stereo
    from partinspect.vision.stereo import measure_stereo

    def registered(res, hint):
        return register([f for f in res.features if f.kind != "line"], [f for f in res.features if f.kind == "line"],
                        inventory, datums=datums, pose_hint=hint)

    res = measure_stereo(left, right, calib)
    reg = registered(res, pose_hint)
    # As inspect does: lines clear of the other edges at their ends (of every
    # edge's image here, hidden ones too: this check has no visibility), and
    # edges in line with others measured on their own stretches.
    polylines = edge_polylines(inventory, reg.part_to_camera, calib)
    outlines = None if scene is None else outline_images(scene, calib, reg.part_to_camera)
    more, found, ends, withdrawn = posed_stereo(res, reg, None, inventory, calib, polylines, outlines)
    if found or ends or withdrawn:
        res, reg = more, registered(more, reg.part_to_camera)
    parts = reg.features_in_part_frame()
    evs = [evaluate_characteristic(c, parts, reg, inventory, seed=seed) for c in characteristics]
    offsets = {c.id: _position_offset(c, parts, inventory) for c in characteristics if c.type == "position"}
    points = {}
    for kind in ("circle", "line"):
        for i, cad_id in reg.assignment[kind].items():
            f3 = reg.measured_feature(kind, i)
            n = (len(res.left.features[f3.left]), len(res.right.features[f3.right]))
            points[cad_id] = max(points.get(cad_id, (0, 0)), n)
    return evs, offsets, reg, points


def monte_carlo_check(scene, inventory, calib, part_to_camera, characteristics, radiance, sensor, *, draws=50,
                      noise=2.0, seed=0, datums=None, progress=None):
    """Measure the characteristics on ``draws`` rendered noise draws.

    Parameters
    ----------
    scene : RaycastScene
    inventory : Inventory
    calib : StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
    characteristics : sequence of Characteristic
    draws : int
    noise : float
        Sensor noise, grey levels.
    seed : int
        Draw ``i`` uses ``numpy.random.default_rng([seed, i])``.
    datums : sequence of str, optional
    radiance : tuple of ndarray
        The noiseless left and right images (:attr:`Renderer.radiance`).
    sensor : callable
        Makes each draw's recorded image (:attr:`Renderer.sensor`).
    progress : callable, optional
        ``progress(message)`` after each draw.

    Returns
    -------
    RenderedCheck
    """
    from partinspect.cad.registration import RegistrationError

    ids = tuple(c.id for c in characteristics)
    values = {i: [] for i in ids}
    us = {i: [] for i in ids}
    offs = {c.id: [] for c in characteristics if c.type == "position"}
    material = {c.id: c for c in characteristics if c.type == "position" and c.material is not None}
    sizes = {cid: [] for cid in material}
    failed = []
    for k in range(draws):
        rng = np.random.default_rng([seed, k])
        left, right = (sensor(img, noise, rng) for img in radiance)
        try:
            evs, offsets, _, _ = measure_pair(left, right, calib, inventory, characteristics, datums=datums,
                                           pose_hint=part_to_camera, seed=seed + k, scene=scene)
        except RegistrationError as exc:
            failed.append(f"draw {k}: {exc}")
            continue
        for ev in evs:
            values[ev.id].append(np.nan if ev.measured is None else ev.measured)
            us[ev.id].append(np.nan if ev.standard_uncertainty is None else ev.standard_uncertainty)
        for cid, d in offsets.items():
            offs[cid].append(d)
        for ev in evs:
            if ev.id in sizes:
                sizes[ev.id].append(float(ev.details.get("measured_size", np.nan)) if ev.measured is not None else np.nan)
        if progress:
            progress(f"draw {k + 1}/{draws}")
    n = draws - len(failed)
    return RenderedCheck(
        ids,
        {c.id: c.type for c in characteristics},
        {i: np.array(v, float) for i, v in values.items()},
        {i: np.array(v, float) for i, v in us.items()},
        {i: np.array(v, float).reshape(-1, 3) for i, v in offs.items()},
        n,
        failed,
        {cid: (c.material, np.array(sizes[cid], float)) for cid, c in material.items()},
    )


def chance_interval(n, level=0.95, excess_kurtosis=0.0):
    """Interval of ``s / sigma`` for the sample standard deviation ``s`` of n values.

    For normal values ``s^2 / sigma^2`` is chi-square with ``nu = n - 1``
    degrees of freedom over ``nu``. Values of excess kurtosis ``k`` give
    ``s^2`` the variance ``sigma^4 (2 / (n - 1) + k / n)``; the interval is
    then that of a scaled chi-square of the same variance (Satterthwaite),
    ``nu = 2 / (2 / (n - 1) + k / n)``: wider for heavy tails, which form values
    and distances have, so that the normal interval would call a sound
    prediction wrong too often.

    Parameters
    ----------
    n : int
        Values, at least 2.
    level : float
    excess_kurtosis : float
        Of the values' distribution; negative values are taken as 0 (the
        normal interval is not narrowed).

    Returns
    -------
    ndarray, shape (2,)
        ``sqrt(chi2_q(nu) / nu)`` at the quantiles ``(1 -+ level) / 2``.

    References
    ----------
    .. [1] Satterthwaite, F. E. (1946). An approximate distribution of
           estimates of variance components. Biometrics Bulletin 2(6),
           110-114.
    .. [2] Cramer, H. (1946). Mathematical Methods of Statistics, 27.4
           (the variance of the sample variance).
    """
    from scipy import stats

    if n < 2:
        raise ValueError("a spread needs at least 2 values")
    nu = 2.0 / (2.0 / (n - 1) + max(float(excess_kurtosis), 0.0) / n)
    q = stats.chi2.ppf([(1 - level) / 2, (1 + level) / 2], nu)
    return np.sqrt(q / nu)


def checked_uncertainty(u, u_noise, measured_spread, n, excess_kurtosis=0.0, interval=None):
    """A predicted standard uncertainty after a check on n noise draws (module notes).

    Parameters
    ----------
    u : float
        The prediction's standard uncertainty (Type B part included).
    u_noise : float
        Its image-noise part: what the draws can show.
    measured_spread : float
        Their sample standard deviation (:meth:`RenderedCheck.spread`).
    n : int
        Values the spread was taken from.
    excess_kurtosis : float
        Of those values (see :func:`chance_interval`).
    interval : array_like, shape (2,), optional
        The interval of ``s / u_noise`` to judge by, instead of
        :func:`chance_interval` (a form value's, from its error model:
        :func:`form_interval`).

    Returns
    -------
    u_checked : float
        ``sqrt(u^2 + s^2 - u_noise^2)`` when ``s / u_noise`` lies above the
        interval, else ``u``.
    verdict : str
        "agrees", "prediction low" or "prediction high" (s below the
        interval: the prediction is kept).
    """
    lo, hi = chance_interval(n, excess_kurtosis=excess_kurtosis) if interval is None else interval
    r = measured_spread / u_noise
    if r > hi:
        return float(np.sqrt(u * u + measured_spread ** 2 - u_noise ** 2)), "prediction low"
    return float(u), ("prediction high" if r < lo else "agrees")


def form_interval(spreads, u_noise, level=0.95):
    """Interval of ``s / u_noise`` for a form value's spread ``s`` over the images of one scene.

    A straightness or circularity is a zone (maximum minus minimum) of points
    whose Type B displacements are fixed in a scene: which points set the zone
    depends on that pattern, so the spread over noise draws of one render
    differs from scene to scene by more than the chance of the draws. The
    prediction's ``u_noise`` is the RMS over scenes; the interval is the
    central ``level`` of the spreads the error model gives for as many draws
    of each scene (:func:`partinspect.tolerances.evaluate.form_scene_spreads`),
    which takes in the chance of the draws and the values' tails too.

    Parameters
    ----------
    spreads : array_like, shape (S,)
        Simulated spreads of S scenes, the characteristic's unit.
    u_noise : float
    level : float

    Returns
    -------
    ndarray, shape (2,)

    References
    ----------
    .. [1] JCGM 101:2008, 7.7 (coverage intervals from the quantiles of
           Monte Carlo output values).
    """
    q = np.quantile(np.asarray(spreads, float), [(1 - level) / 2, (1 + level) / 2])
    return q / u_noise


def spread_interval(chk, prediction, registration, n, *, seed=0, parts=None):
    """The interval of ``spread / u_noise`` a characteristic's spread over n draws is judged by.

    A straightness or circularity: :func:`form_interval` of the spreads
    its error model gives over scenes (from the noise-only prediction's
    ``registration``); any other characteristic: :func:`chance_interval`
    with the draws' sample kurtosis.

    Parameters
    ----------
    chk : RenderedCheck
    prediction : CharacteristicPrediction
        The noise-only prediction (its ``u`` is ``u_noise``).
    registration : Registration or None
        Of that prediction.
    n : int
        Values the spread was taken from.
    seed : int
    parts : list, optional
        ``registration.features_in_part_frame()``, if already at hand.

    Returns
    -------
    tuple of float
    """
    from partinspect.tolerances.evaluate import form_scene_spreads

    sp = None
    if registration is not None:
        parts = registration.features_in_part_frame() if parts is None else parts
        sp = form_scene_spreads(prediction.characteristic, parts, registration, n, seed=seed)
    if sp is not None:
        interval = form_interval(sp, prediction.u)
    else:
        interval = chance_interval(n, excess_kurtosis=_excess_kurtosis(chk, prediction.id))
    return tuple(float(v) for v in interval)


@dataclass(frozen=True)
class CheckedCharacteristic:
    """One characteristic of the proposed pose after the rendered check.

    Attributes
    ----------
    prediction : CharacteristicPrediction
        The plan's (Type B part included).
    u_noise : float
        The prediction's image-noise part, the characteristic's unit.
    spread : float
        Standard deviation of the chain's values over the draws (NaN with
        fewer than 3).
    measured : int
        Draws in which the chain measured it.
    u, U : float
        Standard and expanded (k = 2) uncertainty after the check
        (:func:`checked_uncertainty`).
    verdict : str
        "agrees", "prediction low", "prediction high", or why there is no
        comparison.
    decidable : bool
        ``U <= max_ratio * tolerance`` and measured in every draw.
    interval : tuple of float or None
        The chance interval of ``spread / u_noise`` it was judged by (its
        values' kurtosis taken into account), None without a comparison.
    """

    prediction: object
    u_noise: float
    spread: float
    measured: int
    u: float
    U: float
    verdict: str
    decidable: bool
    interval: tuple | None = None

    @property
    def id(self):
        return self.prediction.id

    @property
    def ratio(self):
        """``U / tolerance`` after the check (NaN without a tolerance)."""
        T = self.prediction.tolerance
        return self.U / T if T else float("nan")

    def to_dict(self):
        c = self.prediction.characteristic
        conv = np.degrees if c.unit == "rad" else float

        def num(x):
            return None if x is None or not np.isfinite(x) else round(float(conv(x)), 9)

        return {"id": self.id, "predicted_noise_u": num(self.u_noise), "measured_spread": num(self.spread),
                "measured_draws": self.measured, "standard_uncertainty": num(self.u),
                "expanded_uncertainty": num(self.U),
                "ratio": None if not np.isfinite(self.ratio) else round(float(self.ratio), 6),
                "verdict": self.verdict, "decidable": bool(self.decidable),
                "chance_interval": None if self.interval is None else [round(float(v), 4) for v in self.interval]}


@dataclass(frozen=True, eq=False)
class PoseCheck:
    """The rendered check of one pose's prediction.

    Attributes
    ----------
    draws : int
        Draws whose chain run completed.
    failed : list of str
        Why the others failed.
    interval : tuple of float
        The chance interval of ``spread / u`` for that many draws of normal
        values (95 %); heavier-tailed values get a wider one
        (``CheckedCharacteristic.interval``).
    characteristics : list of CheckedCharacteristic
        In the prediction's order.
    noise, seed : float, int
        Sensor noise (grey levels) and the seed of the draws.
    """

    draws: int
    failed: list
    interval: tuple
    characteristics: list
    noise: float
    seed: int

    @property
    def all_decidable(self):
        """Every inspected characteristic decidable after the check."""
        return all(c.decidable or not c.prediction.inspected for c in self.characteristics)

    def to_dict(self):
        return {"draws": self.draws, "failed": list(self.failed), "noise": self.noise, "seed": self.seed,
                "chance_interval": [round(float(v), 4) for v in self.interval],
                "all_decidable": self.all_decidable,
                "characteristics": [c.to_dict() for c in self.characteristics]}


def _excess_kurtosis(chk, cid):
    """The sample excess kurtosis of a characteristic's values over the draws (0 with fewer than 4).

    Position: that of the offsets' components, the largest (its spread is a norm of them), and of the
    measured size at MMC or LMC.
    """
    from scipy import stats

    if chk.types[cid] == "position":
        d = chk.offsets[cid]
        material = (chk.bonus or {}).get(cid)
        if material is not None:
            d = np.column_stack([d, material[1]])
        d = d[np.isfinite(d).all(axis=1)]
        cols = [d[:, k] for k in range(d.shape[1])] if len(d) >= 4 else []
    else:
        v = chk.values[cid]
        cols = [v[np.isfinite(v)]] if np.isfinite(v).sum() >= 4 else []
    ks = [float(stats.kurtosis(c, bias=False)) for c in cols if np.ptp(c) > 0]
    return max([k for k in ks if np.isfinite(k)], default=0.0)


def check_pose(inventory, scene, calib, prediction, characteristics, model, renderer, *, datums=None, draws=20,
               seed=0, progress=None):
    """Check one pose's prediction on rendered noise draws (``inspect plan --check``).

    Parameters
    ----------
    inventory : Inventory
    scene : RaycastScene
    calib : StereoCalibration
    prediction : PosePrediction
        The pose's prediction (its characteristics in the order of
        ``characteristics``).
    characteristics : sequence of Characteristic
    model : DetectorModel
        The prediction's; its noise and blur make the renders. A fixed
        ``contrast`` cannot be rendered.
    renderer : Renderer
        Makes the draws' images.
    datums : sequence of str, optional
    draws : int
        At least 3.
    seed : int
    progress : callable, optional

    Returns
    -------
    PoseCheck
    """
    import dataclasses

    from partinspect.planning.predict import predict_pose
    from partinspect.tolerances.evaluate import COVERAGE_FACTOR

    if draws < 3:
        raise ValueError("a check needs at least 3 draws")
    if model.contrast is not None:
        raise ValueError("renders show the faces' shading, not a fixed contrast")
    say = progress or (lambda message: None)
    P = prediction.part_to_camera
    say("check: the image-noise part of the prediction")
    noise_only = predict_pose(inventory, scene, calib, P, characteristics,
                              model=dataclasses.replace(model, systematic=False), datums=datums,
                              max_ratio=prediction.max_ratio)
    say("check: rendering the proposed pose")
    radiance = renderer.radiance(scene, calib, P, blur_sigma=model.blur)
    chk = monte_carlo_check(scene, inventory, calib, P, characteristics, radiance, renderer.sensor, draws=draws,
                            noise=model.noise, seed=seed, datums=datums,
                            progress=lambda message: say(f"check: {message}"))
    scene_parts = noise_only.registration.features_in_part_frame() if noise_only.registration is not None else None
    out = []
    for cp, cn in zip(prediction.characteristics, noise_only.characteristics):
        n = int(np.isfinite(chk.values[cp.id]).sum()) if chk.draws else 0
        s = chk.spread(cp.id) if chk.draws else float("nan")
        interval = None
        if not np.isfinite(cp.u):
            verdict, u = "not predicted measurable", cp.u
        elif n < 3 or not np.isfinite(s):
            verdict, u = f"measured in {n} of {chk.draws} draws: no spread", cp.u
        elif not (np.isfinite(cn.u) and cn.u > 0):
            verdict, u = "no image-noise part predicted", cp.u
        else:
            interval = spread_interval(chk, cn, noise_only.registration, n, seed=seed, parts=scene_parts)
            u, verdict = checked_uncertainty(cp.u, cn.u, s, n, interval=interval)
        U = COVERAGE_FACTOR * u
        T = cp.tolerance
        ok = bool(cp.decidable and chk.draws > 0 and n == chk.draws and T is not None
                  and U <= prediction.max_ratio * T)
        if cp.decidable and chk.draws and n < chk.draws:
            verdict += f"; measured in {n} of {chk.draws} draws"
        out.append(CheckedCharacteristic(cp, cn.u, s, n, u, U, verdict, ok, interval))
    interval = tuple(float(v) for v in chance_interval(max(chk.draws, 2)))
    return PoseCheck(chk.draws, list(chk.failed), interval, out, float(model.noise), int(seed))
