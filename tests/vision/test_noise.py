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
    assert estimate_noise(img.astype(float)) < 0.05  # a float image has no rounding


def test_measure_stereo_on_a_noise_free_render():
    from tests.vision import stereo_scenes as S
    from partinspect.vision.stereo import measure_stereo
    rig, _, L, R = S.render("plate", 0.0, 0, False, (612, 512))
    res = measure_stereo(L, R, rig)
    assert len(res.features) >= 10
    assert all(np.isfinite(f.param_cov).all() for f in res.features)
