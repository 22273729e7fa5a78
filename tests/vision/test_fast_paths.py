"""The fast paths of the fits agree with the plain numpy forms they replace."""

import cv2
import numpy as np
import pytest

from partinspect.vision import _kernels, noise
from partinspect.vision.correspondences import intersect_ellipse, intersect_line
from partinspect.frames import plane_basis
from partinspect.vision.fit3d import circle_image_conic
from partinspect.vision.fitting import (
    EllipseJob,
    _line_tls,
    _pinv_sym,
    ellipse_points,
    ellipse_with_covariance,
    fit_ellipse,
    fit_ellipses,
    fit_line,
    line_with_covariance,
)
from partinspect.vision.rim_errors import smoothed_background


def test_small_symmetric_solvers_match_numpy():
    rng = np.random.default_rng(0)
    for rank in (5, 4):
        A = rng.normal(size=(5, rank))
        S = A @ A.T  # rank-deficient for rank 4, as a circle's theta column
        b = S @ rng.normal(size=5)
        assert np.allclose(_pinv_sym(S, 1e-13), np.linalg.pinv(S, rcond=1e-13, hermitian=True), atol=1e-10)
        if rank == 5:
            assert np.allclose(_kernels._solve(S, b), np.linalg.solve(S, b), rtol=1e-9, atol=0)
    # The fit's solver falls back to the minimum-norm solution where Cholesky
    # fails (a zero pivot: theta's column of a circle without damping).
    A = rng.normal(size=(5, 5))
    A[4] = 0.0
    S = A @ A.T
    b = S @ rng.normal(size=5)
    assert np.allclose(_kernels._solve(S, b), np.linalg.lstsq(S, b, rcond=1e-14)[0], atol=1e-8)
    assert np.all(np.isnan(_kernels._solve(np.full((5, 5), np.nan), b)))


def test_line_tls_closed_form_matches_svd():
    rng = np.random.default_rng(1)
    t = np.linspace(-50, 50, 200)
    xy = np.c_[3 + 0.8 * t, -2 + 0.6 * t] + rng.normal(0, 0.05, (200, 2))
    w = rng.uniform(0.5, 2.0, 200)
    n, c = _line_tls(xy, w)
    d = (xy - c) * np.sqrt(w)[:, None]
    ref = np.linalg.svd(d)[2][-1]
    assert abs(abs(n @ ref) - 1) < 1e-12


def test_ellipse_start_values_reach_the_same_minimum():
    rng = np.random.default_rng(2)
    phi = np.linspace(0.3, 2.5, 150)
    xy = ellipse_points([400, 300, 80, 50, 0.4], phi) + rng.normal(0, 0.05, (150, 2))
    cov = np.broadcast_to(0.0025 * np.eye(2), (150, 2, 2))
    a = fit_ellipse(xy, cov, corr_length=1.0)
    b = fit_ellipse(xy, cov, corr_length=1.0, start=a.params + [0.5, -0.3, 1.0, -0.5, 0.01])
    assert a.converged and b.converged
    u = np.sqrt(np.diag(a.cov))
    assert np.all(np.abs(a.params - b.params) < 1e-4 * u)
    assert np.allclose(a.cov, b.cov, rtol=1e-4, atol=0)


def test_smoothed_background_matches_dense_form():
    rng = np.random.default_rng(3)
    phi = np.linspace(0, 4, 300)
    xy = np.c_[60 * np.cos(phi), 40 * np.sin(phi)]
    values = rng.normal(size=(300, 3))
    std = rng.uniform(0.01, 0.1, 300)
    d2 = ((xy[:, None, :] - xy[None, :, :]) ** 2).sum(-1)
    w = np.exp(-d2 / 8.0)
    w /= w.sum(axis=1, keepdims=True)
    rho = np.exp(-d2 / 4.0)
    a = w * std[None, :]
    var = ((a @ rho) * a).sum(axis=1)
    mean, sd = smoothed_background(xy, values, std, 1.0, 2.0)
    assert np.allclose(mean, w @ values, rtol=0, atol=1e-12)
    assert np.allclose(sd, np.sqrt(var), rtol=1e-10)


def test_fits_without_covariance_completed_are_the_full_fits():
    # The segmentation's tests skip the covariances; completed, a fit is
    # exactly what fit_line / fit_ellipse return.
    rng = np.random.default_rng(3)
    t = np.linspace(-40, 40, 120)
    xy = np.c_[10 + 0.6 * t, 5 - 0.8 * t] + rng.normal(0, 0.05, (120, 2))
    cov = np.broadcast_to(0.0025 * np.eye(2), (120, 2, 2)) + np.diag([1e-4, 0.0])
    full = fit_line(xy, cov, corr_length=1.0)
    bare = fit_line(xy, cov, corr_length=1.0, with_cov=False)
    assert bare.cov is None and bare.consistency == full.consistency
    done = line_with_covariance(bare, xy, 1.0)
    for name in ("params", "cov", "cov_angle_offset", "ci95", "residuals", "point_std", "centroid"):
        assert np.array_equal(getattr(done, name), getattr(full, name)), name

    xy = ellipse_points([400, 300, 80, 50, 0.4], np.linspace(0.3, 4.0, 200)) + rng.normal(0, 0.05, (200, 2))
    cov = np.broadcast_to(0.0025 * np.eye(2), (200, 2, 2))
    full = fit_ellipse(xy, cov, corr_length=1.0)
    bare, = fit_ellipses([EllipseJob(xy, cov, 1.0)], with_cov=False)
    assert bare.cov is None and bare.consistency == full.consistency
    done = ellipse_with_covariance(bare, xy, 1.0)
    for name in ("params", "cov", "ci95", "residuals", "phases", "point_std"):
        assert np.array_equal(getattr(done, name), getattr(full, name)), name
    # With blur the fits before the last correction have no covariance; the result is the same.
    blurred = fit_ellipse(xy, cov, corr_length=1.0, blur=1.2)
    assert blurred.cov is not None and np.all(np.isfinite(blurred.cov[:4, :4]))


def test_compiled_circle_residuals_match_the_conics_one_by_one():
    rng = np.random.default_rng(4)
    P = np.c_[np.diag([7000.0, 7000.0, 1.0]), [10.0, -5.0, 1.0]]
    n0 = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    e1, e2 = plane_basis(n0).T
    thetas = np.c_[rng.normal(0, 20, (12, 3)) + [0, 0, 400], rng.normal(0, 0.3, (12, 2)), rng.uniform(2, 10, 12)]
    thetas[0, 3:5] = [8.0, 0.5]  # a normal near the first helper axis: the other one is used
    xy = rng.normal(0, 150, (40, 2))
    sig = rng.uniform(0.01, 0.05, 40)
    got = _kernels.circle_sampson(thetas, n0, e1, e2, P, xy, sig)
    for t, row in zip(thetas, got):
        C = circle_image_conic(t[:3], n0 + t[3] * e1 + t[4] * e2, t[5], P)
        x = np.c_[xy, np.ones(40)]
        Cx = x @ C.T
        ref = np.einsum("ni,ni->n", x, Cx) / (2 * np.hypot(Cx[:, 0], Cx[:, 1])) / sig
        assert np.allclose(row, ref, rtol=1e-9, atol=1e-12)


def test_intersections_with_one_curve_per_line_match_one_curve_for_all():
    rng = np.random.default_rng(5)
    lines = np.c_[rng.normal(size=(50, 2)), rng.normal(0, 300, 50)]
    ell = np.array([[5.0, -3.0, 200.0, 120.0, 0.3], [0.0, 10.0, 150.0, 149.0, -1.2]])
    lin = np.array([[0.6, 0.8, -20.0], [-0.8, 0.6, 5.0]])
    for params, f in ((ell, intersect_ellipse), (lin, intersect_line)):
        rows = f(np.tile(lines, (2, 1)), np.repeat(params, 50, axis=0))
        each = [f(lines, p) for p in params]
        for k, part in enumerate(rows):
            ref = np.concatenate([e[k] for e in each])
            assert np.allclose(part, ref, rtol=1e-13, atol=1e-9, equal_nan=True)


def _noise_whole_image(image, clip=3.0, edge_k=4.0, iterations=3):
    """estimate_noise as it was: every map over the whole image, subsampled after, all iterations run."""
    img = np.asarray(image)
    top = np.iinfo(img.dtype).max if np.issubdtype(img.dtype, np.integer) else None
    f = img.astype(np.float32)
    resp = cv2.filter2D(f, cv2.CV_32F, noise._MASK, borderType=cv2.BORDER_REFLECT)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
    grad_max = cv2.dilate(cv2.magnitude(gx, gy), np.ones((3, 3), np.uint8))
    step = max(1, int(np.sqrt(resp.size / 4e5)))
    sub = (slice(1, -1, step), slice(1, -1, step))
    resp, grad_max = resp[sub], grad_max[sub]
    valid = np.ones(resp.shape, bool)
    if top is not None:
        sat = ((img == 0) | (img == top)).astype(np.uint8)
        valid &= cv2.dilate(sat, np.ones((3, 3), np.uint8))[sub] == 0
    r = resp[valid]
    sigma = float(np.median(np.abs(r))) / 0.6744897501960817 / noise._MASK_NORM
    if sigma == 0.0 and top is None:
        sigma = float(np.sqrt(np.mean(r * r))) / noise._MASK_NORM
    for _ in range(iterations):
        r = resp[valid & ~(grad_max > edge_k * np.sqrt(12.0) * max(sigma, 1e-3))]
        if r.size < 100:
            break
        r2 = (r * r).astype(np.float64)
        for _ in range(5):
            sel = r2[r2 < (clip * noise._MASK_NORM * sigma) ** 2]
            if sel.size == 0:
                break
            sigma = float(np.sqrt(sel.mean() / noise._truncated_variance_factor(clip))) / noise._MASK_NORM
    return max(sigma, noise.QUANTISATION_STD) if top is not None else sigma


@pytest.mark.parametrize("shape", [(3, 3), (7, 9), (480, 640), (1301, 997), (2048, 2448)])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
def test_noise_from_the_kept_pixels_only_is_the_same(shape, dtype):
    # estimate_noise takes the 3x3 maxima only around the subsample it keeps
    # and stops iterating once the kept responses stop changing: the same
    # value, bit for bit, as filtering the whole image and running every
    # iteration. Edges, saturated pixels and shading included.
    rng = np.random.default_rng(sum(shape))
    y, x = np.mgrid[0:shape[0], 0:shape[1]]
    img = 90 + 0.02 * x + 100 * ((x - shape[1] / 2) ** 2 + (y - shape[0] / 2) ** 2 < (min(shape) / 3) ** 2)
    img = img + rng.normal(0, 2.0, shape)
    if min(shape) > 10:  # (a tiny image with one saturated pixel has no other)
        img[rng.random(shape) < 0.01] = 255
        img[rng.random(shape) < 0.01] = 0
    if np.issubdtype(dtype, np.integer):
        img = np.rint(img) * (257 if dtype == np.uint16 else 1)
    img = img.astype(dtype)
    for step in (1, 2, 3, 5):
        a = rng.normal(size=shape).astype(np.float32)
        ref = cv2.dilate(a, np.ones((3, 3), np.uint8))[1:-1:step, 1:-1:step]
        assert np.array_equal(noise._max3x3_at(a, step), ref)
    assert noise.estimate_noise(img) == _noise_whole_image(img)


def test_pair_fits_shared_by_cost_not_by_turn():
    from partinspect.vision.stereo import _halves

    # The plate's pairs' fit times, ms (rims first, then lines), as a profile gave them.
    costs = [65.2, 44.5, 34.7, 21.8, 14.6, 13.1, 11.7, 7.1, 7.0, 5.8, 4.7, 4.4, 3.6, 3.5, 3.4, 2.9, 2.8]
    here, there = _halves(costs)
    assert sorted(here + there) == list(range(len(costs)))
    assert here == sorted(here) and there == sorted(there)
    split = sorted(sum(costs[i] for i in share) for share in (here, there))
    alternate = sorted((sum(costs[0::2]), sum(costs[1::2])))
    assert split[1] - split[0] <= max(costs[len(costs) // 2:])  # within one small job of even
    assert split[1] < alternate[1] - 10.0


def test_median_from_lattice_counts_is_numpys():
    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 10, 1001):
        for scale, dtype in ((1.0, np.float32), (9.0, np.float32), (1.0, np.float64)):
            x = (rng.integers(0, 300, n) / scale).astype(dtype)
            lattice = noise._levels(x, scale)
            assert lattice is not None and np.array_equal(lattice[1][lattice[0]], x)
            got, ref = noise._median(x, lattice), np.median(x)
            assert got == ref and got.dtype == ref.dtype
    # Off the lattice (a float image), NaN, or too many levels: no lattice, numpy's own median.
    assert noise._levels(rng.normal(size=100).astype(np.float32) + 10, 1.0) is None
    assert noise._levels(np.array([1.0, np.nan]), 1.0) is None
    assert noise._levels(np.array([0.0, float(noise.MAX_LEVELS)]), 1.0) is None


def test_noise_bins_stop_iterating_once_settled():
    # Each bin's truncated second moment stops once its kept responses
    # stop changing: the same variances as running all five iterations.
    rng = np.random.default_rng(8)
    grey = rng.uniform(20, 230, 60000)
    resp = rng.normal(size=grey.size) * 6 * np.sqrt(1 + 0.04 * grey)
    resp[rng.random(grey.size) < 0.02] *= 20  # edge pixels let through
    resp = resp.astype(np.float32)
    edges = np.unique(np.quantile(grey, np.linspace(0, 1, 13)))
    idx = np.clip(np.searchsorted(edges, grey, side="right") - 1, 0, len(edges) - 2)
    ref = []
    for k in range(len(edges) - 1):
        r2 = (resp[idx == k].astype(np.float64) / noise._MASK_NORM) ** 2
        var = float(np.median(r2)) / 0.4549364231195724
        for _ in range(5):
            var = float(r2[r2 < 9.0 * var].mean() / noise._truncated_variance_factor(3.0))
        ref.append(var)
    assert np.array_equal(noise._bin_variances(resp, grey, 12)[:, 2], ref)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_noise_level_read_from_counts_is_the_same(dtype, monkeypatch):
    # The medians and grey bins read off the responses' and means' lattice
    # give the noise level function bit for bit, grey-dependent noise,
    # edges and saturation included; a float image takes the plain path.
    rng = np.random.default_rng(11)
    y, x = np.mgrid[0:600, 0:800]
    clean = 20 + 0.25 * x + 120 * ((x - 400) ** 2 + (y - 300) ** 2 < 150 ** 2)
    img = clean + rng.normal(size=clean.shape) * np.sqrt(1.0 + 0.05 * clean)
    img[rng.random(img.shape) < 0.002] = 255
    if dtype == np.uint16:
        img = img * 7
    img = np.clip(np.rint(img) if dtype != np.float32 else img, 0, None).astype(dtype)
    filtered = noise._filtered(img)
    resp = noise._grid(img, filtered, 3)[0]
    assert (noise._levels(np.abs(resp).ravel(), 1.0) is None) == (dtype == np.float32)
    fast = noise.noise_level_function(img)
    assert fast.signal_dependent
    monkeypatch.setattr(noise, "_levels", lambda x, scale: None)
    assert noise.noise_level_function(img) == fast


def test_smoothing_operators_are_built_once_per_edge():
    from partinspect.vision import rim_errors

    t = np.linspace(0.0, 5.0, 400)
    xy = np.c_[300 + 80 * np.cos(t), 200 + 50 * np.sin(t)]
    w, rho = rim_errors.smoothing_operators(xy, 1.0, rim_errors.BACKGROUND_SMOOTHING)
    # The pair's fit asks again with its own copy of the points: the same matrices, not built again.
    again = rim_errors.smoothing_operators(xy.copy(), 1.0, rim_errors.BACKGROUND_SMOOTHING)
    assert again[0] is w and again[1] is rho
    fresh = rim_errors._smoothing_operators(xy, 1.0, rim_errors.BACKGROUND_SMOOTHING)
    assert all((a != b).nnz == 0 for a, b in zip((w, rho), fresh))
    moved = xy + np.array([1e-9, 0.0])
    assert rim_errors.smoothing_operators(moved, 1.0, rim_errors.BACKGROUND_SMOOTHING)[0] is not w
    assert rim_errors.smoothing_operators(xy, 1.5, rim_errors.BACKGROUND_SMOOTHING)[0] is not w
    for k in range(rim_errors.OPERATORS_KEPT + 5):
        rim_errors.smoothing_operators(xy[: 50 + k], 1.0, 2.0)
    assert len(rim_errors._operators) == rim_errors.OPERATORS_KEPT


def test_grey_bins_from_counts_select_on_sorted_levels(monkeypatch):
    # The bins' quantiles are read from the grey levels laid out in order by
    # their counts (selection on sorted data): the same bins and variances
    # as numpy's quantile of the unsorted means, bit for bit.
    rng = np.random.default_rng(3)
    grey = (rng.integers(0, 2296, 40000) / 9.0).astype(np.float32)
    grey[:9000] = grey[0]  # a level that fills more than one bin: fewer, merged bins
    resp = rng.integers(-60, 61, grey.size).astype(np.float32)
    lattices = noise._levels(np.abs(resp), 1.0), noise._levels(grey, 9.0)
    plain = noise._bin_variances(resp, grey, 12)
    seen = []
    quantile = np.quantile
    monkeypatch.setattr(np, "quantile", lambda a, q: seen.append(bool(np.all(np.diff(a) >= 0))) or quantile(a, q))
    fast = noise._bin_variances(resp, grey, 12, *lattices)
    assert seen == [True]
    assert fast.shape == plain.shape and fast.shape[0] < 12 and fast.tobytes() == plain.tobytes()
