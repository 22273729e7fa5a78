"""Adaptive processing: each measuring step checks its result and is re-run when it falls short.

After the paper's planning system (Situation Graph Trees): the chain's
result is examined against explicit conditions, the *situations*; one that
holds triggers the next untried *action* of its list (a change of the
processing parameters, :data:`DEFAULTS`: the edge filter's scale
``sigma`` in px, the hysteresis thresholds ``k_low``, ``k_high`` in units
of the gradient noise, ``min_points``), the step is re-run, and the better
result is kept. A situation that persists after its actions are spent
gives its *advice*: the change of acquisition (pose, lighting, another
view) the data call for, since processing cannot supply what the images do
not hold. The graph is data (:data:`SITUATIONS`); nothing else branches on
the situation.

A re-run for missing edges seldom measures everything the round before it
did (a lower threshold or wider filter finds a faint edge and loses
another), so only what it adds is taken: its features that the best round
lacks join the best round's and the pose is fitted again. A candidate is
better when it aligns the model where the other does not, then when it
finds one pose where the other finds several that explain its features as
well, then when it measures more of the CAD edges in view, then when it
mends a situation and meets no new one (:func:`better`). Ties keep the earlier round: the defaults
are the parameters the chain's error model is validated at. A smaller
registration misfit alone does not count, as it moves with which features
the pose fit leaves out. Each round's covariances describe its own data,
so the choice needs no correction of the uncertainties.

References
----------
.. [1] The paper of this project (``../shared/paper/``), sections 1-2: the
       planning system that adjusts processing and acquisition.
.. [2] Arens, M., & Nagel, H.-H. (2003). Behavioral knowledge
       representation for the understanding and creation of video sequences
       (Situation Graph Trees). KI 2003, LNAI 2821, 149-163.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from partinspect.errors import InputError

__all__ = ["DEFAULTS", "MAX_ROUNDS", "Situation", "SITUATIONS", "State", "Round", "better", "measured_ids", "state_of", "met_situations", "measure_adaptively"]

DEFAULTS = {"sigma": 1.0, "k_low": 4.0, "k_high": 8.0, "min_points": 12}
MAX_ROUNDS = 4
"""The chain runs at most this many times (the first with the defaults)."""


@dataclass(frozen=True)
class State:
    """What one round of the chain produced, as the conditions see it.

    Attributes
    ----------
    params : dict
        The parameters of the round.
    noise : tuple of float
        Estimated image noise, left and right, grey levels.
    edge_snr : float
        Median edge strength over the gradient noise, both images.
    noise_ratio : float
        Median over the image features of the fit residuals' spread relative
        to the predicted noise (1 when consistent).
    missing : tuple of str
        CAD edges both cameras see at the registered pose, with a grey step
        across them in both images, but not measured.
    registration_error : str or None
        Why the CAD model could not be aligned, when it could not.
    weighted_rms : float
        Registration misfit relative to the stated covariances (NaN when
        there is no registration).
    registration_dof : int
        Its degrees of freedom (residuals less the pose's 6; 0 without one).
    ambiguity : str or None
        Other poses explain the measured features as well and the CAD model
        is not symmetric under the turns between them
        (:attr:`~partinspect.cad.registration.Registration.ambiguity`).
    """

    params: dict
    noise: tuple
    edge_snr: float
    noise_ratio: float
    missing: tuple
    registration_error: str | None
    weighted_rms: float
    registration_dof: int = 0
    ambiguity: str | None = None


@dataclass(frozen=True)
class Situation:
    """One node of the situation graph.

    Attributes
    ----------
    name : str
    step : str
        The processing step it judges ("edges", "fits", "matching",
        "registration").
    condition : callable
        ``condition(state) -> str or None``: a description when it holds.
    actions : tuple of dict
        Parameter changes to try, in order, each applied on top of the
        parameters of the best round so far.
    advice : str
        The acquisition change to make when it persists.
    recovers : bool
        Its actions re-run the chain for what the best round lacks: the
        features a re-run measures that the best round left missing are
        added to the best round's (``merge`` of :func:`measure_adaptively`),
        whose other features stay as they were measured.
    """

    name: str
    step: str
    condition: object
    actions: tuple
    advice: str
    recovers: bool = False


def _registration_failed(s):
    return s.registration_error


def _pose_ambiguous(s):
    return s.ambiguity


def _features_missing(s):
    if s.registration_error or not s.missing:
        return None
    return f"{len(s.missing)} CAD edge(s) in view of both cameras not measured: {', '.join(s.missing)}"


def _residuals_inconsistent(s):
    if np.isfinite(s.noise_ratio) and s.noise_ratio > 1.5:
        return f"fit residuals {s.noise_ratio:.2f} times the predicted noise (median over the fits)"
    return None


REGISTRATION_RMS_LIMIT = 2.0
"""A registration whose weighted RMS (1 when the matched features scatter
about the CAD model as their covariances say) exceeds this, and whose
chi-square is beyond chance (p < 1e-6), is a situation. Sound renders stay
well below it with the first-order model's approximations; since single
mispaired edges are left out of the pose fit
(:data:`partinspect.cad.pose_refine.OUTLIER_P`), what exceeds it is a misfit
spread over many features: a wrong calibration, a part of another revision,
a part that moved."""


def _registration_inconsistent(s):
    # chdtrc is what scipy.stats.chi2.sf calls, without scipy.stats' import time.
    from scipy.special import chdtrc

    w, dof = s.weighted_rms, s.registration_dof
    if s.registration_error or not np.isfinite(w) or dof <= 0 or w <= REGISTRATION_RMS_LIMIT:
        return None
    chi2 = w * w * dof
    if chdtrc(dof, chi2) >= 1e-6:
        return None
    return (f"the matched features scatter about the CAD model {w:.1f} times as much as their uncertainties say "
            f"(weighted RMS; chi-square {chi2:.0f} on {dof} degrees of freedom)")


def _low_contrast(s):
    if np.isfinite(s.edge_snr) and s.edge_snr < 12.0:
        return f"edges only {s.edge_snr:.1f} times the gradient noise (median)"
    return None


SITUATIONS = (
    Situation(
        "registration failed", "registration", _registration_failed,
        ({"sigma": 1.5}, {"k_low": 3.0, "k_high": 6.0, "min_points": 8}),
        "put more of the part in view, or turn it so that two holes or two non-parallel edges are seen "
        "(inspect plan proposes a pose); give --pose-hint for a symmetric part",
    ),
    Situation(
        "pose ambiguous", "registration", _pose_ambiguous,
        ({"min_points": 8}, {"k_low": 3.0, "k_high": 6.0}),
        "turn the part so that a feature the registration names as telling its poses apart is seen, or give "
        "--pose-hint: until then what depends on which pose is right stays inconclusive",
    ),
    Situation(
        "expected edges missing", "matching", _features_missing,
        ({"k_low": 3.0, "k_high": 6.0}, {"min_points": 8}, {"sigma": 1.5}),
        "these edges show too little contrast or too few points: change the lighting so their two faces differ, "
        "or turn the part so they are seen more squarely (inspect plan names a better pose)",
        recovers=True,
    ),
    Situation(
        "residuals inconsistent with the noise", "fits", _residuals_inconsistent,
        ({"sigma": 1.5},),
        "check the focus, vibration and the lens calibration: the edges scatter more than the image noise explains",
    ),
    Situation(
        "registration inconsistent", "registration", _registration_inconsistent, (),
        "the measured edges disagree with the CAD model beyond their uncertainties, so the pose, and the positions, "
        "distances and profiles that rest on it, may be less certain than stated: check the lens calibration "
        "(distortion), that the part is the STEP model's revision, and that it sits still on the fixture",
    ),
    Situation(
        "low edge contrast", "edges", _low_contrast,
        ({"sigma": 1.5}, {"sigma": 2.0}),
        "raise the contrast: more light or exposure, a background that differs from the part",
    ),
)


@dataclass
class Round:
    """One run of the chain: its parameters, result and the situations met."""

    params: dict
    state: State
    stereo: object
    registration: object
    visibility: dict | None
    situations: list = field(default_factory=list)

    def score(self):
        """(aligned, its pose not ambiguous, minus the CAD edges in view left unmeasured): larger is better."""
        measured = -len(self.state.missing) if self.registration is not None else -10**6
        return (self.registration is not None, not self.state.ambiguity, measured)


def better(new, best):
    """Whether round ``new`` replaces round ``best`` (module notes).

    Parameters
    ----------
    new, best : Round

    Returns
    -------
    bool
        True when ``new`` scores higher (:meth:`Round.score`), or scores as
        high and the situations it meets are a strict subset of ``best``'s.
    """
    if new.score() != best.score():
        return new.score() > best.score()
    return {s.name for s, _ in new.situations} < {s.name for s, _ in best.situations}


def measured_ids(registration):
    """The CAD feature ids a registration assigned measured features to (a set)."""
    return set(registration.assignment["circle"].values()) | set(registration.assignment["line"].values())


def state_of(params, stereo, registration, visibility, error=None):
    """The :class:`State` of one round."""
    from partinspect.vision.edges import gradient_noise_std

    snr = []
    for side in (stereo.left, stereo.right):
        e = side.edges
        gn = gradient_noise_std(side.noise, e.sigma)
        if len(e.strength) and gn > 0:
            snr.append(np.asarray(e.strength) / gn)
    edge_snr = float(np.median(np.concatenate(snr))) if snr else float("nan")
    ratios = [f.fit.consistency.noise_ratio for side in (stereo.left, stereo.right) for f in side.features
              if getattr(f.fit, "consistency", None) is not None]
    missing = ()
    wrms, dof = float("nan"), 0
    if registration is not None:
        measured = measured_ids(registration)
        noise = max(float(stereo.left.noise), float(stereo.right.noise))
        missing = tuple(fid for fid, v in visibility.items() if v.shows_edge(noise) and fid not in measured)
        wrms, dof = float(registration.weighted_rms), int(registration.dof)
    ambiguity = getattr(registration, "ambiguity", "") or None
    return State(dict(params), (float(stereo.left.noise), float(stereo.right.noise)), edge_snr,
                 float(np.median(ratios)) if ratios else float("nan"), missing, error, wrms, dof, ambiguity)


def met_situations(state, graph=SITUATIONS):
    """The situations that hold in ``state``: list of (Situation, description)."""
    out = []
    for sit in graph:
        why = sit.condition(state)
        if why:
            out.append((sit, why))
    return out


def measure_adaptively(run_round, *, graph=SITUATIONS, max_rounds=MAX_ROUNDS, progress=None, merge=None):
    """Run the chain, and re-run it with adjusted parameters while a situation holds.

    Parameters
    ----------
    run_round : callable
        ``run_round(params) -> (stereo, registration, visibility)``; raises
        :class:`~partinspect.errors.InputError` when the CAD model cannot be
        aligned (the round then has no registration).
    graph : sequence of Situation
    max_rounds : int
    progress : callable, optional
    merge : callable, optional
        ``merge(best, new, ids) -> (stereo, registration, visibility)``:
        ``best``'s result with the features of round ``new`` measured as
        the CAD ids ``ids`` added, the pose fitted again (module notes);
        may raise :class:`~partinspect.errors.InputError`. Without it a
        re-run for missing edges is a candidate whole.

    Returns
    -------
    best : Round
        The best round (see the module notes); a merged one has the
        parameters of the re-run that added to it.
    log : list of dict
        Every round: its parameters, the situations met, the action taken,
        the features it added to the best round's (``added``, when merged)
        and whether it was kept.
    advice : list of dict
        Situations that still hold in the best round, with their advice.

    Raises
    ------
    InputError
        When no round could align the CAD model: the first round's error.
    """
    say = progress or (lambda m: None)
    tried = {s.name: 0 for s in graph}
    params = dict(DEFAULTS)
    rounds, log, first_error = [], [], None
    best = None
    action_taken, recovering = None, False
    for n in range(max_rounds):
        try:
            stereo, reg, vis = run_round(params)
            error = None
        except InputError as e:
            if first_error is None:
                first_error = e
            stereo, reg, vis, error = getattr(e, "stereo", None), None, None, e.problem
            if stereo is None:
                raise
        r = Round(dict(params), state_of(params, stereo, reg, vis, error), stereo, reg, vis)
        r.situations = met_situations(r.state, graph)
        added = []
        if recovering and merge is not None and reg is not None and best.registration is not None:
            found = measured_ids(reg)
            added = [fid for fid in best.state.missing if fid in found]
            if added:
                try:
                    stereo, reg, vis = merge(best, r, added)
                except InputError:
                    added = []
                else:
                    r = Round(dict(params), state_of(params, stereo, reg, vis), stereo, reg, vis)
                    r.situations = met_situations(r.state, graph)
        rounds.append(r)
        kept = best is None or better(r, best)
        if kept:
            best = r
        entry = {"round": n + 1, "params": dict(params),
                 "situations": [{"name": s.name, "step": s.step, "detail": why} for s, why in r.situations],
                 "missing": list(r.state.missing),
                 "kept": kept}
        if added:
            entry["added"] = list(added)
        if action_taken is not None:
            entry["after"] = action_taken
        log.append(entry)
        # The next action: the first situation of the best round with one left.
        nxt = None
        for sit, why in best.situations:
            if tried[sit.name] < len(sit.actions):
                nxt = (sit, sit.actions[tried[sit.name]])
                tried[sit.name] += 1
                break
        if nxt is None or n + 1 == max_rounds:
            break
        sit, change = nxt
        params = {**best.params, **change}
        recovering = sit.recovers
        action_taken = {"situation": sit.name, "change": dict(change)}
        say(f"adaptive: {sit.name}; re-running with {', '.join(f'{k}={v:g}' for k, v in change.items())}")
    if best.registration is None:
        raise first_error
    advice = [{"situation": s.name, "step": s.step, "detail": why, "advice": s.advice} for s, why in best.situations]
    return best, log, advice
