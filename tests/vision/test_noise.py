import numpy as np
import pytest

from partinspect.vision.noise import estimate_noise
from tests.vision.synthetic import Disc, rectangle, render, render_optics

SHAPES = [(rectangle(150, 120, 180, 140, 0.3), 200.0), (Disc(150, 120, 40), 60.0), (Disc(80, 70, 15), 120.0)]


@pytest.fixture(scope="module")
def clean():
    return render_optics(SHAPES, 240, 300)


@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.0, 4.0, 8.0])
def test_noise_within_10_percent(clean, sigma):
    img = render(SHAPES, 240, 300, noise=sigma, seed=int(sigma * 10), clean=clean)
    # The 8-bit pixels carry the quantisation noise too (variance 1/12).
    truth = np.sqrt(sigma ** 2 + 1.0 / 12.0)
    assert estimate_noise(img) == pytest.approx(truth, rel=0.05)


def test_not_fooled_by_edges(clean):
    # Many strong edges, little noise: a plain MAD of the Laplacian would
    # read the edges as noise.
    stripes = np.kron((np.arange(30) % 2)[None, :] * 150.0 + 50.0, np.ones((240, 10)))
    rng = np.random.default_rng(3)
    img = np.clip(np.rint(stripes + rng.normal(0, 1.0, stripes.shape)), 0, 255).astype(np.uint8)
    assert estimate_noise(img) == pytest.approx(np.sqrt(1 + 1 / 12), rel=0.1)


def test_smooth_shading_is_not_noise():
    y, x = np.mgrid[0:200, 0:200].astype(float)
    img = 60 + 0.3 * x + 0.002 * (y - 100) ** 2
    rng = np.random.default_rng(4)
    noisy = img + rng.normal(0, 2.0, img.shape)
    assert estimate_noise(noisy) == pytest.approx(2.0, rel=0.05)


def test_colour_and_float_input():
    rng = np.random.default_rng(5)
    grey = 100 + rng.normal(0, 3.0, (120, 160))
    assert estimate_noise(grey) == pytest.approx(3.0, rel=0.05)
    col = np.repeat(np.clip(np.rint(grey), 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    assert estimate_noise(col) == pytest.approx(np.sqrt(9 + 1 / 12), rel=0.06)


def test_noise_free_8bit_image_reads_its_rounding(clean):
    # Flat areas of a noise-free 8-bit image round alike and read as zero
    # noise; the edge pixels still carry the rounding error, and a zero
    # estimate would give edge points zero uncertainty (the chain then failed).
    img = render(SHAPES, 240, 300, noise=0.0, seed=0, clean=clean)
    assert estimate_noise(img) == pytest.approx(1 / np.sqrt(12))
    # A float image rounds to its floating-point spacing: tiny, never zero.
    as_float = img.astype(np.float32)
    assert estimate_noise(as_float) == pytest.approx(np.spacing(np.float32(as_float.max())) / np.sqrt(12))
    assert 0 < estimate_noise(img.astype(float)) < 1e-12


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_measure_stereo_on_a_noise_free_render(dtype):
    # In floats the render has no noise at all: its points' uncertainty is
    # the floating-point rounding's, and the chain measures without a
    # division by zero (it failed inside an eigendecomposition).
    from tests.vision import stereo_scenes as S
    from partinspect.vision.stereo import measure_stereo
    rig, _, L, R = S.render("plate", 0.0, 0, False, (612, 512))
    res = measure_stereo(L.astype(dtype), R.astype(dtype), rig)
    assert len(res.features) >= 10
    assert all(np.isfinite(f.param_cov).all() for f in res.features)


# ------------------------------------------------------------ noise level function


def _shaded(h=300, w=400):
    """Grey levels 30..230 in broad steps and ramps: every grey level has flat area."""
    y, x = np.mgrid[0:h, 0:w].astype(float)
    return 30.0 + 200.0 * np.floor(x / 50.0) / 7.0 + 0.05 * (y - h / 2)


def test_noise_level_constant_noise_stays_one_number():
    from partinspect.vision.noise import noise_level_function

    rng = np.random.default_rng(7)
    img = np.clip(np.rint(_shaded() + rng.normal(0, 2.0, (300, 400))), 0, 255).astype(np.uint8)
    level = noise_level_function(img)
    assert not level.signal_dependent
    assert level.std(200.0) == pytest.approx(estimate_noise(img))


@pytest.mark.parametrize("gain,read", [(0.1, 1.0), (0.3, 0.5)])
def test_noise_level_recovers_photon_noise(gain, read):
    # Poisson-Gaussian (Foi et al. 2008): var = gain * I + read^2 (+ 1/12 of rounding).
    from partinspect.vision.noise import noise_level_function

    clean = _shaded()
    rng = np.random.default_rng(8)
    var = gain * clean + read ** 2
    img = np.clip(np.rint(clean + rng.standard_normal(clean.shape) * np.sqrt(var)), 0, 255).astype(np.uint8)
    level = noise_level_function(img)
    assert level.signal_dependent
    for grey in (40.0, 120.0, 220.0):
        truth = np.sqrt(gain * grey + read ** 2 + 1.0 / 12.0)
        assert level.std(grey) == pytest.approx(truth, rel=0.12), grey


def test_noise_level_reads_pixel_response_non_uniformity():
    # A 1 % gain pattern acts on one image as noise proportional to the grey level.
    from partinspect.vision.noise import noise_level_function

    clean = _shaded()
    rng = np.random.default_rng(9)
    img = clean * (1.0 + 0.01 * rng.standard_normal(clean.shape)) + 0.5 * rng.standard_normal(clean.shape)
    level = noise_level_function(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    assert level.signal_dependent
    assert level.std(220.0) == pytest.approx(np.sqrt((0.01 * 220) ** 2 + 0.25 + 1 / 12), rel=0.12)
    assert level.std(40.0) == pytest.approx(np.sqrt((0.01 * 40) ** 2 + 0.25 + 1 / 12), rel=0.2)


def test_edge_points_follow_the_noise_at_their_grey_level():
    # Two straight steps, one dark (20 -> 60) and one bright (180 -> 240), under
    # photon noise: the points' stated std must follow each edge's own noise,
    # which a single image-wide figure cannot (it is between the two).
    from partinspect.vision.edges import edge_points
    from partinspect.vision.noise import noise_level_function
    from scipy.ndimage import gaussian_filter

    h, w = 120, 200
    x = np.arange(w)[None, :] * np.ones((h, 1))
    clean = np.where(x < 50.3, 20.0, 60.0)
    clean = np.where(x >= 100, np.where(x < 150.3, 180.0, 240.0), clean)
    clean = gaussian_filter(clean, 0.8)
    rng = np.random.default_rng(10)
    found = {50: [], 150: []}
    stated = {50: [], 150: []}
    for _ in range(12):
        img = np.clip(np.rint(clean + rng.standard_normal(clean.shape) * np.sqrt(0.4 * clean + 0.5)), 0, 255)
        img = img.astype(np.uint8)
        e = edge_points(img, 1.0, noise_level=noise_level_function(img))
        for c in found:
            sel = (np.abs(e.xy[:, 0] - c) < 3) & (e.xy[:, 1] > 10) & (e.xy[:, 1] < h - 10)
            found[c].append(e.xy[sel, 0] - np.median(e.xy[sel, 0]))
            stated[c].append(e.normal_std[sel])
    for c in found:
        empirical = np.std(np.concatenate(found[c]))
        assert np.sqrt(np.mean(np.concatenate(stated[c]) ** 2)) == pytest.approx(empirical, rel=0.15), c
