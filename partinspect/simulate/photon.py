"""A photon-counting sensor: Poisson-Gaussian noise, full well, gain, vignetting.

The constant-sigma model of :func:`partinspect.simulate.render.sensor` makes
every grey level equally noisy; a real sensor's noise grows with the light.
This is the linear camera model of EMVA 1288: a pixel's mean grey ``g``
(DN, the noiseless render on the 8-bit scale) comes from ``g / K`` electrons
on average, ``K`` the overall system gain in DN per electron; the electrons
are Poisson-distributed, capped at the full-well capacity (saturation), the
read-out adds Gaussian noise of ``read`` electrons, and the result is
``K`` times the charge, rounded and clipped to 8 bits. The temporal
variance then follows the photon transfer line

    var(DN) = K * g + K**2 * read**2 + 1/12,

the quantisation's 1/12 included. Dark signal, fixed-pattern noise
(DSNU/PRNU) and non-linearity are left out: they are calibrated away on a
real rig or small on one of its kind.

Vignetting is the natural cos^4 fall-off of a thin lens's image-plane
irradiance with the angle ``theta`` of a pixel's chief ray to the optical
axis, ``E(theta) = E(0) cos^4(theta)``, applied to the radiance before the
electrons are counted (so the noise of a darker corner is that of a darker
pixel).

References
----------
.. [1] EMVA Standard 1288, Release 4.0 (2021): standard for
       characterization of image sensors and cameras, sec. 2 (the linear
       camera model and the photon transfer method).
.. [2] Foi, A., Trimeche, M., Katkovnik, V., Egiazarian, K. (2008).
       Practical Poissonian-Gaussian noise modeling and fitting for
       single-image raw-data. IEEE Trans. Image Process. 17(10), 1737-1754.
.. [3] Smith, W. J. *Modern Optical Engineering*, 4th ed., sec. 6.3 (the
       cos^4 law of illumination). McGraw-Hill, 2008.
"""

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["PhotonSensor", "parse_photon", "cos4_vignetting", "photon_sensor"]


@dataclass(frozen=True)
class PhotonSensor:
    """A linear camera of EMVA 1288.

    Attributes
    ----------
    full_well : float
        Saturation capacity, electrons.
    gain : float
        Overall system gain K, DN per electron (8-bit DN).
    read_noise : float
        Standard deviation of the read-out noise, electrons.
    """

    full_well: float
    gain: float
    read_noise: float

    def to_dict(self):
        d = asdict(self)
        d.update(units={"full_well": "e-", "gain": "DN/e-", "read_noise": "e-"},
                 model="EMVA 1288 linear camera: electrons ~ Poisson(g / gain) capped at full_well, "
                       "+ N(0, read_noise^2) e-, DN = clip(round(gain * e-), 0, 255); "
                       "var(DN) = gain * g + gain^2 read_noise^2 + 1/12",
                 vignetting="cos^4 of the chief ray's angle to the optical axis, applied before the noise")
        return d


def parse_photon(text):
    """``FULL_WELL,GAIN,READ`` (electrons, DN per electron, electrons) as a :class:`PhotonSensor`.

    Raises
    ------
    ValueError
        Not three numbers, or a full well or gain not > 0, or a read noise < 0.
    """
    try:
        full_well, gain, read = (float(v) for v in str(text).split(","))
    except ValueError:
        raise ValueError(f"expected FULL_WELL,GAIN,READ (e-, DN/e-, e-), got {text!r}") from None
    if not (full_well > 0 and gain > 0 and read >= 0) or not np.isfinite([full_well, gain, read]).all():
        raise ValueError(f"full well and gain must be > 0 and read noise >= 0, got {text!r}")
    return PhotonSensor(full_well, gain, read)


def cos4_vignetting(K, D, image_size):
    """Relative irradiance ``cos^4(theta)`` at every pixel centre.

    Parameters
    ----------
    K : ndarray, shape (3, 3)
    D : array_like
        OpenCV distortion vector; the chief ray's angle is that of the
        undistorted direction.
    image_size : (width, height)

    Returns
    -------
    ndarray of float64, shape (height, width)
        1 on the optical axis, less off it.
    """
    from partinspect.vision.calibration import undistort_points

    w, h = (int(s) for s in image_size)
    v, u = np.mgrid[0:h, 0:w]
    xn = undistort_points(np.stack([u.ravel(), v.ravel()], axis=1).astype(float), K, D)
    # cos(theta) = 1 / sqrt(1 + x^2 + y^2) for the direction (x, y, 1)
    return (1.0 / (1.0 + np.einsum("ij,ij->i", xn, xn)) ** 2).reshape(h, w)


def photon_sensor(image, photon, rng, vignetting=None):
    """Count electrons, add read noise and quantise to 8 bits.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Noiseless grey levels (DN) the sensor would read without noise at
        the image centre.
    photon : PhotonSensor
    rng : numpy.random.Generator
    vignetting : ndarray, shape (H, W), optional
        Relative irradiance (:func:`cos4_vignetting`); multiplies ``image``.

    Returns
    -------
    ndarray of uint8, shape (H, W)
    """
    mean = np.asarray(image, dtype=np.float64)
    if vignetting is not None:
        mean = mean * vignetting
    electrons = rng.poisson(np.maximum(mean, 0.0) / photon.gain).astype(np.float64)
    electrons = np.minimum(electrons, photon.full_well)
    if photon.read_noise > 0:
        electrons += photon.read_noise * rng.standard_normal(mean.shape)
    return np.clip(np.rint(photon.gain * electrons), 0, 255).astype(np.uint8)
