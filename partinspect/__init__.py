"""partinspect: inspect machined parts against their CAD model from a calibrated stereo pair.

Every measured number carries a standard uncertainty propagated from the image
pixels to the 3D result; pass/fail decisions follow ISO 14253-1.
"""

__version__ = "0.1.0"
