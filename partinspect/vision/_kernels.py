"""Compiled inner loops of the 2D fits (Numba).

- :func:`lm_ellipse`: the damped Gauss-Newton iteration of
  :func:`partinspect.vision.fitting._lm_ellipses` for one point set, and
  :func:`foot_phases` and :func:`ellipse_geometry`, the foot points it
  starts from and ends with and the residuals, normals and rows there;
- :func:`band_sums`: the sums over the band of correlated point pairs of
  :func:`partinspect.vision.fitting.information_matrices`;
- :func:`circle_sampson`: the residuals of the 3D circle fit
  (:func:`partinspect.vision.fit3d.fit_circle_3d`), a dozen parameter
  vectors at a time for its numeric Jacobian.

Each is O(m) arithmetic on a few hundred points, which numpy spent mostly in
call overhead (a few hundred calls an iteration of the ellipse fit). The
algorithms and their notation are documented in those functions; this
module only carries them out, as loops over the points.

Imported where the fits run, not before (Numba's import is not free, and
the first call compiles, or loads the compiled code cached beside this
file).

References
----------
.. [1] Gander, W., Golub, G. H., Strebel, R. (1994). Least-squares fitting
       of circles and ellipses. BIT 34, 558-578.
.. [2] Transtrum, M. K., Sethna, J. P. (2012). Improvements to the
       Levenberg-Marquardt algorithm for nonlinear least-squares
       minimization. arXiv:1201.5885 (geodesic acceleration).
.. [3] Madsen, K., Nielsen, H. B., Tingleff, O. (2004). Methods for
       non-linear least squares problems, 2nd ed. IMM, DTU, section 3.2
       (the damping update from the gain ratio).
"""

import numpy as np
from numba import njit

# Step of the second directional derivative of the residuals, and largest
# ratio 2 |a| / |v| of the geodesic acceleration a to the step v: the values
# of Transtrum & Sethna [2]_.
ACCEL_H = 0.1
ACCEL_RATIO = 0.75

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def _residuals(p, phi, xy, out):
    """rho_i in the ellipse frame: Q(theta)^T (x_i - c) - (a cos, b sin); (m, 2)."""
    c, s = np.cos(p[4]), np.sin(p[4])
    for i in range(len(phi)):
        dx, dy = xy[i, 0] - p[0], xy[i, 1] - p[1]
        out[i, 0] = c * dx + s * dy - p[2] * np.cos(phi[i])
        out[i, 1] = -s * dx + c * dy - p[3] * np.sin(phi[i])


@njit(**_JIT)
def _system(p, phi, r, cparts, w, nil, k, H, rn, rt, X, G):
    """Weights, rows and the normal equations' parts at an iterate.

    Fills w (m), -1/|j| (m), k (m, 4: the normal and tangent times |j| in
    the ellipse frame), H (m, 10: the rows hn, ht), rn, rt (m), X = sum w
    H H^T (10, 10), G (10, 2) = sum w H (rn, rt); returns the cost.
    """
    a, b = p[2], p[3]
    c, s = np.cos(p[4]), np.sin(p[4])
    X[:] = 0.0
    G[:] = 0.0
    cost = 0.0
    h = np.empty(10)
    for i in range(len(phi)):
        cp, sp = np.cos(phi[i]), np.sin(phi[i])
        k0, k1, k2, k3 = b * cp, a * sp, a * sp, -b * cp
        k[i, 0], k[i, 1], k[i, 2], k[i, 3] = k0, k1, k2, k3
        j2 = k0 * k0 + k1 * k1
        q = -1.0 / np.sqrt(j2)
        nil[i] = q
        # Normal and tangent in the image frame, times |j|.
        n0, n1 = k0 * c - k1 * s, k0 * s + k1 * c
        t0, t1 = k2 * c - k3 * s, k2 * s + k3 * c
        wi = j2 / (n0 * n0 * cparts[i, 0] + n0 * n1 * cparts[i, 1] + n1 * n1 * cparts[i, 2])
        w[i] = wi
        h[0], h[1], h[5], h[6] = n0 * q, n1 * q, t0 * q, t1 * q
        h[2], h[3], h[7], h[8] = k0 * cp * q, k1 * sp * q, k2 * cp * q, k3 * sp * q
        h[4] = (a - b) * (a + b) * cp * sp * q
        h[9] = -a * b * q
        for j in range(10):
            H[i, j] = h[j]
        rni = -q * (k0 * r[i, 0] + k1 * r[i, 1])
        rti = -q * (k2 * r[i, 0] + k3 * r[i, 1])
        rn[i], rt[i] = rni, rti
        for j in range(10):
            wh = wi * h[j]
            G[j, 0] += wh * rni
            G[j, 1] += wh * rti
            for l in range(j, 10):
                X[j, l] += wh * h[l]
        cost += wi * (r[i, 0] * r[i, 0] + r[i, 1] * r[i, 1])
    for j in range(10):
        for l in range(j):
            X[j, l] = X[l, j]
    return cost


@njit(**_JIT)
def _solve(S, rhs):
    """S x = rhs for a 5 x 5 symmetric S: Cholesky, else the minimum-norm
    least-squares solution (eigenvalues below 1e-14 of the largest cut), else
    NaN (the step is then refused)."""
    n = 5
    L = np.zeros((n, n))
    ok = True
    for j in range(n):
        d = S[j, j]
        for l in range(j):
            d -= L[j, l] * L[j, l]
        if not d > 0.0:
            ok = False
            break
        L[j, j] = np.sqrt(d)
        for i in range(j + 1, n):
            v = S[i, j]
            for l in range(j):
                v -= L[i, l] * L[j, l]
            L[i, j] = v / L[j, j]
    x = np.empty(n)
    if ok:
        y = np.empty(n)
        for i in range(n):
            v = rhs[i]
            for l in range(i):
                v -= L[i, l] * y[l]
            y[i] = v / L[i, i]
        for i in range(n - 1, -1, -1):
            v = y[i]
            for l in range(i + 1, n):
                v -= L[l, i] * x[l]
            x[i] = v / L[i, i]
        return x
    for i in range(n):
        for j in range(n):
            if not np.isfinite(S[i, j]):
                x[:] = np.nan
                return x
    ev, V = np.linalg.eigh(S)
    big = np.abs(ev).max() * 1e-14
    proj = V.T @ rhs
    for i in range(n):
        proj[i] = proj[i] / ev[i] if abs(ev[i]) > big else 0.0
    return V @ proj


@njit(**_JIT)
def _step(X, Cd, lam, Gn, Gt, rt, H, nil, du, dphi):
    """Damped step (du, dphi) for the right-hand side parts Gn, Gt, rt."""
    kk = lam / (1.0 + lam)
    S = np.empty((5, 5))
    rhs = np.empty(5)
    for i in range(5):
        for j in range(5):
            S[i, j] = X[i, j] + kk * X[5 + i, 5 + j]
        S[i, i] += lam * Cd[i]
        rhs[i] = -(Gn[i] + kk * Gt[i])
    x = _solve(S, rhs)
    du[:] = x
    f = 1.0 / (1.0 + lam)
    for i in range(len(rt)):
        v = rt[i]
        for j in range(5):
            v += H[i, 5 + j] * x[j]
        dphi[i] = v * nil[i] * f


@njit(**_JIT)
def _newton_decrement(X, Cd, Gn):
    """du^T Sn du for the undamped step du = -Sn^-1 Gn (a ridge of 1e-12
    diag(Sn + St) for the free theta of a circle)."""
    S = np.empty((5, 5))
    rhs = np.empty(5)
    for i in range(5):
        for j in range(5):
            S[i, j] = X[i, j]
        S[i, i] += 1e-12 * Cd[i]
        rhs[i] = -Gn[i]
    x = _solve(S, rhs)
    return max(-(x @ Gn), 0.0)


@njit(**_JIT)
def lm_ellipse(xy, cparts, p0, phi0, max_iter, tol, sigma_tol, bound):
    """Damped Gauss-Newton ellipse fit of one point set.

    Parameters
    ----------
    xy : ndarray, shape (m, 2)
        Points, px.
    cparts : ndarray, shape (m, 3)
        Parts of each point's variance along a unit normal n,
        (n_x^2, n_x n_y, n_y^2) coefficients: cov_xx, cov_xy + cov_yx, cov_yy.
    p0 : ndarray, shape (5,)
        Start (xc, yc, a, b, theta).
    phi0 : ndarray, shape (m,)
        Start phases, rad.
    max_iter : int
    tol : float
        Pixel tolerance of the accepted step (fraction of max(1, a)); < 0: none.
    sigma_tol : float
        Newton-decrement tolerance in standard uncertainties; < 0: none.
    bound : float
        Largest semi-major axis (np.inf: none).

    Returns
    -------
    p : ndarray, shape (5,)
    converged : bool
    iterations : int
    """
    m = len(phi0)
    p = p0.copy()
    phi = phi0.copy()
    r = np.empty((m, 2))
    _residuals(p, phi, xy, r)
    w, nil, rn, rt = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    k, H = np.empty((m, 4)), np.empty((m, 10))
    X, G = np.empty((10, 10)), np.empty((10, 2))
    Cd = np.empty(5)
    du, dphi, au, aphi = np.empty(5), np.empty(m), np.empty(5), np.empty(m)
    jn, jt, rn2, rt2 = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    Gn2, Gt2 = np.empty(5), np.empty(5)
    p_new, phi_new, r_new = np.empty(5), np.empty(m), np.empty((m, 2))
    p_h, phi_h, r_h = np.empty(5), np.empty(m), np.empty((m, 2))
    lam, nu = 1e-3, 2.0
    h = ACCEL_H
    for it in range(1, max_iter + 1):
        cost = _system(p, phi, r, cparts, w, nil, k, H, rn, rt, X, G)
        Gn, Gt = G[:5, 0].copy(), G[5:, 1].copy()
        for i in range(5):
            Cd[i] = X[i, i] + X[5 + i, 5 + i]
        if sigma_tol >= 0.0 and _newton_decrement(X, Cd, Gn) <= sigma_tol * sigma_tol:
            return p, True, it - 1
        p_before = p.copy()
        done, converged = False, False
        while True:
            # The damped Gauss-Newton step v and the model's change of the
            # residuals along it, J v (normal and tangent parts).
            _step(X, Cd, lam, Gn, Gt, rt, H, nil, du, dphi)
            for i in range(m):
                vn, vt = 0.0, 0.0
                for j in range(5):
                    vn += H[i, j] * du[j]
                    vt += H[i, 5 + j] * du[j]
                jn[i] = vn
                jt[i] = vt - dphi[i] / nil[i]
            # Geodesic acceleration [2]_: the second directional derivative
            # of the residuals along v by a forward difference, from the
            # residuals at x + h v turned into the current iterate's frame.
            for j in range(5):
                p_h[j] = p[j] + h * du[j]
            for i in range(m):
                phi_h[i] = phi[i] + h * dphi[i]
            _residuals(p_h, phi_h, xy, r_h)
            cd, sd = np.cos(p_h[4] - p[4]), np.sin(p_h[4] - p[4])
            for j in range(5):
                Gn2[j] = 0.0
                Gt2[j] = 0.0
            for i in range(m):
                m0 = cd * r_h[i, 0] - sd * r_h[i, 1]
                m1 = sd * r_h[i, 0] + cd * r_h[i, 1]
                mn = -nil[i] * (k[i, 0] * m0 + k[i, 1] * m1)
                mt = -nil[i] * (k[i, 2] * m0 + k[i, 3] * m1)
                rn2[i] = (2.0 / h) * ((mn - rn[i]) / h - jn[i])
                rt2[i] = (2.0 / h) * ((mt - rt[i]) / h - jt[i])
                for j in range(5):
                    Gn2[j] += w[i] * H[i, j] * rn2[i]
                    Gt2[j] += w[i] * H[i, 5 + j] * rt2[i]
            _step(X, Cd, lam, Gn2, Gt2, rt2, H, nil, au, aphi)
            # Norms scaled by the damping's diagonal; the decrease of the
            # cost the linearised model predicts for v.
            dd, aa, pred = 0.0, 0.0, cost
            for j in range(5):
                dd += Cd[j] * du[j] * du[j]
                aa += Cd[j] * au[j] * au[j]
            for i in range(m):
                wj = w[i] / (nil[i] * nil[i])
                dd += wj * dphi[i] * dphi[i]
                aa += wj * aphi[i] * aphi[i]
                en, et = rn[i] + jn[i], rt[i] + jt[i]
                pred -= w[i] * (en * en + et * et)
            acc_ok = 4.0 * aa <= (ACCEL_RATIO * ACCEL_RATIO) * dd
            for j in range(5):
                p_new[j] = p[j] + du[j] + 0.5 * au[j]
            for i in range(m):
                phi_new[i] = phi[i] + dphi[i] + 0.5 * aphi[i]
            _residuals(p_new, phi_new, xy, r_new)
            # The cost with the weights of the current iterate.
            f1 = 0.0
            for i in range(m):
                f1 += w[i] * (r_new[i, 0] * r_new[i, 0] + r_new[i, 1] * r_new[i, 1])
            acc = acc_ok and p_new[2] > 0 and p_new[3] > 0 and f1 <= cost * (1 + 1e-12)
            if acc:
                step = du + 0.5 * au
                if tol >= 0.0:
                    moved = np.abs(step[:4]).sum() + abs(p[2] - p[3]) * abs(step[4])
                    converged = moved < tol * max(1.0, p[2])
                done = True
                p[:] = p_new
                phi[:] = phi_new
                r[:] = r_new
                gain = min(max((cost - f1) / max(pred, 1e-300), 0.0), 1.0)
                lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), 1e-12)
                nu = 2.0
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e12:
                break
        size = max(p[2], p[3])
        beyond = size > bound and size > max(p_before[2], p_before[3])
        if not done or converged or beyond or it == max_iter:
            return (p_before if beyond else p), done and converged and not beyond, it
    return p, False, max_iter


@njit(**_JIT)
def foot_phases(xy, params, phi, iters, start):
    """Phases of the orthogonal foot points, Newton on each point (in place),
    at most ``iters`` steps, a point stopping once its step is below 1e-13
    rad; with ``start`` the phases given are replaced first by the points'
    angles scaled to the ellipse."""
    xc, yc, a, b, th = params[0], params[1], params[2], params[3], params[4]
    c, s = np.cos(th), np.sin(th)
    for i in range(len(phi)):
        dx, dy = xy[i, 0] - xc, xy[i, 1] - yc
        u, v = c * dx + s * dy, -s * dx + c * dy
        f_phi = np.arctan2(v * a, u * b) if start else phi[i]
        for _ in range(iters):
            cp, sp = np.cos(f_phi), np.sin(f_phi)
            ex, ey = a * cp, b * sp
            tx, ty = -a * sp, b * cp
            f = (u - ex) * tx + (v - ey) * ty
            fp = -(tx * tx + ty * ty) - (u - ex) * ex - (v - ey) * ey
            if abs(fp) < 1e-12:
                fp = -1e-12
            d = f / min(fp, -1e-12)
            f_phi -= d
            if abs(d) < 1e-13:
                break
        phi[i] = f_phi
    return phi


@njit(**_JIT)
def ellipse_geometry(xy, params, phi):
    """Residuals r (m), outward unit normals n (m, 2) and rows h (m, 5) at
    the foot points (see :func:`partinspect.vision.fitting.ellipse_geometry`)."""
    xc, yc, a, b, th = params[0], params[1], params[2], params[3], params[4]
    c, s = np.cos(th), np.sin(th)
    m = len(phi)
    r, n, h = np.empty(m), np.empty((m, 2)), np.empty((m, 5))
    for i in range(m):
        cp, sp = np.cos(phi[i]), np.sin(phi[i])
        lx, ly = b * cp, a * sp
        ln = np.sqrt(lx * lx + ly * ly)
        lx, ly = lx / ln, ly / ln
        nx, ny = c * lx - s * ly, s * lx + c * ly
        ex = xc + c * (a * cp) - s * (b * sp)
        ey = yc + s * (a * cp) + c * (b * sp)
        r[i] = (xy[i, 0] - ex) * nx + (xy[i, 1] - ey) * ny
        n[i, 0], n[i, 1] = nx, ny
        h[i, 0], h[i, 1] = -nx, -ny
        h[i, 2] = -lx * cp
        h[i, 3] = -ly * sp
        h[i, 4] = b * sp * lx - a * cp * ly
    return r, n, h


@njit(**_JIT)
def band_sums(xy, corr_length, hw):
    """Sums over the band of correlated pairs (i, (i + k) mod n), k = 1 ..
    n // 2, with rho = exp(-d^2 / (4 corr_length^2)) (halved for k = n - k,
    the same pair seen twice); the band ends before the first k whose rho
    are all below 1e-4.

    Parameters
    ----------
    xy : ndarray, shape (n, 2)
    corr_length : float
    hw : ndarray, shape (n, p)
        Weighted rows (p = 0: only the second sum).

    Returns
    -------
    C : ndarray, shape (p, p)
        sum over the band of rho hw_i^T hw_(i+k).
    rho2 : float
        sum over the band of rho^2.
    """
    n, q = xy.shape[0], hw.shape[1]
    C = np.zeros((q, q))
    rho2 = 0.0
    scale = -1.0 / (4.0 * corr_length * corr_length)
    rho = np.empty(n)
    for k in range(1, n // 2 + 1):
        top = 0.0
        for i in range(n):
            j = i + k
            if j >= n:
                j -= n
            dx, dy = xy[j, 0] - xy[i, 0], xy[j, 1] - xy[i, 1]
            r = np.exp((dx * dx + dy * dy) * scale)
            if k == n - k:
                r *= 0.5
            rho[i] = r
            top = max(top, r)
        if top < 1e-4:
            break
        for i in range(n):
            j = i + k
            if j >= n:
                j -= n
            r = rho[i]
            rho2 += r * r
            for a in range(q):
                ra = r * hw[i, a]
                for b in range(q):
                    C[a, b] += ra * hw[j, b]
    return C, rho2


@njit(**_JIT)
def circle_sampson(thetas, n0, e1, e2, P, xy, sig):
    """Sampson distances of image points to the images of 3D circles.

    Parameters
    ----------
    thetas : ndarray, shape (k, 6)
        Centre (mm), the normal's offsets along e1, e2 from n0, radius (mm).
    n0, e1, e2 : ndarray, shape (3,)
        The normal the offsets are taken from and the two axes completing it.
    P : ndarray, shape (3, 4)
        Camera matrix.
    xy : ndarray, shape (N, 2)
        Image points, px.
    sig : ndarray, shape (N,)
        Their standard uncertainties, px.

    Returns
    -------
    ndarray, shape (k, N)
        The algebraic residual x^T C x over its gradient's norm, over sig,
        with C the circle's image conic as
        :func:`partinspect.vision.fit3d.circle_image_conic` makes it.
    """
    k, N = thetas.shape[0], xy.shape[0]
    out = np.empty((k, N))
    M = np.zeros((4, 3))
    for row in range(k):
        t = thetas[row]
        n = n0 + t[3] * e1 + t[4] * e2
        n = n / np.sqrt(n @ n)
        a = np.zeros(3)
        if abs(n[0]) >= 0.9:
            a[1] = 1.0
        else:
            a[0] = 1.0
        u = np.array([n[1] * a[2] - n[2] * a[1], n[2] * a[0] - n[0] * a[2], n[0] * a[1] - n[1] * a[0]])
        u = u / np.sqrt(u @ u)
        v = np.array([n[1] * u[2] - n[2] * u[1], n[2] * u[0] - n[0] * u[2], n[0] * u[1] - n[1] * u[0]])
        # Homography plane (x, y, 1) -> image: columns P (u, 0), P (v, 0), P (c, 1).
        M[:3, 0], M[:3, 1], M[:3, 2], M[3, 2] = u, v, t[:3], 1.0
        Hinv = np.linalg.inv(P @ M)
        D = np.diag(np.array([1.0, 1.0, -t[5] * t[5]]))
        C = Hinv.T @ D @ Hinv
        C = C / np.sqrt((C * C).sum())
        for i in range(N):
            x, y = xy[i, 0], xy[i, 1]
            c0 = C[0, 0] * x + C[0, 1] * y + C[0, 2]
            c1 = C[1, 0] * x + C[1, 1] * y + C[1, 2]
            c2 = C[2, 0] * x + C[2, 1] * y + C[2, 2]
            out[row, i] = (c0 * x + c1 * y + c2) / (2.0 * np.sqrt(c0 * c0 + c1 * c1)) / sig[i]
    return out


def warm():
    """Compile the kernels (or load them from the cache beside this file) now.

    The first call of each compiles it, which takes a while on a fresh
    install, after that it only loads: the install script calls this once,
    and a caller about to fork
    (:func:`partinspect.vision.stereo.measure_stereo`) calls it first, so
    that the child inherits the loaded code.
    """
    t = np.linspace(0.0, 6.0, 12)
    xy = np.ascontiguousarray(np.c_[10.0 * np.cos(t), 6.0 * np.sin(t)])
    p = np.array([0.0, 0.0, 10.0, 6.0, 0.0])
    phi = foot_phases(xy, p, t.copy(), 6, True)
    ellipse_geometry(xy, p, phi)
    lm_ellipse(xy, np.tile([1.0, 0.0, 1.0], (12, 1)), p, phi, 2, 1e-9, 0.1, np.inf)
    band_sums(xy, 1.0, np.ones((12, 5)))
    band_sums(xy, 1.0, np.ones((12, 0)))
    P = np.c_[np.eye(3), [0.0, 0.0, 1.0]]
    circle_sampson(np.array([[0.0, 0.0, 100.0, 0.0, 0.0, 5.0]]), np.array([0.0, 0.0, 1.0]),
                   np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), P, xy, np.ones(12))
