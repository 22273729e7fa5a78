"""Reading the stereo image pair: 8- or 16-bit, grey or colour, checked."""

from pathlib import Path

import numpy as np

from partinspect.errors import InputError
from partinspect.vision.calibration import check_image_size

IMAGE_NAMES = ("left.png", "right.png")


def read_image(path):
    """Read one image as grey levels.

    Parameters
    ----------
    path : str or Path
        PNG (or any format OpenCV reads), 8- or 16-bit, grey or colour
        (colour is converted with ITU-R BT.601 luma weights, alpha dropped).

    Returns
    -------
    image : ndarray, shape (H, W), uint8 or uint16
        Grey levels in the file's own scale (0-255 or 0-65535), integers as
        recorded: the noise estimate needs to know they were rounded (an
        integer image's pixels carry at least the rounding error, so even a
        noise-free one has a noise, and its top value is saturation).
    bit_depth : int
        8 or 16.

    Raises
    ------
    InputError
        Missing, empty or unreadable file, unsupported depth, or an image
        with no contrast at all (all black, all saturated, uniform).
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "image not found" if not path.exists() else "not a regular file")
    if path.stat().st_size == 0:
        raise InputError(path, "image file is empty")
    data = np.fromfile(path, dtype=np.uint8)  # np.fromfile + imdecode copes with non-ASCII paths
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "not a readable image (corrupt or truncated?)")
    if img.dtype == np.uint8:
        depth = 8
    elif img.dtype == np.uint16:
        depth = 16
    else:
        raise InputError(path, f"unsupported pixel type {img.dtype}; expected 8- or 16-bit")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[:, :, :3]
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.shape[2] == 3 else img[:, :, 0]
    lo, hi = float(img.min()), float(img.max())
    if hi == lo:
        what = "all black" if hi == 0 else "saturated" if hi == 2**depth - 1 else "uniform"
        raise InputError(path, f"image is {what} (every pixel is {hi:g}): nothing can be measured")
    return img, depth


def read_pair(images_dir, calib=None):
    """Read ``left.png`` and ``right.png`` from a folder and check their sizes.

    Parameters
    ----------
    images_dir : str or Path
    calib : StereoCalibration, optional
        When given, both images must have its image size.

    Returns
    -------
    left, right : ndarray, shape (H, W), uint8 or uint16 (see :func:`read_image`)
    bit_depth : int
    """
    images_dir = Path(images_dir)
    if not images_dir.is_dir():
        raise InputError(images_dir, "images folder not found" if not images_dir.exists() else "not a folder")
    (left, d1), (right, d2) = (read_image(images_dir / n) for n in IMAGE_NAMES)
    if left.shape != right.shape:
        raise InputError(
            images_dir / IMAGE_NAMES[1],
            f"image is {right.shape[1]}x{right.shape[0]} pixels but left.png is {left.shape[1]}x{left.shape[0]}",
        )
    if d1 != d2:
        raise InputError(images_dir / IMAGE_NAMES[1], f"image is {d2}-bit but left.png is {d1}-bit")
    if calib is not None:
        check_image_size(calib, (left.shape[1], left.shape[0]), images_dir / IMAGE_NAMES[0])
    return left, right, d1
