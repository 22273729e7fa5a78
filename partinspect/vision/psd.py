"""Square roots of covariance matrices that hold where a covariance is ill-conditioned.

A fit's parameter covariance can span ten orders of magnitude (an ellipse
fitted to a short arc: its centre and axes almost free along one
combination, well fixed along the others). Such a matrix carries only
about ``eps * cond`` relative precision, and its last digits are whatever
the processor's rounding made them: computed as a sandwich it is not even
exactly symmetric. Propagated as ``J C J^T`` into quantities the data do
fix, those digits decide the result, down to a negative variance. Every
propagation and every simulation of such a covariance goes through one
factor ``L`` with ``L L^T`` the nearest positive semi-definite matrix to
its symmetric part, so that what is propagated and what is drawn agree and
no variance is negative.

References
----------
.. [1] Higham, N. J. (1988). Computing a nearest symmetric positive
       semidefinite matrix. Linear Algebra and its Applications 103,
       103-118 (the eigenvalue clipping of the symmetric part).
.. [2] JCGM 101:2008, 6.4.8.4 (drawing from a multivariate Gaussian through
       a factor of its covariance).
"""

import numpy as np

__all__ = ["covariance_factor"]


def covariance_factor(C):
    """A factor ``L`` with ``L L^T`` the nearest PSD matrix to the symmetric part of ``C``.

    Parameters
    ----------
    C : array_like, shape (k, k)
        A covariance, any units; finite.

    Returns
    -------
    L : ndarray, shape (k, k)
        ``V sqrt(max(w, 0))`` from the eigen-decomposition ``(C + C^T) / 2
        = V diag(w) V^T``: negative eigenvalues, which only rounding makes,
        are set to 0.
    """
    C = np.asarray(C, float)
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return V * np.sqrt(np.clip(w, 0.0, None))
