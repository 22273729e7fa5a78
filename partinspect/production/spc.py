"""Statistical process control of one characteristic: capability, control limits, run rules.

Plain functions on a numpy array ``x`` (n,) of one characteristic's
measured values in production order (mm or whatever the characteristic's
unit is). No I/O.

Two standard deviations, as ISO 22514-2 distinguishes them: the *within*
one (short-term) gives Cp and Cpk; the *overall* one, the sample standard
deviation s, gives Pp and Ppk. A drifting process has sigma_w < s, so
Cpk > Ppk flags the drift as much as the control chart does. Parts taken
one at a time give sigma_w = mean moving range / d2 and an individuals
chart; parts taken in rational subgroups of n = 2 to 10 (a lot, an hour's
sample) give sigma_w = mean subgroup range / d2(n) and an X-bar/R chart,
whose means show a shift of the process sooner and whose ranges show its
spread [2].

References
----------
.. [1] ISO 22514-2:2017, Statistical methods in process management --
       Capability and performance -- Part 2: Process capability and
       performance of time-dependent process models.
.. [2] ISO 7870-2:2023, Control charts -- Part 2: Shewhart control charts
       (individuals chart; the eight tests for special causes).
.. [3] Bissell, A. F. (1990). How reliable is your capability index?
       Applied Statistics 39(3), 331-340.
.. [4] Cryer, J. D., Ryan, T. P. (1990). The estimation of sigma for an X
       chart: MR/d2 or S/c4? Journal of Quality Technology 22(3), 187-192.
.. [5] Nelson, L. S. (1984). The Shewhart control chart -- tests for
       special causes. Journal of Quality Technology 16(4), 237-239.
.. [6] VDA Volume 5 (2021), Measurement and inspection processes;
       ISO 22514-7:2021, Capability of measurement processes.
.. [7] Montgomery, D. C. (2009). Introduction to Statistical Quality
       Control, 6th ed. Wiley: Appendix VI (the chart constants), the
       piston-ring inside diameters (25 subgroups of 5).
.. [8] Duncan, A. J. (1986). Quality Control and Industrial Statistics,
       5th ed. Irwin: the mean range's degrees of freedom, about
       0.9 k (n - 1) for k subgroups of n.
"""

from collections import Counter

import numpy as np
from scipy import special

#: E[|X1 - X2|] / sigma for two independent normal values: 2 / sqrt(pi).
D2 = 2.0 / np.sqrt(np.pi)
#: Upper limit of the moving-range chart, in mean moving ranges (n = 2).
D4 = 3.267
#: Degrees of freedom of sigma_w per degree of freedom of s ([4]; a
#: simulation of 10^5 normal series of 10 to 100 values gives 0.61-0.62).
MR_DOF_RATIO = 0.62
#: VDA 5's usual limit of the measurement process capability ratio Q_MP.
Q_LIMIT = 0.30

#: Chart constants of subgroups of n values (ISO 7870-2 [2], the tables of
#: [7]): n -> (A2, D3, D4, d2). X-bar limits x_bar_bar -+ A2 R_bar, range limits
#: D3 R_bar and D4 R_bar, sigma_w = R_bar / d2.
XBAR_R_CONSTANTS = {
    2: (1.880, 0.000, 3.267, 1.128),
    3: (1.023, 0.000, 2.574, 1.693),
    4: (0.729, 0.000, 2.282, 2.059),
    5: (0.577, 0.000, 2.114, 2.326),
    6: (0.483, 0.000, 2.004, 2.534),
    7: (0.419, 0.076, 1.924, 2.704),
    8: (0.373, 0.136, 1.864, 2.847),
    9: (0.337, 0.184, 1.816, 2.970),
    10: (0.308, 0.223, 1.777, 3.078),
}
#: Degrees of freedom of R_bar / d2 per degree of freedom of the pooled s ([8]).
RANGE_DOF_RATIO = 0.9

RULES = {
    1: "a point beyond the 3-sigma control limits",
    2: "9 points in a row on one side of the centre line",
    3: "6 points in a row steadily increasing or decreasing",
    4: "14 points in a row alternating up and down",
    5: "2 of 3 points in a row beyond 2 sigma on one side",
    6: "4 of 5 points in a row beyond 1 sigma on one side",
    7: "15 points in a row within 1 sigma of the centre line",
    8: "8 points in a row beyond 1 sigma, either side",
}


def sigma_within(x):
    """Within (short-term) standard deviation: mean moving range / d2; NaN for fewer than 2 values."""
    x = np.asarray(x, float)
    if x.size < 2:
        return np.nan
    return np.mean(np.abs(np.diff(x))) / D2


def individuals_limits(x):
    """Control limits of the individuals (X) and moving-range (MR) charts, ISO 7870-2.

    Returns
    -------
    dict
        ``center`` (mean), ``sigma`` (sigma_w), ``lcl``/``ucl`` = center
        -+ 3 sigma_w, ``mr_mean`` and ``mr_ucl`` = D4 x mean MR.
    """
    x = np.asarray(x, float)
    sigma = sigma_within(x)
    center = float(np.mean(x))
    return {"center": center, "sigma": sigma, "lcl": center - 3 * sigma, "ucl": center + 3 * sigma,
            "mr_mean": sigma * D2, "mr_ucl": D4 * sigma * D2}


def subgroups_of(labels):
    """The subgroups of values labelled ``labels`` (n,), in order of their first value.

    Returns
    -------
    list of ndarray of int
        Each subgroup's indices into the values, in production order.
    """
    order, members = [], {}
    for i, key in enumerate(labels):
        if key not in members:
            order.append(key)
            members[key] = []
        members[key].append(i)
    return [np.array(members[k], int) for k in order]


def subgroup_size(groups):
    """The subgroup size n a chart takes: the most common one (the larger on a tie)."""
    counts = Counter(len(g) for g in groups)
    return max(counts, key=lambda n: (counts[n], n)) if counts else 0


def xbar_r_limits(means, ranges, n):
    """Control limits of the X-bar and R charts of subgroups of ``n`` values, ISO 7870-2.

    Parameters
    ----------
    means, ranges : ndarray (k,)
        Each subgroup's mean and range (largest minus smallest value).
    n : int
        The subgroups' size, 2 to 10 (:data:`XBAR_R_CONSTANTS`).

    Returns
    -------
    dict
        ``center`` (grand mean), ``lcl``/``ucl`` = center -+ A2 R_bar,
        ``sigma`` = R_bar / d2 (the within standard deviation of one
        value), ``sigma_mean`` = A2 R_bar / 3 (one sigma of a subgroup
        mean, so that the run rules' zones are thirds of the drawn limits),
        ``r_mean`` = R_bar, ``r_lcl`` = D3 R_bar, ``r_ucl`` = D4 R_bar, ``n``.
    """
    a2, d3, d4, d2 = XBAR_R_CONSTANTS[n]
    center, r_mean = float(np.mean(means)), float(np.mean(ranges))
    return {"center": center, "lcl": center - a2 * r_mean, "ucl": center + a2 * r_mean, "sigma": r_mean / d2,
            "sigma_mean": a2 * r_mean / 3, "r_mean": r_mean, "r_lcl": d3 * r_mean, "r_ucl": d4 * r_mean, "n": n}


def capability_indices(mean, sigma, lower, upper):
    """Potential (Cp) and actual (Cpk) capability for a mean and a standard deviation.

    Parameters
    ----------
    lower, upper : float or None
        Specification limits; None where the characteristic has none
        (Cp then is None: one-sided, only Cpk = the one side's index).

    Returns
    -------
    (float or None, float or None)
        Cp = (U - L) / 6 sigma; Cpk = min(U - mean, mean - L) / 3 sigma.
    """
    if not sigma > 0:
        return None, None
    sides = [d / (3 * sigma) for d in ((None if upper is None else upper - mean),
                                       (None if lower is None else mean - lower)) if d is not None]
    cp = None if lower is None or upper is None else (upper - lower) / (6 * sigma)
    return cp, (min(sides) if sides else None)


def cp_interval(cp, dof, confidence=0.95):
    """Two-sided confidence interval of Cp (or Pp) from the chi-square distribution of the variance.

    Cp_hat sqrt(chi2_{a/2, nu} / nu) <= Cp <= Cp_hat sqrt(chi2_{1-a/2, nu} / nu), exact for normal
    data when sigma is the sample standard deviation (nu = n - 1), approximate
    with sigma_w (nu = 0.62 (n - 1), [4]). ISO 22514-2 [1].
    """
    if cp is None or not dof > 0:
        return None
    a = 1 - confidence
    # chdtri(nu, q): the chi-square quantile with upper tail q (scipy.special, no scipy.stats import).
    return (cp * np.sqrt(special.chdtri(dof, 1 - a / 2) / dof), cp * np.sqrt(special.chdtri(dof, a / 2) / dof))


def cpk_interval(cpk, n, dof, confidence=0.95):
    """Two-sided confidence interval of Cpk (or Ppk), Bissell's normal approximation [3].

    Cpk_hat -+ z_{1-a/2} sqrt(1 / (9 n) + Cpk_hat^2 / (2 nu)).
    """
    if cpk is None or not dof > 0:
        return None
    half = special.ndtri(1 - (1 - confidence) / 2) * np.sqrt(1 / (9 * n) + cpk ** 2 / (2 * dof))
    return (cpk - half, cpk + half)


def tolerance_width(lower, upper):
    """T = U - L; a one-sided upper limit (form, position) has the natural lower limit 0 (VDA 5 [6])."""
    if upper is None:
        return None
    return upper - (0.0 if lower is None else lower)


def measurement_capability_ratio(expanded_uncertainty, lower, upper):
    """Q_MP = 2 U / T: the share of the tolerance the measurement's own uncertainty takes (VDA 5 [6]).

    ``expanded_uncertainty``: U (k = 2) of the measurement process. Above
    :data:`Q_LIMIT` (30 %) the measuring system cannot judge the
    characteristic well enough, whatever the process does.
    """
    t = tolerance_width(lower, upper)
    if t is None or not t > 0 or expanded_uncertainty is None:
        return None
    return 2 * expanded_uncertainty / t


def run_rule_violations(x, center, sigma):
    """The points that complete each of the eight tests for special causes (ISO 7870-2 [2], Nelson [5]).

    Parameters
    ----------
    x : ndarray (n,)
        Values in production order.
    center, sigma : float
        Centre line and sigma of the individuals chart.

    Returns
    -------
    dict of int to ndarray of int
        Rule number (:data:`RULES`) -> indices of the points at which that
        pattern is complete (the last point of each window that shows it).
    """
    x = np.asarray(x, float)
    out = {r: np.zeros(0, int) for r in RULES}
    if x.size == 0 or not sigma > 0:
        return out
    z = (x - center) / sigma
    d = np.sign(np.diff(x))
    out[1] = np.flatnonzero(np.abs(z) > 3)
    out[2] = np.union1d(_window_ends(z > 0, 9, 9), _window_ends(z < 0, 9, 9))
    out[3] = np.union1d(_window_ends(d > 0, 5, 5), _window_ends(d < 0, 5, 5)) + 1
    out[4] = _window_ends(d[1:] * d[:-1] < 0, 12, 12) + 2
    out[5] = np.union1d(_window_ends(z > 2, 3, 2), _window_ends(z < -2, 3, 2))
    out[6] = np.union1d(_window_ends(z > 1, 5, 4), _window_ends(z < -1, 5, 4))
    out[7] = _window_ends(np.abs(z) < 1, 15, 15)
    out[8] = _window_ends(np.abs(z) > 1, 8, 8)
    return out


def _window_ends(flags, length, need):
    """Indices i where at least ``need`` of flags[i - length + 1 : i + 1] are true."""
    flags = np.asarray(flags, int)
    if flags.size < length:
        return np.zeros(0, int)
    counts = np.convolve(flags, np.ones(length, int), mode="valid")
    return np.flatnonzero(counts >= need) + length - 1


def characteristic_summary(x, lower, upper, u=None, confidence=0.95, subgroups=None):
    """Every SPC figure of one characteristic.

    Parameters
    ----------
    x : ndarray (n,)
        Measured values in production order (parts not measured left out).
    lower, upper : float or None
        Specification limits.
    u : ndarray (n,), optional
        Each value's standard uncertainty; its quadratic mean times 2 is the
        measurement process's U for Q_MP.
    confidence : float
        Level of the capability indices' intervals.
    subgroups : sequence (n,), optional
        Each value's subgroup label (a lot, a sample taken together). With
        subgroups of a common size of 2 to 10, at least two of them, the
        chart is X-bar/R and sigma_w = R_bar / d2 (ISO 22514-2); subgroups of
        another size are left out of the chart and of sigma_w, not of the
        mean and s. Otherwise, and without labels, the individuals chart.

    Returns
    -------
    dict
        n, mean, s (overall), sigma_within, cp, cpk, pp, ppk, each index's
        interval (``*_ci``, a pair or None), ``chart`` ("individuals" or
        "xbar-r"), control ``limits`` (:func:`individuals_limits` or
        :func:`xbar_r_limits`), ``violations`` (rule -> indices of values,
        or of subgroups on an X-bar chart), ``u_rms``, ``U`` (2 u_rms),
        ``q_mp`` (2 U / T) and ``capable_measurement`` (q_mp <= 30 %; None
        when it cannot be judged). On an X-bar/R chart also
        ``subgroup_size``, ``subgroup_index`` (the indices of each subgroup
        charted), ``subgroup_means``, ``subgroup_ranges``,
        ``range_violations`` (subgroups whose range is outside the R
        chart's limits) and ``subgroups_left_out``.
    """
    x = np.asarray(x, float)
    n = x.size
    out = {"n": n, "mean": float(np.mean(x)) if n else None, "s": float(np.std(x, ddof=1)) if n > 1 else None,
           "chart": "individuals"}
    groups = subgroups_of(subgroups) if subgroups is not None and n else []
    size = subgroup_size(groups)
    charted = [g for g in groups if len(g) == size]
    if 2 <= size <= max(XBAR_R_CONSTANTS) and len(charted) >= 2:
        means = np.array([x[g].mean() for g in charted])
        ranges = np.array([np.ptp(x[g]) for g in charted])
        limits = xbar_r_limits(means, ranges, size)
        out.update(chart="xbar-r", subgroup_size=size, subgroup_index=charted, subgroup_means=means,
                   subgroup_ranges=ranges, subgroups_left_out=len(groups) - len(charted),
                   range_violations=np.flatnonzero((ranges > limits["r_ucl"]) | (ranges < limits["r_lcl"])))
        dof_w = RANGE_DOF_RATIO * len(charted) * (size - 1)
        violations = run_rule_violations(means, limits["center"], limits["sigma_mean"])
    else:
        limits = individuals_limits(x) if n > 1 else None
        dof_w = MR_DOF_RATIO * (n - 1)
        violations = run_rule_violations(x, limits["center"], limits["sigma"]) if limits else {}
    sw = None if limits is None else limits["sigma"]
    out["sigma_within"] = sw
    dof_s = n - 1
    out["cp"], out["cpk"] = capability_indices(out["mean"], sw, lower, upper) if n > 1 else (None, None)
    out["pp"], out["ppk"] = capability_indices(out["mean"], out["s"], lower, upper) if n > 1 else (None, None)
    out["cp_ci"], out["pp_ci"] = cp_interval(out["cp"], dof_w, confidence), cp_interval(out["pp"], dof_s, confidence)
    out["cpk_ci"] = cpk_interval(out["cpk"], n, dof_w, confidence)
    out["ppk_ci"] = cpk_interval(out["ppk"], n, dof_s, confidence)
    out["limits"] = limits
    out["violations"] = violations
    u_rms = None if u is None or len(u) == 0 else float(np.sqrt(np.mean(np.square(u))))
    out["u_rms"], out["U"] = u_rms, None if u_rms is None else 2 * u_rms
    out["q_mp"] = measurement_capability_ratio(out["U"], lower, upper)
    out["capable_measurement"] = None if out["q_mp"] is None else bool(out["q_mp"] <= Q_LIMIT)
    return out
