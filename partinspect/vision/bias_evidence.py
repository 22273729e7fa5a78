"""How much of a fit's stated systematic (Type B) displacement its own residuals show.

A rim's points carry a stated Type B standard uncertainty for what the
shading correction and the detector leave of their displacement
(:attr:`partinspect.vision.fit3d.View.bias`), correlated along the edge over
``bias_corr_length``. That statement is a model: how large the remainder
really is depends on the optics, the sensor and the surface, not on the
renderer it was set on. The fit's residuals are evidence of it. Smoothed
along the edge over the systematic part's own correlation length, the
image noise (correlated over about one pixel) averages out, and what is
left is the systematic displacement, less what the fit's parameters took
up. The ratio of its observed to its stated variance, ``k^2``, is a Type A
evaluation of the Type B component's level (JCGM 100, 4.2 and 4.3.9),
which the fit's systematic covariance is then scaled by.

With residuals ``e`` (px) of the stacked views, smoothing ``A`` (a
Gaussian along each view's edge, rows summing to one) and the fit's
residual maker ``M = I - Q Q^T`` (``Q`` an orthonormal basis of the
weighted Jacobian), the smoothed residuals' expected square is
``tr(A M S M^T A^T)`` for the errors' covariance ``S``: the noise's
``S_n`` and the stated Type B ``S_b``. Then
``k^2 = (|A e|^2 - E_n) / E_b``, and its standard error under noise
alone is ``sqrt(2 tr((A S_n A^T)^2)) / E_b`` (a Gaussian quadratic form).

References
----------
.. [1] JCGM 100:2008 (GUM), 4.2 (Type A), 4.3.9 (Type B from a bound),
       F.2.4.5 (a systematic effect evaluated from the data).
.. [2] Birge, R. T. (1932). The calculation of errors by the method of
       least squares. Phys. Rev. 40, 207-227 (scaling stated uncertainties
       by what the residuals show).
.. [3] Mathai, A. M., Provost, S. B. (1992). Quadratic Forms in Random
       Variables, 3.2 (mean and variance of a Gaussian quadratic form).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

__all__ = ["correlation_matrix", "bias_evidence"]

CUTOFF = 6.0
"""Correlations ``exp(-d^2 / (4 l^2))`` are kept to ``d = CUTOFF l`` (below 1e-4)."""


def correlation_matrix(xy, length, scale=4.0):
    """Sparse ``exp(-d^2 / (scale l^2))`` between the points of one edge, (N, N).

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Points, px (any order: near points count whatever their index).
    length : float
        Correlation length l, px.
    scale : float
        4 for the correlation form of :class:`partinspect.vision.fit3d.View`;
        2 for a Gaussian of standard deviation l.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (N, N)
    """
    n = len(xy)
    tree = cKDTree(xy)
    pairs = tree.query_pairs(CUTOFF * length * np.sqrt(scale / 4.0), output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    d2 = np.sum((xy[i] - xy[j]) ** 2, axis=1)
    w = np.exp(-d2 / (scale * length * length))
    rows = np.r_[i, j, np.arange(n)]
    cols = np.r_[j, i, np.arange(n)]
    return sparse.csr_matrix((np.r_[w, w, np.ones(n)], (rows, cols)), shape=(n, n))


def _scaled(R, a, b=None):
    """``diag(a) R diag(b)`` of a sparse R."""
    b = a if b is None else b
    return sparse.diags(a) @ R @ sparse.diags(b)


def _expected_squares(A, Q):
    """``S -> tr(A M S M^T A^T)`` with ``M = I - Q Q^T``: the smoothed residuals' expected square.

    ``tr(A S A^T)`` is taken as the sum of ``(A^T A) * S`` elementwise,
    which needs neither product of two wide matrices.
    """
    AtA = (A.T @ A).tocsr()
    AtAQ = AtA @ Q
    QtAtAQ = Q.T @ AtAQ

    def expected(S):
        SQ = S @ Q
        return float(AtA.multiply(S).sum() - 2.0 * np.sum(SQ * AtAQ) + np.sum((Q.T @ SQ) * QtAtAQ))

    return expected


def bias_evidence(views, residuals, jacobian):
    """Observed over stated variance of the views' systematic displacement, from the fit's residuals.

    Parameters
    ----------
    views : sequence of View
        The fit's views (:class:`partinspect.vision.fit3d.View`), each with
        ``bias`` and ``bias_corr_length``.
    residuals : ndarray, shape (N,)
        The fit's weighted residuals (each point's over its ``total_sigma``),
        views stacked in order.
    jacobian : ndarray, shape (N, p)
        Their Jacobian with respect to the fit's p parameters.

    Returns
    -------
    k2 : float
        ``(|A e|^2 - E_n) / E_b`` (module notes); may be negative by chance.
    se : float
        Its standard error under the image noise alone.
    None if no view carries a systematic part.
    """
    blocks_A, blocks_n, blocks_b, t_all = [], [], [], []
    for v in views:
        n = len(v.xy)
        t = np.broadcast_to(np.asarray(v.total_sigma, float), (n,))
        sigma = np.broadcast_to(np.asarray(v.sigma, float), (n,))
        G = correlation_matrix(v.xy, v.bias_corr_length or 1.0, scale=2.0) if v.bias is not None else None
        if G is None:
            G = sparse.csr_matrix((n, n))
        G = sparse.diags(1.0 / np.maximum(np.asarray(G.sum(axis=1)).ravel(), 1e-300)) @ G
        Sn = _scaled(correlation_matrix(v.xy, v.corr_length or 1e-6), sigma)
        if v.sigma_correction is not None:
            Sn = Sn + _scaled(correlation_matrix(v.xy, v.correction_corr_length), v.sigma_correction)
        if v.bias is not None:
            Sb = _scaled(correlation_matrix(v.xy, v.bias_corr_length), np.broadcast_to(v.bias, (n,)))
        else:
            Sb = sparse.csr_matrix((n, n))
        blocks_A.append(G @ sparse.diags(t))
        blocks_n.append(Sn)
        blocks_b.append(Sb)
        t_all.append(t)
    if all(v.bias is None for v in views):
        return None
    A = sparse.block_diag(blocks_A, format="csr")
    tinv = sparse.diags(1.0 / np.concatenate(t_all))
    Sn = (tinv @ sparse.block_diag(blocks_n) @ tinv).tocsr()
    Sb = (tinv @ sparse.block_diag(blocks_b) @ tinv).tocsr()
    Q, _ = np.linalg.qr(np.asarray(jacobian, float))
    observed = float(np.sum((A @ residuals) ** 2))
    expected = _expected_squares(A, Q)
    En, Eb = expected(Sn), expected(Sb)
    if not Eb > 0:
        return None
    C = A @ Sn @ A.T
    se = float(np.sqrt(2.0 * C.multiply(C).sum())) / Eb
    return (observed - En) / Eb, se
