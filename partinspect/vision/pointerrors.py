"""Simulated errors of one feature's triangulated edge points, correlated as the chain makes them.

The form of an edge (straightness, circularity) is judged on its triangulated
points, and the noise in them widens the form zone. How much depends on more
than each point's 3x3 covariance:

- a point's error comes from its left edge point's displacement across the
  edge (through the left ray and, along the epipolar line, into its right
  partner), and neighbouring edge points share smoothed noise: their
  displacements are correlated as ``exp(-d^2 / (4 l^2))`` over the edge
  filter's scale ``l`` (:func:`partinspect.vision.fitting.information_matrices`),
  so a zone sees fewer independent deviations than there are points;
- what remains of the shading displacement of a rim (the Type B component
  of :mod:`partinspect.vision.stereo`, ``View.bias``) is correlated over a
  much longer stretch: it bends the rim out of round rather than adding
  noise to it;
- the right fitted curve's error is common to all points (a smooth
  deformation of the whole edge, which moves the reference more than the
  zone);
- the calibration's error is common to all points too, one error for the
  whole run: besides moving the feature it bends it, for an error of the
  epipolar geometry slides each partner along the right curve by more
  where the epipolar lines cross it obliquely
  (:mod:`partinspect.vision.calibration_points`).

:class:`PointErrorModel` keeps these parts apart and draws them together,
for the Monte Carlo of :mod:`partinspect.tolerances.form` (JCGM 101: the
input quantities' distributions, their correlations included, propagated
by simulation).

References
----------
.. [1] JCGM 101:2008, Evaluation of measurement data -- Supplement 1 to the
       GUM -- Propagation of distributions using a Monte Carlo method,
       section 6.4.8 (multivariate Gaussian inputs).
.. [2] JCGM 100:2008, section 4.3 (Type B evaluation), 5.2 (correlated
       input quantities).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from partinspect.vision.psd import covariance_factor

__all__ = ["PointErrorModel", "correlated_field", "point_error_model", "short_scale_ratio"]

CHI2_1_MEDIAN = 0.454936423119572
"""Median of a chi-square variable with one degree of freedom."""


def correlated_field(s, length, rng, n_draws):
    """Gaussian random fields along an edge with unit variance and correlation ``exp(-d^2 / (4 length^2))``.

    White noise on a grid of arc length, smoothed by a Gaussian of standard
    deviation ``length`` (whose autocorrelation is the one wanted) and read
    at the points: O(points) per draw where a Cholesky factor of the
    points' correlation matrix would be O(points^3).

    Parameters
    ----------
    s : ndarray, shape (N,)
        Arc length of each point along the edge, px (any order; points far
        apart in ``s`` are uncorrelated).
    length : float
        Correlation length, px; 0 or None: independent points.
    rng : numpy.random.Generator
    n_draws : int

    Returns
    -------
    ndarray, shape (n_draws, N)
    """
    from scipy.ndimage import gaussian_filter1d

    s = np.asarray(s, float)
    if not length or len(s) == 0:
        return rng.standard_normal((n_draws, len(s)))
    h = length / 4.0  # grid step: neighbouring nodes correlate at 0.996, so interpolation keeps the variance
    pad = 5.0 * length
    s0 = s.min() - pad
    n_grid = int(np.ceil((s.max() + pad - s0) / h)) + 2
    sg = length / h
    w = gaussian_filter1d(rng.standard_normal((n_draws, n_grid)), sg, axis=1, mode="wrap")
    impulse = np.zeros(int(10 * sg) + 1)
    impulse[len(impulse) // 2] = 1.0
    w /= np.sqrt((gaussian_filter1d(impulse, sg, mode="constant") ** 2).sum())
    u = (s - s0) / h
    i = np.clip(np.floor(u).astype(int), 0, n_grid - 2)
    t = u - i
    return w[:, i] * (1.0 - t) + w[:, i + 1] * t


@dataclass(frozen=True)
class PointErrorModel:
    """Errors of a feature's triangulated points: parts along the edge and a common part.

    Attributes
    ----------
    arc_length : ndarray, shape (N,)
        Position of each point's left edge point along the edge, px (ideal
        pixels, cumulative distance in the points' order).
    normal_jacobian : ndarray, shape (N, 3)
        Displacement of each 3D point per px of its left edge point across
        the edge, mm/px (rig frame).
    components : tuple of (ndarray (N,), float)
        Displacements of the left edge points across the edge: per point
        standard uncertainty, px, and correlation length along the edge,
        px; independent of each other.
    common_jacobian : ndarray, shape (N, 3, k)
        d(3D point)/d(right fitted curve's parameters), mm.
    common_cov : ndarray, shape (k, k)
        Covariance of those parameters.
    systematic : tuple of int
        Indices into ``components`` of the Type B ones: fixed for one scene
        and lighting, unknown (:meth:`draw_held`).
    outlier_z : float or None
        The image fits rejected edge points whose residual exceeded this
        many of their standard uncertainties, so the points are those that
        passed; a simulation of them leaves out the simulated points
        beyond it (``outlier_z`` of :func:`partinspect.tolerances.form.straightness`).
        None: no such test.
    calibration : ndarray, shape (N, 3, q) or None
        Each point's response to the calibration's q principal directions
        of uncertainty, mm (:func:`partinspect.vision.calibration_points.point_responses`),
        drawn by :meth:`draw_calibration`, one standard normal deviate per
        direction common to all points. Kept out of :meth:`draw` and
        :meth:`covariances`: the image fits' outlier test, and the choice of
        the points a zone is read on, see each image's edge about its own
        fitted curve, which the calibration does not move.
    """

    arc_length: np.ndarray
    normal_jacobian: np.ndarray
    components: tuple
    common_jacobian: np.ndarray | None = None
    common_cov: np.ndarray | None = None
    systematic: tuple = ()
    outlier_z: float | None = None
    calibration: np.ndarray | None = None

    def draw(self, rng, n_draws):
        """Simulated errors of the points, shape (n_draws, N, 3), mm."""
        return self._draw(rng, n_draws, range(len(self.components)), True)

    def draw_calibration(self, rng, n_draws):
        """Simulated errors of the points from the calibration, shape (n_draws, N, 3), mm; None without them."""
        G = self.calibration
        if G is None or G.shape[2] == 0:
            return None
        z = rng.standard_normal((n_draws, G.shape[2]))
        return (z @ G.reshape(-1, G.shape[2]).T).reshape(n_draws, *G.shape[:2])

    def draw_held(self, rng, n_patterns, n_draws):
        """Errors of ``n_draws`` images of each of ``n_patterns`` scenes, shape (n_patterns, n_draws, N, 3), mm.

        The ``systematic`` components are drawn once per scene and held
        over its images; the random ones (and the common part, the right
        curve's fit of each image) anew for every image. What varies over
        the images of one scene is what noise draws of one render show.
        The calibration's part is not drawn: one rig's images share it.
        """
        n = len(self.arc_length)
        random = [k for k in range(len(self.components)) if k not in self.systematic]
        held = self._draw(rng, n_patterns, self.systematic, False)
        noise = self._draw(rng, n_patterns * n_draws, random, True).reshape(n_patterns, n_draws, n, 3)
        return noise + held[:, None]

    def covariances(self):
        """Each point's error covariance, shape (N, 3, 3), mm^2: what :meth:`draw` draws, point by point."""
        J = self.normal_jacobian
        var = sum(np.asarray(std, float) ** 2 for std, _ in self.components) if self.components else 0.0
        C = np.asarray(var)[..., None, None] * np.einsum("ni,nj->nij", J, J)
        if self.common_jacobian is not None and self.common_cov is not None:
            F = self._common_factor()
            C = C + np.einsum("nik,njk->nij", F, F)
        return C

    def _common_factor(self):
        """d(points)/d(unit normal deviates) of the common part, shape (N, 3, k), mm.

        The one factor both :meth:`covariances` and the draws use
        (:func:`partinspect.vision.psd.covariance_factor`): a right fit's
        covariance can be so ill-conditioned that propagating the matrix
        itself and drawing from its eigen-decomposition disagree by more
        than the points' own variance.
        """
        return np.einsum("nik,kl->nil", self.common_jacobian, covariance_factor(self.common_cov))

    def _draw(self, rng, n_draws, which, common):
        n = len(self.arc_length)
        # Every component moves the points along the same normal direction:
        # their fields add first, then one product with the Jacobian.
        across = np.zeros((n_draws, n))
        for k in which:
            std, length = self.components[k]
            across += correlated_field(self.arc_length, length, rng, n_draws) * std
        out = across[:, :, None] * self.normal_jacobian
        if common and self.common_jacobian is not None and self.common_cov is not None:
            F = self._common_factor()
            z = rng.standard_normal((n_draws, F.shape[2]))
            out += (z @ F.reshape(-1, F.shape[2]).T).reshape(n_draws, n, 3)  # a BLAS product, not einsum's loop
        return out


def point_error_model(corr, normals, components, systematic=(), outlier_z=None, calibration=None, left_common=None):
    """The :class:`PointErrorModel` of a feature's correspondences.

    Parameters
    ----------
    corr : Correspondences
        With ``jac_left``, ``jac_fit`` and ``fit_cov``.
    normals : ndarray, shape (M, 2)
        Unit normals of all the left feature's points (ideal pixels), of
        which ``corr.left_index`` picks the used ones.
    components : sequence of (ndarray (M,), float)
        Per point standard uncertainties across the edge, px, of all the
        left feature's points, with their correlation lengths, px.
    systematic : tuple of int
        Which of ``components`` are Type B (see :class:`PointErrorModel`).
    outlier_z : float, optional
        See :class:`PointErrorModel`.
    calibration : ndarray, shape (N, 3, q), optional
        The points' responses to the calibration (:class:`PointErrorModel`).
    left_common : ndarray, shape (M, q), optional
        An error of all the left feature's points across the edge common to
        them, px per unit normal deviate (a removed phase ripple's,
        :attr:`partinspect.vision.pixel_phase.PhaseRipple.factor`): drawn
        with the right fit's part, as one draw for the whole edge.
    """
    idx = corr.left_index
    steps = np.linalg.norm(np.diff(corr.left, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(steps)]
    n = np.asarray(normals, float)[idx]
    J = np.einsum("nij,nj->ni", corr.jac_left, n)
    comps = tuple((np.asarray(std, float)[idx] if np.ndim(std) else np.full(len(idx), float(std)), length)
                  for std, length in components)
    from scipy.linalg import block_diag

    jac, cov = corr.jac_fit, corr.fit_cov
    if left_common is not None:
        extra = J[:, :, None] * np.asarray(left_common, float)[idx][:, None, :]
        if jac is None or cov is None:
            jac, cov = extra, np.eye(extra.shape[2])
        else:
            jac, cov = np.concatenate([jac, extra], axis=2), block_diag(cov, np.eye(extra.shape[2]))
    return PointErrorModel(s, J, comps, jac, cov, tuple(systematic), outlier_z, calibration)


def short_scale_ratio(r, sigma, xy, length):
    """How much more the residuals scatter from point to point than the noise model predicts.

    Successive differences of the residuals about the fitted curve see
    what varies from one edge point to the next and not a smooth form
    deviation of the edge. Their squares over the variances the model
    predicts for them (``sigma`` correlated as ``exp(-d^2 / (4 length^2))``)
    are chi-square with one degree of freedom when the model is right, and
    so are the squared residuals over ``sigma^2``; the medians (robust to
    a few local defects) over the expected 0.455 give two variance ratios.
    The smaller is returned: an added ripple raises both, a smooth form
    deviation only the second, noise less correlated than modelled only
    the first. With it its standard error, 2.55 / sqrt(pairs) for
    neighbours correlated as the edge filter makes them (simulated).

    Returns
    -------
    ratio, standard error : float
        NaN, NaN with fewer than 10 neighbouring pairs.
    """
    d = np.diff(r)
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    rho = np.exp(-step * step / (4.0 * length * length)) if length else np.zeros_like(step)
    pred = sigma[:-1] ** 2 + sigma[1:] ** 2 - 2.0 * rho * sigma[:-1] * sigma[1:]
    ok = (step < 2.0) & (pred > 0)  # neighbours, not across a gap
    if ok.sum() < 10:
        return float("nan"), float("nan")
    short = float(np.median(d[ok] ** 2 / pred[ok]) / CHI2_1_MEDIAN)
    whole = float(np.median((r / sigma) ** 2) / CHI2_1_MEDIAN)
    return min(short, whole), 2.55 / np.sqrt(ok.sum())
