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

from partinspect.vision.blas import one_blas_thread

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
    from scipy.spatial import cKDTree

    n = len(xy)
    tree = cKDTree(xy)
    pairs = tree.query_pairs(CUTOFF * length * np.sqrt(scale / 4.0), output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    d2 = np.sum((xy[i] - xy[j]) ** 2, axis=1)
    w = np.exp(-d2 / (scale * length * length))
    rows = np.r_[i, j, np.arange(n)]
    cols = np.r_[j, i, np.arange(n)]
    return sparse.csr_matrix((np.r_[w, w, np.ones(n)], (rows, cols)), shape=(n, n))


DENSE_MAX = 3000
"""Views of at most this many points are handled as dense matrices: a
rim's smoothing over its Type B correlation length couples a good part of
its points, and dense products of a few hundred rows beat sparse ones
many times; larger views stay sparse, for memory."""


def _hadamard_sum(X, Y):
    """``sum(X * Y)`` elementwise, X and Y both sparse or both dense."""
    return float(X.multiply(Y).sum()) if sparse.issparse(X) else float(np.sum(X * Y))


def _dense_correlation(d2, length, scale=4.0):
    """`correlation_matrix` as a dense array, with the same cutoff, from the squared distances (n, n)."""
    w = np.exp(d2 * (-1.0 / (scale * length * length)))
    w[d2 > (CUTOFF * length) ** 2 * (scale / 4.0)] = 0.0
    return w


def _view_operators(v):
    """One view's smoothing A (rows summing to one, per weighted residual) and its S_n, S_b.

    All (n, n), in units of the weighted residuals; dense when the view
    has at most ``DENSE_MAX`` points, sparse otherwise.
    """
    n = len(v.xy)
    dense = n <= DENSE_MAX
    xy = np.asarray(v.xy, float)

    if dense:
        d2 = np.subtract.outer(xy[:, 0], xy[:, 0]) ** 2 + np.subtract.outer(xy[:, 1], xy[:, 1]) ** 2

    def corr(length, scale=4.0):
        return _dense_correlation(d2, length, scale) if dense else correlation_matrix(xy, length, scale)

    def scaled(R, a):  # diag(a) R diag(a)
        a = np.broadcast_to(np.asarray(a, float), (n,))
        return a[:, None] * R * a[None, :] if dense else (sparse.diags(a) @ R @ sparse.diags(a)).tocsr()

    def zero():
        return np.zeros((n, n)) if dense else sparse.csr_matrix((n, n))

    t = np.broadcast_to(np.asarray(v.total_sigma, float), (n,))
    A = zero()
    if v.bias is not None:
        G = corr(v.bias_corr_length or 1.0, scale=2.0)
        rows = np.asarray(G.sum(axis=1)).ravel()
        A = G / rows[:, None] * t[None, :] if dense else (sparse.diags(1.0 / rows) @ G @ sparse.diags(t)).tocsr()
    Sn = scaled(corr(v.corr_length or 1e-6), np.asarray(v.sigma, float) / t)
    if v.sigma_correction is not None:
        Sn = Sn + scaled(corr(v.correction_corr_length), np.asarray(v.sigma_correction, float) / t)
    Sb = scaled(corr(v.bias_corr_length), np.asarray(v.bias, float) / t) if v.bias is not None else zero()
    return A, Sn, Sb


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

    Notes
    -----
    A, S_n and S_b are block diagonal over the views; only the residual
    maker ``M = I - Q Q^T`` couples them, through Q's (N, p) rows. With
    ``B = A^T A`` per view, ``tr(A M S M^T A^T) = sum_v <B_v, S_v> - 2
    sum_v <S_v Q_v, B_v Q_v> + <sum_v Q_v^T S_v Q_v, sum_v Q_v^T B_v Q_v>``
    (``<X, Y>`` the elementwise product's sum), which needs no product of
    two wide matrices across views.
    """
    # One BLAS thread: the dense products' last bits then do not depend on the machine (vision.blas).
    with one_blas_thread():
        return _evidence(views, residuals, jacobian)


def _evidence(views, residuals, jacobian):
    if all(v.bias is None for v in views):
        return None
    Q, _ = np.linalg.qr(np.asarray(jacobian, float))
    residuals = np.asarray(residuals, float)
    p = Q.shape[1]
    observed, se2, start = 0.0, 0.0, 0
    direct = {"n": 0.0, "b": 0.0}
    cross = {"n": 0.0, "b": 0.0}
    small = {"n": np.zeros((p, p)), "b": np.zeros((p, p))}
    QBQ = np.zeros((p, p))
    for v in views:
        n = len(v.xy)
        Qv, ev = Q[start:start + n], residuals[start:start + n]
        start += n
        A, Sn, Sb = _view_operators(v)
        B = A.T @ A
        BQ = B @ Qv
        QBQ += Qv.T @ BQ
        observed += float(np.sum((A @ ev) ** 2))
        for key, S in (("n", Sn), ("b", Sb)):
            SQ = S @ Qv
            direct[key] += _hadamard_sum(B, S)
            cross[key] += float(np.sum(SQ * BQ))
            small[key] += Qv.T @ SQ
        # |A S_n A^T|_F^2 = tr(S_n B S_n B): one product of two wide matrices, not two.
        SnB = Sn @ B
        se2 += 2.0 * _hadamard_sum(SnB, SnB.T)
    En, Eb = (direct[k] - 2.0 * cross[k] + float(np.sum(small[k] * QBQ)) for k in ("n", "b"))
    if not Eb > 0:
        return None
    return (observed - En) / Eb, float(np.sqrt(se2)) / Eb

