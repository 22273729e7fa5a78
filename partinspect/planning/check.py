"""Check predicted uncertainties against the real chain on rendered images (JCGM 101).

The part is ray-cast once per camera (noiseless radiance, blurred by the
optics); each draw then adds fresh sensor noise
(:func:`partinspect.simulate.render.sensor`) and runs the whole measurement
chain as ``inspect`` does: :func:`partinspect.vision.stereo.measure_stereo`,
:func:`partinspect.cad.registration.register` (with the true pose as hint,
so a rare ambiguous draw does not stop the check), and
:func:`partinspect.tolerances.evaluate.evaluate`. Over the draws, each
characteristic's measured spread is set beside its predicted ``u`` and the
``u`` the chain reported.

The measured spread is the standard deviation of the measured values,
except for position, which is a norm (2 |d| for the centre's offset d in
the plane of the nominal circle): its spread is taken as
``2 sqrt(tr Cov(d))``, the RMS of ``2 |d - mean(d)|``, which is what
:func:`partinspect.tolerances.evaluate.true_position` gives as ``u`` for a
centre at its true position (the rendered images carry a small systematic
offset that is no part of the spread).

References
----------
.. [1] JCGM 101:2008, GUM Supplement 1: propagation of distributions using
       a Monte Carlo method, 7.6 (the standard deviation of the output
       values as the standard uncertainty).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RenderedCheck", "render_radiance_pair", "measure_pair", "monte_carlo_check", "spread"]


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
    """

    ids: tuple
    types: dict
    values: dict
    reported_u: dict
    offsets: dict
    draws: int
    failed: list

    def spread(self, cid):
        """Measured standard uncertainty of one characteristic (module notes), NaN with < 3 values."""
        if self.types[cid] == "position":
            d = self.offsets[cid]
            d = d[np.isfinite(d).all(axis=1)]
            if len(d) < 3:
                return float("nan")
            return 2.0 * float(np.sqrt(np.trace(np.cov(d, rowvar=False))))
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


def spread(values):
    """Sample standard deviation of the finite values (ddof 1), NaN with fewer than 3."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.std(v, ddof=1)) if len(v) >= 3 else float("nan")


def render_radiance_pair(scene, calib, part_to_camera, *, blur_sigma=0.6, shading=None, samples=None):
    """The noiseless, blurred left and right images (float32 grey levels).

    Each draw of a Monte Carlo check is ``sensor(image, noise, rng)`` of
    these: the ray casting is done once.
    """
    from partinspect.simulate.render import DEFAULT_SHADING, SAMPLES, blur, camera_in_part, render_radiance

    shading = shading or DEFAULT_SHADING
    samples = SAMPLES if samples is None else samples
    light = np.asarray(part_to_camera, float)[:3, :3].T @ shading.direction()
    out = []
    for index in (0, 1):
        K, D, R, t = camera_in_part(calib, index, part_to_camera)
        img, _ = render_radiance(scene, K, D, R, t, calib.image_size, light, shading=shading, samples=samples)
        out.append(blur(img, blur_sigma))
    return tuple(out)


def _position_offset(c, parts, inventory):
    fid = c.features[0]
    cands = [p for p in parts if p.cad_id == fid and p.kind == "circle"]
    if not cands:
        return np.full(3, np.nan)
    nominal = inventory[fid]
    N = np.asarray(nominal.normal, float)
    Pn = np.eye(3) - np.outer(N, N)
    return Pn @ (cands[0].center - np.asarray(nominal.center, float))


def measure_pair(left, right, calib, inventory, characteristics, *, datums=None, pose_hint=None, seed=0):
    """Run the measurement chain on one image pair and evaluate the characteristics.

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
    from partinspect.cad.registration import register
    from partinspect.tolerances.evaluate import evaluate_characteristic
    from partinspect.vision.stereo import measure_stereo

    res = measure_stereo(left, right, calib)
    circles = [f for f in res.features if f.kind != "line"]
    lines = [f for f in res.features if f.kind == "line"]
    reg = register(circles, lines, inventory, datums=datums, pose_hint=pose_hint)
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


def monte_carlo_check(scene, inventory, calib, part_to_camera, characteristics, *, draws=50, noise=2.0, seed=0,
                      datums=None, blur_sigma=0.6, radiance=None, progress=None):
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
    blur_sigma : float
        Optics blur, px.
    radiance : tuple of ndarray, optional
        The noiseless images, if already rendered
        (:func:`render_radiance_pair`).
    progress : callable, optional
        ``progress(message)`` after each draw.

    Returns
    -------
    RenderedCheck
    """
    from partinspect.cad.registration import RegistrationError
    from partinspect.simulate.render import sensor

    if radiance is None:
        radiance = render_radiance_pair(scene, calib, part_to_camera, blur_sigma=blur_sigma)
    ids = tuple(c.id for c in characteristics)
    values = {i: [] for i in ids}
    us = {i: [] for i in ids}
    offs = {c.id: [] for c in characteristics if c.type == "position"}
    failed = []
    for k in range(draws):
        rng = np.random.default_rng([seed, k])
        left, right = (sensor(img, noise, rng) for img in radiance)
        try:
            evs, offsets, _, _ = measure_pair(left, right, calib, inventory, characteristics, datums=datums,
                                           pose_hint=part_to_camera, seed=seed + k)
        except RegistrationError as exc:
            failed.append(f"draw {k}: {exc}")
            continue
        for ev in evs:
            values[ev.id].append(np.nan if ev.measured is None else ev.measured)
            us[ev.id].append(np.nan if ev.standard_uncertainty is None else ev.standard_uncertainty)
        for cid, d in offsets.items():
            offs[cid].append(d)
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
    )
